"""Real orthonormal spherical harmonics: evaluation by a stable recurrence.

Conventions (see docs/sh-conventions.md):

* Directions are unit vectors in Blender's world frame, Z up:
  x = sin(theta) cos(phi), y = sin(theta) sin(phi), z = cos(theta).
* ``bands = n`` means degrees l = 0 .. n-1 and K = n**2 coefficients, indexed
  k = l**2 + l + m with -l <= m <= l.
* Real basis with the Condon-Shortley phase, as in Sloan's "Stupid SH Tricks":
  y(1,-1) = -0.4886 y, y(1,0) = 0.4886 z, y(1,1) = -0.4886 x.
  For m > 0: y_lm = sqrt(2) K_lm P_l^m(z) cos(m phi); for m < 0:
  y_lm = sqrt(2) K_l|m| P_l^|m|(z) sin(|m| phi); y_l0 = K_l0 P_l(z), where P_l^m
  carries the (-1)^m phase and K_lm = sqrt((2l+1)/(4 pi) (l-m)!/(l+m)!).

The recurrence never divides by sin(theta): it runs on the polynomial
Pbar_l^m(z) = K_lm P_l^m(z) / sin^m(theta) and multiplies by
Re/Im (x + i y)^m = sin^m(theta) (cos, sin)(m phi), so the poles are exact and
there is no trigonometry at all. The fully normalised three-term recurrence
keeps every intermediate of order one, so it is stable for any band count.

float32 path: with ``dtype=np.float32`` the same recurrence runs in float32 (as
the viewport shader does). Its error grows with the square of the band count;
the documented bound, asserted by tests/test_basis.py for bands <= 16 on the
same float32 input directions, is
    max |y32 - y64| <= float32_error_bound(bands) = 4e-8 * bands**2
(measured: 5.5e-8 at 2 bands, 4.2e-7 at 5, 1.3e-6 at 8, 6.4e-6 at 16, where
max |y| is 0.49, 0.85, 1.09, 1.57).
"""
from __future__ import annotations

import math

import numpy as np

#: float32 path: |y32 - y64| <= FLOAT32_ERROR_COEFF * bands**2 (absolute, any
#: unit float32 direction, bands <= 16); the measured maximum is ~0.6 of it.
FLOAT32_ERROR_COEFF = 4e-8

#: A direction whose length differs from 1 by more than this is rejected unless
#: the caller asks for normalisation. float32 unit vectors are within ~1e-7.
UNIT_TOLERANCE = 1e-5

#: Shorter vectors carry no direction; they are rejected even with normalize=True.
MIN_LENGTH = 1e-12


def float32_error_bound(bands: int) -> float:
    """Documented max |eval_basis(float32) - eval_basis(float64)| for ``bands``."""
    return FLOAT32_ERROR_COEFF * check_bands(bands) ** 2


def n_coeffs(bands: int) -> int:
    """Number of coefficients K = bands**2 for ``bands`` SH bands."""
    return check_bands(bands) ** 2


def sh_index(l: int, m: int) -> int:
    """Flat coefficient index k = l**2 + l + m."""
    if not -l <= m <= l:
        raise ValueError(f"m={m} outside -l..l for l={l}")
    return l * l + l + m


def lm_of(k: int) -> tuple[int, int]:
    """Inverse of :func:`sh_index`: the (l, m) of coefficient k."""
    if k < 0:
        raise ValueError(f"coefficient index must be >= 0, got {k}")
    l = math.isqrt(k)
    return l, k - l * l - l


def band_of_coeffs(bands: int) -> np.ndarray:
    """(K,) int array: the degree l of every coefficient."""
    n = check_bands(bands)
    return np.repeat(np.arange(n), 2 * np.arange(n) + 1)


def check_bands(bands) -> int:
    """Validate a band count: an integer >= 1. Returns it as int."""
    if isinstance(bands, bool) or not isinstance(bands, (int, np.integer)):
        raise TypeError(f"bands must be an integer >= 1, got {bands!r}")
    if bands < 1:
        raise ValueError(f"bands must be >= 1, got {bands}")
    return int(bands)


def bands_of(n_coefficients: int) -> int:
    """Band count for a coefficient vector of length K (K must be a square)."""
    n = math.isqrt(int(n_coefficients))
    if n < 1 or n * n != n_coefficients:
        raise ValueError(
            f"an SH vector has bands**2 coefficients; {n_coefficients} is not a square"
        )
    return n


