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
  Layered (the default, the Principled BSDF's): rho_d scaled by 1 - a_d(n.v)
  and k_s replaced by the specular layer's albedo at n.v (layering.py).
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
from .layering import layer_weights, multiscatter
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


def layer(normal, view, params: ShadingParams) -> tuple[np.ndarray, np.ndarray]:
    """(diffuse (N,), glossy (N, 3)): the Principled layering's lobe weights
    at each point's view cosine n.v (layering.layer_weights): the diffuse
    albedo is scaled by the first, the glossy lobe weighed by the second
    instead of ``spec``. Without a known F0 (params.f0 None) a dielectric
    of F0 = spec; without metallic, 0."""
    n = np.asarray(normal, np.float64)
    mu = np.einsum("nc,nc->n", n, np.broadcast_to(np.asarray(view, np.float64), n.shape))
    spec = np.asarray(params.spec, np.float64).reshape(-1, 3)
    N = spec.shape[0]
    m = np.zeros(N) if params.metallic is None else np.asarray(params.metallic, np.float64).reshape(N)
    f0 = spec.mean(axis=1) if params.f0 is None else np.asarray(params.f0, np.float64).reshape(N)
    ex = np.broadcast_to(np.asarray(params.exponent, np.float64), (N,))
    return layer_weights(mu, ex, f0, m, spec)


def outgoing(Lp: np.ndarray, normal: np.ndarray, view: np.ndarray, params: ShadingParams,
             *, clamp: bool = True, layered: bool = True) -> np.ndarray:
    """Radiance (N, 3) towards ``view`` from cosine-weighted incident radiance Lp (N, 3, K).

    ``layered`` (the preview's model): the Principled layering's weights
    (:func:`layer`); False: rho_d and k_s as they are (the model before it).
    Computed in Lp's precision: float64 for the reference, float32 for the
    bounce bake's hit shading (error ~1e-6 relative; tests/test_shading.py).
    """
    N, _, K = Lp.shape
    n = bands_of(K)
    dt = np.float32 if Lp.dtype == np.float32 else np.float64
    albedo, spec = params.albedo, params.spec
    if layered:
        dw, spec = layer(normal, view, params)
        albedo = albedo * dw[:, None]
    diffuse = (albedo * (SQRT_4PI / math.pi)).astype(dt) * Lp[:, :, 0]
    out = diffuse
    if np.any(params.spec):
        r = reflect(np.asarray(view, np.float64), np.asarray(normal, np.float64))
        r /= np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-300)
        Ay = lobe_factors(params.exponent, n).astype(dt) * basis_unchecked(r.astype(dt), n, dt)
        out = out + spec.astype(dt) * np.matmul(Lp, Ay[:, :, None])[:, :, 0]
    return np.maximum(out, 0.0) if clamp else out


