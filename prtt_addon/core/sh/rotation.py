"""Rotation of real SH coefficient vectors.

Rotating a function by a 3x3 rotation R means g(w) = f(R^T w). Its coefficients
are g = D(R) f, with D block-diagonal (one (2l+1)^2 block per band).

Two paths, cross-checked against each other and against quadrature in the tests:

* :func:`sh_rotation` builds D(R) for any rotation (or a batch of them) with
  the Ivanic-Ruedenberg recurrence (J. Phys. Chem. 1996, 100, 6342 and the
  1998 erratum). No Euler angles, so no gimbal singularities. Used for turning
  the environment (the World's Mapping node rotation).
* :func:`rotate_zyz` applies D(Rz(a) Ry(b) Rz(g)) to a batch of vectors without
  forming matrices: z-rotations are 2x2 mixes of (m, -m) pairs, and
  Ry(b) = Rx(-90) Rz(b) Rx(90) uses one fixed matrix X = D(Rx(90)). This is
  the bake's hot path (a tangent frame per texel, built from these angles).

Coefficient order k = l^2 + l + m, Condon-Shortley phase (see basis.py).
"""
from __future__ import annotations

import functools
import math

import numpy as np

from .basis import bands_of, check_bands


def _check_rotation(R) -> np.ndarray:
    a = np.asarray(R, dtype=np.float64)
    if a.shape[-2:] != (3, 3):
        raise ValueError(f"rotation must have shape (..., 3, 3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError("rotation matrix contains NaN or Inf")
    eye_err = np.abs(np.einsum("...ji,...jk->...ik", a, a) - np.eye(3)).max(initial=0.0)
    if eye_err > 1e-6:
        raise ValueError(f"matrix is not orthonormal (|R^T R - I| = {eye_err:.3g})")
    det = np.linalg.det(a)
    if np.any(det < 0):
        raise ValueError("matrix is a reflection (det = -1), not a rotation")
    return a


def _ivanic_blocks(R: np.ndarray, n: int) -> list[np.ndarray]:
    """Per-band blocks (B, 2l+1, 2l+1) in the real basis *without* CS phase."""
    B = R.shape[0]
    # Band 1 in the order (m=-1, 0, 1) ~ (y, z, x).
    perm = [1, 2, 0]
    r1 = R[:, perm][:, :, perm]
    blocks = [np.ones((B, 1, 1)), r1]
    for l in range(2, n):
        prev = blocks[-1]

        def P(i, a, b, l=l, prev=prev):
            ri = r1[:, i + 1]
            if b == l:
                return ri[:, 2] * prev[:, a + l - 1, 2 * l - 2] - ri[:, 0] * prev[:, a + l - 1, 0]
            if b == -l:
                return ri[:, 2] * prev[:, a + l - 1, 0] + ri[:, 0] * prev[:, a + l - 1, 2 * l - 2]
            return ri[:, 1] * prev[:, a + l - 1, b + l - 1]

        M = np.zeros((B, 2 * l + 1, 2 * l + 1))
        for m in range(-l, l + 1):
            am = abs(m)
            d = 1.0 if m == 0 else 0.0
            for nn in range(-l, l + 1):
                denom = (2.0 * l) * (2 * l - 1) if abs(nn) == l else float((l + nn) * (l - nn))
                u = math.sqrt((l + m) * (l - m) / denom)
                v = 0.5 * math.sqrt((1 + d) * (l + am - 1) * (l + am) / denom) * (1 - 2 * d)
                w = -0.5 * math.sqrt(max(0, (l - am - 1) * (l - am)) / denom) * (1 - d)
                val = np.zeros(B)
                if u != 0.0:
                    val = val + u * P(0, m, nn)
                if v != 0.0:
                    if m == 0:
                        V = P(1, 1, nn) + P(-1, -1, nn)
                    elif m > 0:
                        V = P(1, m - 1, nn) * math.sqrt(1 + (m == 1))
                        if m != 1:
                            V = V - P(-1, -m + 1, nn)
                    else:
                        V = P(-1, -m - 1, nn) * math.sqrt(1 + (m == -1))
                        if m != -1:
                            V = V + P(1, m + 1, nn)
                    val = val + v * V
                if w != 0.0:
                    if m > 0:
                        W = P(1, m + 1, nn) + P(-1, -m - 1, nn)
                    else:
                        W = P(1, m - 1, nn) - P(-1, -m + 1, nn)
                    val = val + w * W
                M[:, m + l, nn + l] = val
        blocks.append(M)
    return blocks[:n]


def sh_rotation(R, bands: int) -> np.ndarray:
    """Block-diagonal SH rotation matrix D(R): g = D @ f for g(w) = f(R^T w).

    R : (3, 3) or (B, 3, 3) proper rotation(s), float64.
    Returns (K, K) or (B, K, K) float64, K = bands**2.
    """
    n = check_bands(bands)
    a = _check_rotation(R)
    single = a.ndim == 2
    a = a.reshape(-1, 3, 3)
    blocks = _ivanic_blocks(a, n)
    K = n * n
    D = np.zeros((a.shape[0], K, K))
    for l, blk in enumerate(blocks):
        s = (-1.0) ** np.abs(np.arange(-l, l + 1))     # Condon-Shortley signs
        lo = l * l
        D[:, lo:lo + 2 * l + 1, lo:lo + 2 * l + 1] = blk * s[:, None] * s[None, :]
    return D[0] if single else D


def rotate(coeffs, R, *, axis: int = 0) -> np.ndarray:
    """Rotate SH coefficients (K along ``axis``) by one rotation R (3, 3)."""
    c = np.asarray(coeffs, dtype=np.float64)
    n = bands_of(c.shape[axis])
    D = sh_rotation(R, n)
    return np.moveaxis(np.tensordot(D, np.moveaxis(c, axis, 0), axes=(1, 0)), 0, axis)


def rotation_zyz(alpha, beta, gamma) -> np.ndarray:
    """3x3 matrices Rz(alpha) Ry(beta) Rz(gamma) for arrays of angles (radians).

    Returns shape (..., 3, 3). Column 2 is (cos a sin b, sin a sin b, cos b),
    so a frame with normal n has beta = acos(n_z), alpha = atan2(n_y, n_x).
    """
    a, b, g = np.broadcast_arrays(*(np.asarray(t, dtype=np.float64) for t in (alpha, beta, gamma)))
    ca, sa, cb, sb, cg, sg = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(g), np.sin(g)
    R = np.empty(a.shape + (3, 3))
    R[..., 0, 0] = ca * cb * cg - sa * sg
    R[..., 0, 1] = -ca * cb * sg - sa * cg
    R[..., 0, 2] = ca * sb
    R[..., 1, 0] = sa * cb * cg + ca * sg
    R[..., 1, 1] = -sa * cb * sg + ca * cg
    R[..., 1, 2] = sa * sb
    R[..., 2, 0] = -sb * cg
    R[..., 2, 1] = sb * sg
    R[..., 2, 2] = cb
    return R


@functools.lru_cache(maxsize=32)
def _x90(n: int, dtype: str) -> np.ndarray:
    c, s = 0.0, 1.0
    rx = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    X = sh_rotation(rx, n).astype(dtype)
    X.setflags(write=False)
    return X


@functools.lru_cache(maxsize=32)
def _zrot_tables(n: int):
    """Per coefficient: |m|, the index of its (l, -m) partner, and the sign that
    turns sin(|m| t) into its contribution (so z-rotation is 3 array ops)."""
    K = n * n
    absm = np.empty(K, np.int64)
    partner = np.empty(K, np.int64)
    sign = np.empty(K)
    for l in range(n):
        for m in range(-l, l + 1):
            k = l * l + l + m
            absm[k] = abs(m)
            partner[k] = l * l + l - m
            sign[k] = -1.0 if m > 0 else (1.0 if m < 0 else 0.0)
    return absm, partner, sign


def _multiples(t, n: int, dtype) -> tuple[np.ndarray, np.ndarray]:
    """cos(m t), sin(m t) for m = 0..n-1 as (B, n) arrays, by the angle-addition
    recurrence (two trig calls per angle instead of 2n)."""
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    c1, s1 = np.cos(t), np.sin(t)
    C = np.empty((t.size, n))
    S = np.empty((t.size, n))
    C[:, 0], S[:, 0] = 1.0, 0.0
    for m in range(1, n):
        C[:, m] = C[:, m - 1] * c1 - S[:, m - 1] * s1
        S[:, m] = S[:, m - 1] * c1 + C[:, m - 1] * s1
    return C.astype(dtype, copy=False), S.astype(dtype, copy=False)


def _zrot(c: np.ndarray, t: np.ndarray, n: int) -> np.ndarray:
    """c (B, K) rotated about +Z by angles t (B,): for m > 0
    c'_m = c_m cos(mt) - c_-m sin(mt), c'_-m = c_-m cos(mt) + c_m sin(mt)."""
    absm, partner, sign = _zrot_tables(n)
    C, S = _multiples(t, n, c.dtype)
    return c * C[:, absm] + c[:, partner] * (S[:, absm] * sign.astype(c.dtype))


def rotate_zyz(coeffs, alpha, beta, gamma) -> np.ndarray:
    """Batched D(Rz(alpha) Ry(beta) Rz(gamma)) @ c without building matrices.

    coeffs : (B, K) float32 or float64; alpha, beta, gamma : (B,) radians.
    Returns a new (B, K) array of the same dtype (15 array operations in all,
    so it stays cheap and mostly outside the GIL for large batches).
    """
    c = np.asarray(coeffs)
    if c.ndim != 2:
        raise ValueError(f"coeffs must have shape (B, K), got {c.shape}")
    if c.dtype not in (np.float32, np.float64):
        c = c.astype(np.float64)
    n = bands_of(c.shape[1])
    if n == 1:
        return c
    X = _x90(n, c.dtype.str)
    c = _zrot(c, gamma, n) @ X.T
    c = _zrot(c, beta, n) @ X
    return _zrot(c, alpha, n)
