"""The Principled BSDF's layering: how much of a point's light its specular
layer takes from the diffuse beneath, at the view angle (docs/shading.md).

Cycles' Principled BSDF (Multiscatter GGX, its default) puts a dielectric
specular layer over the diffuse base and scales the base's weight by one
minus the layer's directional albedo at the view direction
(``closure_layering_weight`` fed by ``bsdf_microfacet_estimate_albedo``);
the metallic part is a conductor mixed in by ``metallic``. With mu = n.v,
r the roughness (alpha = r², single-scatter GGX of height-correlated Smith
masking):

* E(mu, r): the white single-scatter albedo, int D G2 / (4 mu) dl;
  E_avg(r) = 2 int E mu dmu.
* s(mu, r, z): the lobe-normalised average of the generalized-Schlick
  blend of the real dielectric Fresnel, (F(v.h, eta) - F0(eta)) / (1 - F0(eta)),
  z = sqrt((eta - 1) / (eta + 1)) = F0^(1/4) (Cycles' axis);
  s5(mu, r): the same with Schlick's (1 - v.h)^5 (the metallic part).
* Multiscatter: Kulla & Conty's darkening E + Fms (1 - E), Fms =
  Fss E_avg / (1 - Fss (1 - E_avg)), Fss the hemispherical average of the
  Fresnel (mix(F0, 1, 2 int blend c dc); 1/21 for Schlick's).

A point's dielectric layer albedo a_d = darkening(F0) mix(F0, 1, s) and
the metal's a_m = darkening(C) mix(C, 1, s5) (RGB); the preview shades

    B = (1 - a_d) rho_d / pi sqrt(4 pi) Lp_0 + ((1 - m) a_d + m a_m) glossy,

so a white Principled surface under a white sky sums to exactly 1 for any
roughness and angle (the Phong lobe of the SH, like Multiscatter GGX,
keeps all its energy). The tables (:data:`MU`, :data:`ROUGH`, :data:`Z`
nodes, uniform on [0, 1]) are computed here in float64 by quadrature
and stored rounded to float32 in ``shaders/prtt_layering.glsl``
(``python -m prtt_addon.dev.layering_table`` writes it; a test regenerates
and compares); :func:`lookup` interpolates them exactly as the GLSL does.
"""
from __future__ import annotations

import math

import numpy as np

#: Table nodes: mu = n.v, roughness, and z = F0^(1/4) (the dielectric's axis).
MU, ROUGH, Z = 16, 16, 8
#: Quadrature points over the half vector's (GGX-distributed) polar and azimuth.
_QU, _QP = 256, 128
#: The smallest mu and roughness evaluated (the nodes at 0 take their limits).
_MU_MIN, _ROUGH_MIN = 1e-4, 1e-3


