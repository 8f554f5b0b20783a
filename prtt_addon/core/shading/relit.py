"""Relightable bounce light shown under a light (bounce_mode "relightable";
the operator is baked by core/bake/estimators/relightable.py, docs/shading.md).

B(p)_c,o = sum_i R(p)_c,o,i L_c,i: the DC row over every light coefficient,
the glossy rows (out 1 .. Kg - 1) over the first Kg. Linear in the light.
"""
from __future__ import annotations

import numpy as np


def apply_light(dc: np.ndarray, glossy: np.ndarray | None, light: np.ndarray, bands: int) -> np.ndarray:
    """The bounce light under ``light`` (K, 3): (..., 3, K) float32 from ``dc``
    (..., 3, K) and ``glossy`` (..., 3, Kg - 1, Kg); coefficients the operator
    does not hold are zero. Linear in the light."""
    K = bands * bands
    L = np.asarray(light, np.float32)[:K].T                                        # (3, K)
    out = np.zeros(dc.shape[:-2] + (3, K), np.float32)
    n = min(K, dc.shape[-1])
    out[..., 0] = np.einsum("...ci,ci->...c", dc[..., :n], L[:, :n])
    if glossy is not None:
        kg = glossy.shape[-1]
        out[..., 1:kg] = np.einsum("...coi,ci->...co", glossy, L[:, :kg])
    return out
