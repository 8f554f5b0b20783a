"""Spherical quadrature and SH projection of sampled functions.

``gauss_sphere(degree)`` is Gauss-Legendre in cos(theta) times uniform phi: it
integrates every polynomial of total degree <= ``degree`` on the unit sphere
exactly (up to float64 rounding). A product of two SH of bands n_a and n_b has
degree (n_a - 1) + (n_b - 1), so projecting a band-limited function needs
``degree >= (bands - 1) + (function band - 1)``.

Monte Carlo projection uses the same ``project`` with weights 1 / (N pdf).
"""
from __future__ import annotations

import functools
import math

import numpy as np

from .basis import bands_of, check_bands, eval_basis


@functools.lru_cache(maxsize=64)
def _gauss_sphere_cached(degree: int, phase: float):
    n_z = degree // 2 + 1          # exact for polynomials in z of degree 2 n_z - 1
    n_phi = degree + 1             # exact for trigonometric degree <= degree
    z, wz = np.polynomial.legendre.leggauss(n_z)
    phi = (np.arange(n_phi) + phase) * (2.0 * math.pi / n_phi)
    s = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    dirs = np.empty((n_z, n_phi, 3))
    dirs[..., 0] = s[:, None] * np.cos(phi)[None, :]
    dirs[..., 1] = s[:, None] * np.sin(phi)[None, :]
    dirs[..., 2] = z[:, None]
    w = np.repeat(wz * (2.0 * math.pi / n_phi), n_phi)
    dirs = dirs.reshape(-1, 3)
    dirs.setflags(write=False)
    w.setflags(write=False)
    return dirs, w


def gauss_sphere(degree: int, *, phase: float = 0.5):
    """Quadrature exact for spherical polynomials of total degree <= ``degree``.

    Returns ``(dirs (Q, 3) float64 unit vectors, weights (Q,) float64)`` with
    sum(weights) = 4 pi. ``phase`` offsets the phi grid by that fraction of a
    step (0.5 keeps nodes off the x-z plane). Arrays are read-only (cached).
    """
    if isinstance(degree, bool) or not isinstance(degree, (int, np.integer)) or degree < 0:
        raise ValueError(f"quadrature degree must be an integer >= 0, got {degree!r}")
    return _gauss_sphere_cached(int(degree), float(phase))


def project(values, dirs, weights, bands: int) -> np.ndarray:
    """SH coefficients  c_k = sum_q w_q f(d_q) y_k(d_q).

    values : (Q,) or (Q, C) samples of f at ``dirs`` (Q, 3).
    weights : (Q,) quadrature or Monte Carlo weights (1 / (Q pdf)).
    Returns (K,) or (K, C) float64.
    """
    n = check_bands(bands)
    f = np.asarray(values, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    d = np.asarray(dirs)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"dirs must have shape (Q, 3), got {d.shape}")
    if f.shape[:1] != d.shape[:1] or w.shape != d.shape[:1]:
        raise ValueError(
            f"values {f.shape}, dirs {d.shape} and weights {w.shape} disagree on Q"
        )
    y = eval_basis(d, n)
    if f.ndim == 1:
        return y.T @ (w * f)
    return y.T @ (w[:, None] * f.reshape(f.shape[0], -1))


def project_function(func, bands: int, *, degree: int | None = None) -> np.ndarray:
    """Exact SH projection of a callable f(dirs (Q, 3)) -> (Q,) or (Q, C).

    Exact when f is a polynomial of degree <= degree - (bands - 1); the default
    ``degree`` is 2 (bands - 1) + 16, ample for smooth f of modest band.
    """
    n = check_bands(bands)
    if degree is None:
        degree = 2 * (n - 1) + 16
    d, w = gauss_sphere(degree)
    return project(func(d), d, w, n)


def reconstruct(coeffs, dirs) -> np.ndarray:
    """Evaluate f(d) = sum_k c_k y_k(d). coeffs (K,) or (K, C); dirs (N, 3)."""
    c = np.asarray(coeffs, dtype=np.float64)
    n = bands_of(c.shape[0])
    return eval_basis(dirs, n) @ c
