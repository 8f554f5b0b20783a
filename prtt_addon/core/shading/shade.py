"""The reference shading model (numpy): what the viewport shader must match.

Conventions (docs/shading.md):

* ``view`` is the unit vector from the surface point towards the eye; the
  reflection direction is r = 2 (n.v) n - v.
* Transfer T (K,) per point is the SH projection of V(w) max(0, n.w).
* The light L (K, 3) is the environment's RGB SH in world coordinates (after
  the World's rotation and strength).
* Transferred (cosine-weighted) incident radiance, per colour channel c:
      TPFL:  Lp_c = M(L_c) @ T          (M from gaunt.tpfl_matrix, O(K^2))
      TP:    Lp_c,k = sum_ij tau_ijk T_i L_c,j   (the Gaunt tensor, same result)
* Outgoing radiance towards the viewer (the cosine is already in Lp):
      diffuse  B_d = rho_d / pi * integral Lp = rho_d / pi * sqrt(4 pi) Lp_0
               (a constant lobe: evaluating "at the normal" or anywhere is the
               same, and it equals the double product rho_d / pi * T . L_c)
      glossy   B_s = k_s * sum_lm A_l(s) Lp_lm y_lm(r)
               (normalised Phong lobe of exponent s, zonal.phong_factors)
      B = max(0, B_d + B_s)       clamped: SH ringing can dip below zero.
* Inter-reflections: a bounce texture holds the extra cosine-weighted incident
  radiance (K, 3) from k bounces; it is added to Lp before the lobes (the
  model is linear, so this equals adding the shaded results).
* Optional ringing window on the light (zonal.window_factors), off by default.
"""
from __future__ import annotations

import math

import numpy as np

from ..sh.basis import band_of_coeffs, bands_of, basis_unchecked
from ..sh.gaunt import sparse_gaunt, tpfl_matrix
from ..sh.zonal import convolve, phong_factors, window_factors
from .materials import ShadingParams

SQRT_4PI = math.sqrt(4.0 * math.pi)


def prepare_light(light, bands: int, *, window: str | None = None) -> np.ndarray:
    """(K, 3) light truncated to ``bands`` and optionally windowed."""
    L = np.asarray(light, dtype=np.float64)
    if L.ndim != 2 or L.shape[1] != 3:
        raise ValueError(f"light must be (K, 3) RGB SH, got {L.shape}")
    if not np.all(np.isfinite(L)):
        raise ValueError("light has NaN/Inf coefficients")
    n_light = bands_of(L.shape[0])
    if n_light < bands:
        raise ValueError(f"light has {n_light} bands, shading needs {bands}")
    L = L[:bands * bands]
    if window:
        L = convolve(L, window_factors(bands, window))
    return L


def incident_tpfl(T: np.ndarray, light: np.ndarray, M: np.ndarray | None = None) -> np.ndarray:
    """Lp (N, 3, K) = M(L_c) @ T for each point, by the fixed-light matrix."""
    T = np.atleast_2d(np.asarray(T, dtype=np.float64))
    if M is None:
        M = tpfl_matrix(light, bands_of(T.shape[1]))        # (3, K, K), symmetric
    return np.einsum("cik,nk->nci", M, T)


