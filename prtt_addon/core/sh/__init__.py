"""Public SH API of PRTT: the names scripts, docs and tests rely on.

Conventions (docs/sh-conventions.md): real orthonormal SH, Z-up world,
Condon-Shortley phase as in Sloan's "Stupid SH Tricks", coefficient index
k = l**2 + l + m, ``bands = n`` -> K = n**2 coefficients.

* :func:`eval_basis` (dirs (N, 3), bands) -> (N, K)
* :func:`triple_product_tensor` (bands) -> (K, K, K) Gaunt tensor
* :func:`tpfl_matrix` (light (K,) or (K, 3), bands) -> (K, K) or (3, K, K)

The implementations live in small modules (basis, quadrature, gaunt, zonal,
rotation); this module re-exports them.
"""
from .basis import (
    FLOAT32_ERROR_COEFF,
    band_of_coeffs,
    bands_of,
    check_bands,
    eval_basis,
    float32_error_bound,
    lm_of,
    n_coeffs,
    sh_index,
)
from .gaunt import SparseGaunt, sparse_gaunt, tpfl_matrix, triple_product, triple_product_tensor
from .quadrature import gauss_sphere, project, project_function, reconstruct
from .rotation import rotate, rotate_zyz, rotation_zyz, sh_rotation
from .zonal import (
    clamped_cosine_factors,
    clamped_cosine_zh,
    convolve,
    phong_factors,
    power_cosine_integrals,
    window_factors,
    zonal_to_sh,
)

__all__ = [
    "FLOAT32_ERROR_COEFF", "band_of_coeffs", "bands_of", "check_bands", "eval_basis", "float32_error_bound", "lm_of",
    "n_coeffs", "sh_index",
    "SparseGaunt", "sparse_gaunt", "tpfl_matrix", "triple_product", "triple_product_tensor",
    "gauss_sphere", "project", "project_function", "reconstruct",
    "rotate", "rotate_zyz", "rotation_zyz", "sh_rotation",
    "clamped_cosine_factors", "clamped_cosine_zh", "convolve", "phong_factors", "power_cosine_integrals",
    "window_factors", "zonal_to_sh",
]