def _fresnel(c, eta):
    g2 = eta * eta - 1.0 + c * c
    g = np.sqrt(np.maximum(g2, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (g - c) / (g + c)
        b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
        f = 0.5 * a * a * (1.0 + b * b)
    return np.where(g2 > 0.0, np.nan_to_num(f, nan=1.0), 1.0)


def _eta(z: float) -> float:
    """The IOR whose F0 is z⁴ (z < 1)."""
    return (1.0 + z * z) / (1.0 - z * z)


def blend(c, z: float) -> np.ndarray:
    """The generalized-Schlick blend of the real Fresnel at cos ``c`` for
    z = F0^(1/4): (F(c, eta) - F0) / (1 - F0), 0 at z = 0, 1 at z = 1."""
    c = np.asarray(c, np.float64)
    if z <= 0.0:
        return np.zeros_like(c)
    if z >= 1.0:
        return np.ones_like(c)
    f0 = z ** 4
    return (_fresnel(c, _eta(z)) - f0) / (1.0 - f0)


def _lobe(mu: float, r: float):
    """Quadrature of the single-scatter GGX lobe seen from mu: (weights (P,),
    v.h (P,)) with sum(weights) = E(mu, r) and sum(weights F(v.h)) its
    albedo for Fresnel F. Half vectors drawn from D(h) (n.h) in the
    cumulative variable u (tan² = alpha² u / (1 - u)) at midpoints."""
    mu = max(mu, _MU_MIN)
    a2 = max(r, _ROUGH_MIN) ** 4
    u = (np.arange(_QU) + 0.5) / _QU
    phi = (np.arange(_QP) + 0.5) / _QP * math.pi             # the lobe is symmetric in phi
    U, P = np.meshgrid(u, phi, indexing="ij")
    ch = 1.0 / np.sqrt(1.0 + a2 * U / (1.0 - U))
    sh = np.sqrt(1.0 - ch * ch)
    st = math.sqrt(1.0 - mu * mu)
    vh = sh * np.cos(P) * st + ch * mu
    nl = 2.0 * vh * ch - mu
    ok = (nl > 0.0) & (vh > 0.0)

    def lam(c):
        c2 = np.clip(c * c, 1e-300, 1.0)
        return 0.5 * (np.sqrt(1.0 + a2 * (1.0 - c2) / c2) - 1.0)
    g = 1.0 / (1.0 + lam(mu) + lam(np.where(ok, nl, 1.0)))
    w = np.where(ok, g * vh / (mu * ch), 0.0) / (_QU * _QP)
    return w.ravel(), np.clip(vh, 0.0, 1.0).ravel()


def nodes(n: int) -> np.ndarray:
    return np.linspace(0.0, 1.0, n)


def _average(f, n: int = 512) -> float:
    """2 int_0^1 f(c) c dc by the midpoint rule."""
    c = (np.arange(n) + 0.5) / n
    return float(2.0 * np.mean(f(c) * c))


def tables() -> dict[str, np.ndarray]:
    """The float64 tables: ``E`` (ROUGH, MU), ``s5`` (ROUGH, MU), ``s``
    (Z, ROUGH, MU), ``E_avg`` (ROUGH,), ``blend_avg`` (Z,): 2 int blend c dc."""
    mus, rs, zs = nodes(MU), nodes(ROUGH), nodes(Z)
    E = np.zeros((ROUGH, MU))
    s5 = np.zeros((ROUGH, MU))
    s = np.zeros((Z, ROUGH, MU))
    for i, r in enumerate(rs):
        for j, mu in enumerate(mus):
            w, vh = _lobe(mu, r)
            e = w.sum()
            E[i, j] = e
            s5[i, j] = (w * (1.0 - vh) ** 5).sum() / e
            for k, z in enumerate(zs):
                s[k, i, j] = (w * blend(vh, z)).sum() / e
    E_avg = np.array([_average(lambda c, i=i: np.interp(c, mus, E[i])) for i in range(ROUGH)])
    blend_avg = np.array([_average(lambda c, z=z: blend(c, z)) for z in zs])
    return {"E": E, "s5": s5, "s": s, "E_avg": E_avg, "blend_avg": blend_avg}


def float32_tables(t: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """The tables as the shader holds them (float32)."""
    t = tables() if t is None else t
    return {k: np.asarray(v, np.float32) for k, v in t.items()}


def _lerp1(table, x):
    """Linear interpolation of (..., n) ``table`` at x in [0, 1] (N,) along its
    last axis, nodes uniform (the GLSL's prtt_lerp_index)."""
    n = table.shape[-1]
    f = np.clip(x, 0.0, 1.0) * (n - 1)
    i = np.minimum(np.floor(f).astype(np.int64), n - 2)
    t = f - i
    return i, t


def lookup(tab: dict[str, np.ndarray], mu, rough, z):
    """(E, E_avg, s, s5, blend_avg) interpolated at (N,) mu, roughness and z
    (float64 arithmetic on the float32 tables, the GLSL's order)."""
    mu, rough, z = (np.asarray(a, np.float64).reshape(-1) for a in (mu, rough, z))
    jm, tm = _lerp1(tab["E"], mu)
    ir, tr = _lerp1(tab["E"].T, rough)
    kz, tz = _lerp1(tab["blend_avg"], z)

    def bil(T, *lead):
        T = np.asarray(T, np.float64)
        a = T[(*lead, ir, jm)] * (1 - tm) + T[(*lead, ir, jm + 1)] * tm
        b = T[(*lead, ir + 1, jm)] * (1 - tm) + T[(*lead, ir + 1, jm + 1)] * tm
        return a * (1 - tr) + b * tr

    E = bil(tab["E"])
    s5 = bil(tab["s5"])
    s = bil(tab["s"], kz) * (1 - tz) + bil(tab["s"], kz + 1) * tz
    Ea = np.asarray(tab["E_avg"], np.float64)
    E_avg = Ea[ir] * (1 - tr) + Ea[ir + 1] * tr
    Ba = np.asarray(tab["blend_avg"], np.float64)
    blend_avg = Ba[kz] * (1 - tz) + Ba[kz + 1] * tz
    return E, E_avg, s, s5, blend_avg


def darkening(E, E_avg, Fss):
    """Kulla-Conty's multiscatter factor on a lobe normalised to albedo 1:
    E + Fms (1 - E), Fms = Fss E_avg / (1 - Fss (1 - E_avg)) (Fss broadcast)."""
    Fms = Fss * E_avg / (1.0 - Fss * (1.0 - E_avg))
    return E + Fms * (1.0 - E)


def roughness_of(exponent) -> np.ndarray:
    """Principled roughness of a Phong exponent (materials.phong_exponent
    inverted: alpha² = r⁴ = 1 / (2 s + 1)), as the shader recovers it."""
    return (1.0 / (2.0 * np.maximum(np.asarray(exponent, np.float64), 0.0) + 1.0)) ** 0.25


_TABLES: dict[str, np.ndarray] | None = None


def shader_tables() -> dict[str, np.ndarray]:
    """The float32 tables the shader draws with (shaders/prtt_layering.glsl
    holds these numbers: tests/test_layering.py), computed once per process."""
    global _TABLES
    if _TABLES is None:
        _TABLES = float32_tables()
    return _TABLES


def _point(mu, exponent, f0, metallic, spec, tab):
    """The inputs both weights read, clipped, and the tables at them:
    (f0, m, spec, C (the metal's colour, N x 3), E, E_avg, s, s5, blend_avg)."""
    tab = shader_tables() if tab is None else tab
    mu = np.clip(np.asarray(mu, np.float64).reshape(-1), 0.0, 1.0)
    n = mu.size
    f0 = np.clip(np.asarray(f0, np.float64).reshape(n), 0.0, 1.0)
    m = np.clip(np.asarray(metallic, np.float64).reshape(n), 0.0, 1.0)
    spec = np.asarray(spec, np.float64).reshape(n, 3)
    E, E_avg, s, s5, blend_avg = lookup(tab, mu, roughness_of(exponent), np.sqrt(np.sqrt(f0)))
    metal = np.clip(spec - ((1.0 - m) * f0)[:, None], 0.0, None)       # m C
    C = np.where(m[:, None] > 0.0, metal / np.where(m > 0.0, m, 1.0)[:, None], 0.0)
    return f0, m, spec, C, E, E_avg, s, s5, blend_avg


def layer_weights(mu, exponent, f0, metallic, spec, tab=None):
    """(diffuse (N,), glossy (N, 3)): the weights of the diffuse and glossy
    lobes at view cosines ``mu`` (N,) for Phong ``exponent`` (N,), dielectric
    ``f0`` (N,), ``metallic`` (N,) and specular weight ``spec`` (N, 3)
    (materials.derive: spec = (1 - m) F0 + m C). diffuse scales rho_d: 1 - a_d;
    glossy replaces spec: (1 - m) a_d + m a_m (module docstring); 1 and 0
    where spec is 0."""
    f0, m, spec, C, E, E_avg, s, s5, blend_avg = _point(mu, exponent, f0, metallic, spec,
                                                        shader_tables() if tab is None else tab)
    fss_d = f0 + (1.0 - f0) * blend_avg
    a_d = darkening(E, E_avg, fss_d) * (f0 + (1.0 - f0) * s)
    fss_m = C + (1.0 - C) / 21.0
    a_m = darkening(E[:, None], E_avg[:, None], fss_m) * (C + (1.0 - C) * s5[:, None])
    diffuse = np.clip(1.0 - a_d, 0.0, 1.0)
    glossy = ((1.0 - m) * a_d)[:, None] + m[:, None] * a_m
    # No specular layer (spec 0: a Diffuse BSDF, or a black metal): Lambert
    # alone, as the GLSL returns it without a lookup.
    none = ~np.any(spec > 0.0, axis=1)
    diffuse[none], glossy[none] = 1.0, 0.0
    return diffuse, glossy


def multiscatter(mu, exponent, f0, metallic, spec, tab=None):
    """(dielectric (N,), metal (N, 3)): Multiscatter GGX's factor on the
    single-scatter lobe seen from view cosines ``mu``, 1 + Fms (1 - E) / E
    (Cycles' energy_scale times its darkening; Fms of each part's Fss, as in
    :func:`layer_weights`): what the sun's highlight (shade.sun_glossy) gets
    back of the energy single scattering loses on rough surfaces."""
    f0, m, spec, C, E, E_avg, _, _, blend_avg = _point(mu, exponent, f0, metallic, spec,
                                                       shader_tables() if tab is None else tab)
    missing = (1.0 - E) / E

    def factor(Fss):
        return 1.0 + Fss * E_avg / (1.0 - Fss * (1.0 - E_avg)) * missing
    Fss_m = C + (1.0 - C) / 21.0
    ms_m = 1.0 + Fss_m * (E_avg * missing)[:, None] / (1.0 - Fss_m * (1.0 - E_avg)[:, None])
    return factor(f0 + (1.0 - f0) * blend_avg), ms_m