def incident_tp(T: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Lp (N, 3, K) by the full triple product with the sparse Gaunt tensor."""
    T = np.atleast_2d(np.asarray(T, dtype=np.float64))
    L = np.asarray(light, dtype=np.float64)
    g = sparse_gaunt(bands_of(T.shape[1]))
    K = T.shape[1]
    out = np.zeros((T.shape[0], 3, K))
    for c in range(3):
        terms = T[:, g.i] * (g.value * L[g.j, c])[None, :]       # (N, nnz)
        for k in range(K):
            sel = g.k == k
            out[:, c, k] = terms[:, sel].sum(axis=1)
    return out


def reflect(view: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """r = 2 (n.v) n - v for unit view (towards the eye) and normal vectors."""
    d = np.einsum("nc,nc->n", view, normal)[:, None]
    return 2.0 * d * normal - view


def lobe_factors(exponent: np.ndarray, bands: int) -> np.ndarray:
    """(N, K) Phong convolution factor of every coefficient, computed once per
    distinct exponent (materials usually share a handful)."""
    u, inv = np.unique(np.asarray(exponent, dtype=np.float64), return_inverse=True)
    return phong_factors(u, bands)[:, band_of_coeffs(bands)][inv.reshape(-1)]


def outgoing(Lp: np.ndarray, normal: np.ndarray, view: np.ndarray, params: ShadingParams,
             *, clamp: bool = True) -> np.ndarray:
    """Radiance (N, 3) towards ``view`` from cosine-weighted incident radiance Lp (N, 3, K).

    Computed in Lp's precision: float64 for the reference, float32 for the
    bounce bake's hit shading (error ~1e-6 relative; tests/test_shading.py).
    """
    N, _, K = Lp.shape
    n = bands_of(K)
    dt = np.float32 if Lp.dtype == np.float32 else np.float64
    diffuse = (params.albedo * (SQRT_4PI / math.pi)).astype(dt) * Lp[:, :, 0]
    out = diffuse
    if np.any(params.spec):
        r = reflect(np.asarray(view, np.float64), np.asarray(normal, np.float64))
        r /= np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-300)
        Ay = lobe_factors(params.exponent, n).astype(dt) * basis_unchecked(r.astype(dt), n, dt)
        out = out + params.spec.astype(dt) * np.matmul(Lp, Ay[:, :, None])[:, :, 0]
    return np.maximum(out, 0.0) if clamp else out


def shade(T, normal, view, light, params: ShadingParams, *, bounces=(), method: str = "tpfl",
          window: str | None = None, clamp: bool = True) -> np.ndarray:
    """Outgoing radiance (N, 3) of points with transfer T (N, K).

    bounces : iterable of (N, 3, K) incident-radiance SH (bounce textures).
    method  : "tpfl" (default), "tp" (full triple product) or "diffuse" (the
              double-product fast path; ignores the glossy lobe).
    """
    T = np.atleast_2d(np.asarray(T, dtype=np.float64))
    n = bands_of(T.shape[1])
    L = prepare_light(light, n, window=window)
    if method == "diffuse":
        direct = params.albedo / math.pi * (T @ L)
        extra = sum((params.albedo / math.pi * SQRT_4PI * np.asarray(b)[:, :, 0] for b in bounces),
                    np.zeros_like(direct))
        out = direct + extra
        return np.maximum(out, 0.0) if clamp else out
    if method == "tpfl":
        Lp = incident_tpfl(T, L)
    elif method == "tp":
        Lp = incident_tp(T, L)
    else:
        raise ValueError(f"unknown shading method {method!r}; use tpfl, tp or diffuse")
    for b in bounces:
        Lp = Lp + np.asarray(b, dtype=np.float64)
    return outgoing(Lp, normal, view, params, clamp=clamp)


def sun_exponent(exponent, angle: float) -> np.ndarray:
    """The Phong exponent of a lobe of exponent ``exponent`` seen through a sun
    disc of full angle ``angle`` (radians): the lobe near its axis is a
    Gaussian of per-axis variance 1 / s, the uniform disc of radius a / 2 adds
    (a / 2)² / 4, so s' = 1 / (1 / s + a² / 16) (an exponent of 0 stays 0). A
    mirror's highlight of the sun is then the disc's width, not a point."""
    s = np.asarray(exponent, np.float64)
    widen = angle * angle / 16.0
    return np.where(s > 0.0, 1.0 / (1.0 / np.maximum(s, 1e-300) + widen), 0.0)


def sun_direct(normal, view, params: ShadingParams, mask, direction, irradiance, angle: float, *,
               method: str = "tpfl") -> np.ndarray:
    """(N, 3) radiance towards ``view`` from a sun (core.light.sun.Sun):
    unit ``direction`` (3,) towards it, ``irradiance`` (3,) W/m² on a surface
    facing it, disc of full ``angle``; ``mask`` (N,) the visible fraction of
    its disc (the bake's sun mask). With the preview's material model, the
    sun as one direction (its Lp is E V max(0, n.l) delta(w - l)):

        B = mask max(0, n.l) E (rho_d / pi + k_s (s' + 1) / (2 pi) max(0, r.l)^s')

    s' the material's exponent widened by the disc (:func:`sun_exponent`);
    ``method`` "diffuse" leaves the lobe out, as the diffuse mode does."""
    n = np.asarray(normal, np.float64)
    l = np.asarray(direction, np.float64).reshape(3)
    E = np.asarray(irradiance, np.float64).reshape(1, 3)
    cos = np.maximum(n @ l, 0.0) * np.asarray(mask, np.float64).reshape(-1)
    out = params.albedo / math.pi * E
    if method != "diffuse" and np.any(params.spec):
        r = reflect(np.asarray(view, np.float64), n)
        r /= np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-300)
        s = sun_exponent(params.exponent, angle).reshape(-1)
        lobe = (s + 1.0) / (2.0 * math.pi) * np.maximum(r @ l, 0.0) ** s
        out = out + params.spec * E * lobe[:, None]
    return out * cos[:, None]


def sun_sh(direction, irradiance, bands: int) -> np.ndarray:
    """(K, 3) RGB SH of a distant light of ``irradiance`` (3,) W/m² from unit
    ``direction`` (3,), L(w) = E delta(w - l): L_k = E y_k(l). What the bounce
    sees of a sun: through a texel's transfer it gives the band-limited
    shadowed cosine at l times E, low-frequency as bounce light is (its
    direct light is drawn exactly, with its mask: :func:`sun_direct`)."""
    d = np.asarray(direction, np.float64).reshape(1, 3)
    d = d / np.linalg.norm(d)
    y = basis_unchecked(d, bands)[0]                                  # (K,)
    return np.outer(y, np.asarray(irradiance, np.float64).reshape(3))


def light_hash(light) -> str:
    """sha256 of the light coefficients a bounce texture was baked with."""
    import hashlib
    return hashlib.sha256(np.ascontiguousarray(np.asarray(light, dtype=np.float64)).tobytes()).hexdigest()