def shade(T, normal, view, light, params: ShadingParams, *, bounces=(), method: str = "tpfl",
          window: str | None = None, clamp: bool = True, layered: bool = True) -> np.ndarray:
    """Outgoing radiance (N, 3) of points with transfer T (N, K).

    bounces : iterable of (N, 3, K) incident-radiance SH (bounce textures).
    method  : "tpfl" (default), "tp" (full triple product) or "diffuse" (the
              double-product fast path; ignores the glossy lobe).
    """
    T = np.atleast_2d(np.asarray(T, dtype=np.float64))
    n = bands_of(T.shape[1])
    L = prepare_light(light, n, window=window)
    if method == "diffuse":
        albedo = params.albedo * layer(normal, view, params)[0][:, None] if layered else params.albedo
        direct = albedo / math.pi * (T @ L)
        extra = sum((albedo / math.pi * SQRT_4PI * np.asarray(b)[:, :, 0] for b in bounces),
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
    return outgoing(Lp, normal, view, params, clamp=clamp, layered=layered)


def sun_direct(normal, view, params: ShadingParams, mask, direction, irradiance, angle: float, *,
               method: str = "tpfl", layered: bool = True) -> np.ndarray:
    """(N, 3) radiance towards ``view`` from a sun (core.light.sun.Sun):
    unit ``direction`` (3,) towards it, ``irradiance`` (3,) W/m² on a surface
    facing it, disc of full ``angle``; ``mask`` (N,) the visible fraction of
    its disc (the bake's sun mask). The sun as one direction l (its Lp is
    E V max(0, n.l) delta(w - l)), evaluated per pixel, so its highlight is
    Cycles' microfacet model rather than the SH lobe:

        B = mask max(0, n.l) E (w_d rho_d / pi + f_s),  f_s = D G F / (4 (n.v) (n.l))

    (w_d the layering's diffuse weight at n.v, :func:`layer`, and f_s
    Multiscatter GGX's: :func:`sun_glossy`; ``layered`` False: w_d = 1 and
    single scattering, the model before)
    D the GGX distribution of alpha'^2 = alpha^2 + angle^2 / 32 (the
    material's alpha^2 = 1 / (2 s + 1), materials.phong_exponent inverted,
    widened by the disc: :func:`sun_alpha2`), G Smith's height-correlated
    masking of alpha^2, F the dielectric Fresnel of the IOR whose F0 the
    material has, plus Schlick's for the metallic part (:func:`sun_fresnel`).
    ``method`` "diffuse" leaves the lobe out, as the diffuse mode does."""
    n = np.asarray(normal, np.float64)
    l = np.asarray(direction, np.float64).reshape(3)
    E = np.asarray(irradiance, np.float64).reshape(1, 3)
    cos = np.maximum(n @ l, 0.0) * np.asarray(mask, np.float64).reshape(-1)
    albedo = params.albedo * layer(n, view, params)[0][:, None] if layered else params.albedo
    out = albedo / math.pi * E
    if method != "diffuse" and np.any(params.spec):
        out = out + sun_glossy(n, np.asarray(view, np.float64), l, params, angle, multi=layered) * E
    return out * cos[:, None]


def lamp_direct(points, normal, view, params: ShadingParams, masks, lamps, *, method: str = "tpfl",
                layered: bool = True) -> np.ndarray:
    """(N, 3) radiance towards ``view`` from point and spot lamps
    (core.light.lamp.Lamp) at world ``points`` (N, 3); ``masks`` (N, L) the
    visible fraction of each lamp's sphere (the bake's lamp masks). Each lamp
    as one direction l from the point to its centre, as the sun
    (:func:`sun_direct`), of irradiance E = I spot / r^2 (Lamp.irradiance),
    its lobe widened by the sphere's disc of full angle 2 asin(R / r):

        B = sum_i mask_i max(0, n.l_i) E_i (w_d rho_d / pi + f_s(l_i))"""
    n = np.asarray(normal, np.float64)
    v = np.asarray(view, np.float64)
    p = np.asarray(points, np.float64)
    masks = np.asarray(masks, np.float64).reshape(n.shape[0], -1)
    albedo = params.albedo * layer(n, v, params)[0][:, None] if layered else params.albedo
    out = np.zeros((n.shape[0], 3))
    for i, lp in enumerate(lamps):
        l, E = lp.irradiance(p)
        cos = np.maximum(np.einsum("nc,nc->n", n, l), 0.0) * masks[:, i]
        b = albedo / math.pi * E
        if method != "diffuse" and np.any(params.spec):
            r = np.linalg.norm(np.asarray(lp.position) - p, axis=1)
            angle = 2.0 * np.arcsin(np.minimum(lp.radius / np.maximum(r, 1e-12), 1.0))
            b = b + sun_glossy(n, v, l, params, angle, multi=layered) * E
        out += b * cos[:, None]
    return out


def sun_alpha2(exponent, angle: float) -> tuple[np.ndarray, np.ndarray]:
    """(alpha^2, alpha'^2): the GGX roughness of a Phong ``exponent``
    (materials.phong_exponent: alpha^2 = 1 / (2 s + 1)) and that widened by a
    disc of full ``angle``. Near its peak GGX is a Gaussian in tan(theta_h)
    of per-axis variance alpha^2 / 2; the disc's uniform radius a / 2 adds
    (a / 2)^2 / 4 per axis in the light's direction, a quarter of it in the
    half vector's: alpha'^2 = alpha^2 + a^2 / 32."""
    a2 = 1.0 / (2.0 * np.maximum(np.asarray(exponent, np.float64), 0.0) + 1.0)
    return a2, a2 + angle * angle / 32.0


def fresnel_dielectric(c, eta) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a dielectric of relative IOR ``eta``
    at cos(incidence) ``c`` (1 beyond total internal reflection)."""
    c = np.asarray(c, np.float64)
    g2 = np.asarray(eta, np.float64) ** 2 - 1.0 + c * c
    g = np.sqrt(np.maximum(g2, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (g - c) / (g + c)
        b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
        f = 0.5 * a * a * (1.0 + b * b)
    return np.where(g2 > 0.0, np.nan_to_num(f, nan=1.0), 1.0)


def sun_fresnel(vh, params: ShadingParams, ms=None) -> np.ndarray:
    """(N, 3) F at cos(v.h) ``vh``: (1 - m) times the dielectric Fresnel of
    eta = (1 + sqrt F0) / (1 - sqrt F0) and, for the metallic part, Schlick's
    with the base colour (m C = spec - (1 - m) F0). ``ms`` (dielectric (N,),
    metal (N, 3)): each part times its multiscatter factor."""
    spec = np.asarray(params.spec, np.float64)
    n = spec.shape[0]
    m = np.zeros(n) if params.metallic is None else np.asarray(params.metallic, np.float64).reshape(n)
    f0 = spec.mean(axis=1) if params.f0 is None else np.asarray(params.f0, np.float64).reshape(n)
    sf = np.sqrt(np.clip(f0, 0.0, 0.999))
    eta = (1.0 + sf) / (1.0 - sf)
    metal = spec - ((1.0 - m) * f0)[:, None]
    q = (1.0 - np.clip(vh, 0.0, 1.0)) ** 5
    d = ((1.0 - m) * fresnel_dielectric(vh, eta))[:, None]
    c = metal + (m[:, None] - metal) * q[:, None]
    if ms is not None:
        d, c = d * ms[0][:, None], c * ms[1]
    return d + c


def _smith_lambda(c, a2):
    c2 = np.clip(c * c, 1e-12, 1.0)
    return 0.5 * (np.sqrt(1.0 + a2 * (1.0 - c2) / c2) - 1.0)


def sun_glossy(n, v, l, params: ShadingParams, angle: float, *, multi: bool = True) -> np.ndarray:
    """(N, 3) the sun's specular BRDF f_s = D G F / (4 (n.v) (n.l)) at unit
    normals ``n`` and view vectors ``v`` (N, 3), towards the sun ``l`` (3,)
    or one direction a point (N, 3) (0 where n.v or n.l is not positive):
    see :func:`sun_direct`. ``multi`` (Multiscatter GGX, Blender's default): each Fresnel part times
    layering.multiscatter at n.v; False: single scattering."""
    l = np.asarray(l, np.float64)
    nv = np.einsum("ij,ij->i", n, v)
    nl = n @ l if l.ndim == 1 else np.einsum("ij,ij->i", n, l)
    h = v + l
    hn = np.linalg.norm(h, axis=1, keepdims=True)
    h = np.where(hn > 0, h / np.where(hn > 0, hn, 1.0), n)
    nh = np.clip(np.einsum("ij,ij->i", n, h), 0.0, 1.0)
    vh = np.clip(np.einsum("ij,ij->i", v, h), 0.0, 1.0)
    a2, a2s = sun_alpha2(params.exponent, angle)
    a2, a2s = np.broadcast_to(a2, nh.shape), np.broadcast_to(a2s, nh.shape)
    t = nh * nh * (a2s - 1.0) + 1.0
    D = a2s / (math.pi * t * t)
    ok = (nv > 0.0) & (nl > 0.0)
    G = 1.0 / (1.0 + _smith_lambda(nv, a2) + _smith_lambda(nl, a2))
    f = np.where(ok, D * G / (4.0 * np.where(ok, nv * nl, 1.0)), 0.0)
    spec = np.asarray(params.spec, np.float64).reshape(-1, 3)
    N = spec.shape[0]
    mm = np.zeros(N) if params.metallic is None else params.metallic
    f0 = spec.mean(axis=1) if params.f0 is None else params.f0
    ms = multiscatter(nv, np.broadcast_to(params.exponent, (N,)), f0, mm, spec) if multi else None
    return sun_fresnel(vh, params, ms) * f[:, None]


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