def as_directions(dirs, *, normalize: bool = False, dtype=np.float64,
                  name: str = "dirs") -> np.ndarray:
    """Validate directions and return them as a C-contiguous (N, 3) array.

    Accepts (N, 3) or (3,). Rejects non-finite values and vectors shorter than
    MIN_LENGTH. Unit length is required within UNIT_TOLERANCE unless
    ``normalize`` is true, in which case vectors are normalised in float64.
    """
    a = np.asarray(dirs)
    if a.dtype.kind not in "fiu":
        raise TypeError(f"{name} must be a real numeric array, got dtype {a.dtype}")
    if a.ndim == 1:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3) or (3,), got {np.shape(dirs)}")
    a64 = a.astype(np.float64, copy=False)
    if not np.all(np.isfinite(a64)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(a64), axis=1))[0])
        raise ValueError(f"{name}[{bad}] is not finite: {a64[bad].tolist()}")
    length = np.sqrt(np.einsum("ij,ij->i", a64, a64))
    if a64.shape[0] and length.min() < MIN_LENGTH:
        bad = int(np.argmin(length))
        raise ValueError(
            f"{name}[{bad}] has length {length[bad]:.3g}: a zero vector has no direction"
        )
    if normalize:
        a64 = a64 / length[:, None]
    elif a64.shape[0]:
        dev = np.abs(length - 1.0)
        if dev.max() > UNIT_TOLERANCE:
            bad = int(np.argmax(dev))
            raise ValueError(
                f"{name}[{bad}] has length {length[bad]:.9g}, not 1 "
                f"(tolerance {UNIT_TOLERANCE:g}); pass normalize=True to normalise"
            )
    return np.ascontiguousarray(a64, dtype=dtype)


def sectoral_constants(n: int) -> np.ndarray:
    """Pbar_m^m for m = 0..n-1 (they do not depend on z), float64."""
    c = np.empty(n)
    c[0] = math.sqrt(1.0 / (4.0 * math.pi))
    for m in range(1, n):
        c[m] = -math.sqrt((2 * m + 1) / (2.0 * m)) * c[m - 1]
    return c


def eval_basis(dirs, bands: int, *, dtype=np.float64, normalize: bool = False) -> np.ndarray:
    """Evaluate all real SH of ``bands`` bands at unit directions.

    Parameters
    ----------
    dirs : (N, 3) or (3,) array of unit vectors (Z up).
    bands : number of bands n >= 1; K = n**2 outputs, index k = l**2 + l + m.
    dtype : np.float64 (reference path) or np.float32 (same recurrence in float32).
    normalize : normalise non-unit vectors instead of rejecting them.

    Returns
    -------
    (N, K) array (or (K,) for a single direction) of ``dtype``.
    """
    n = check_bands(bands)
    dtype = np.dtype(dtype)
    if dtype not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise TypeError(f"dtype must be float32 or float64, got {dtype}")
    single = np.ndim(dirs) == 1
    d = as_directions(dirs, normalize=normalize, dtype=dtype)
    out = basis_unchecked(d, n, dtype)
    return out[0] if single else out


def basis_unchecked(d: np.ndarray, n: int, dtype=np.float64, *, coeff_major: bool = False) -> np.ndarray:
    """The recurrence of :func:`eval_basis` without input checks, for hot loops
    whose directions are unit by construction. d (N, 3) of ``dtype``, or the
    tuple of its three columns (x, y, z), each (N,).

    Returns (N, K); with ``coeff_major`` (K, N). The recurrence always fills
    coefficient rows (contiguous writes); the (N, K) result is their transposed
    copy, which with it is ~4x faster than writing strided columns."""
    dtype = np.dtype(dtype)
    x, y, z = d if isinstance(d, tuple) else (d[:, 0], d[:, 1], d[:, 2])
    N = x.shape[0]
    out = np.empty((n * n, N), dtype=dtype)
    sect = sectoral_constants(n).astype(dtype)
    sqrt2 = dtype.type(math.sqrt(2.0))
    cm = np.ones_like(x)   # Re (x + i y)^m
    sm = np.zeros_like(x)  # Im (x + i y)^m
    for m in range(n):
        if m > 0:
            cm, sm = x * cm - y * sm, x * sm + y * cm
        # Pbar_l^m for l = m, m+1, ... by the normalised three-term recurrence.
        p_prev = np.full_like(x, sect[m])                     # l = m
        p_cur = None
        for l in range(m, n):
            if l == m:
                p = p_prev
            elif l == m + 1:
                p_cur = dtype.type(math.sqrt(2 * m + 3)) * z * p_prev
                p = p_cur
            else:
                a = dtype.type(math.sqrt((4.0 * l * l - 1.0) / (l * l - m * m)))
                b = dtype.type(math.sqrt(((l - 1.0) ** 2 - m * m) / (4.0 * (l - 1.0) ** 2 - 1.0)))
                p = a * (z * p_cur - b * p_prev)
                p_prev, p_cur = p_cur, p
            if m == 0:
                out[l * l + l] = p
            else:
                np.multiply(sqrt2 * p, cm, out=out[l * l + l + m])
                np.multiply(sqrt2 * p, sm, out=out[l * l + l - m])
    return out if coeff_major else np.ascontiguousarray(out.T)
