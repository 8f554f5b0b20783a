"""The reference shading model against brute-force quadrature of the same integrals."""
import math

import numpy as np
import pytest

from prtt_addon.core import sh
from prtt_addon.core.model.material import Material
from prtt_addon.core.shading.materials import ShadingParams, derive, phong_exponent
from prtt_addon.core.shading.shade import incident_tp, incident_tpfl, layer, outgoing, reflect, shade
from tests.conftest import random_dirs

BANDS = 5
QD, QW = sh.gauss_sphere(120)
YQ = sh.eval_basis(QD, BANDS)


def cap_quadrature(axis, n=96):
    """Gauss-Legendre on the hemisphere about ``axis`` (where the lobe lives)."""
    x, wx = np.polynomial.legendre.leggauss(n)
    t, phi = 0.5 * (x + 1), math.pi * (x + 1)
    Tt, P = np.meshgrid(t, phi, indexing="ij")
    W = np.outer(wx * 0.5, wx * math.pi).ravel()
    r = np.sqrt(1 - Tt ** 2)
    a = np.cross(axis, [1.0, 0, 0] if abs(axis[0]) < 0.9 else [0, 1.0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(axis, a)
    d = (r * np.cos(P)).reshape(-1, 1) * a + (r * np.sin(P)).reshape(-1, 1) * b + Tt.reshape(-1, 1) * axis
    return d, W, Tt.ravel()


def brute_force(T, L, normal, view, params, layered=True):
    """Outgoing radiance by quadrature, written without Gaunt tensors or
    convolution factors: Lp = projection of the pointwise product T(w) L(w)
    onto the K coefficients (what the SH pipeline keeps), then
    rho_d / pi * integral Lp + k_s * integral Lp(w) (s+1)/(2 pi) max(0, w.r)^s,
    the lobe integrated on its own hemisphere (it has a kink at w.r = 0);
    ``layered``: rho_d and k_s replaced by the layering's weights (layer)."""
    out = np.zeros((T.shape[0], 3))
    if layered:
        dw, gw = layer(normal, view, params)
        params = ShadingParams(params.albedo * dw[:, None], gw, params.exponent)
    for i in range(T.shape[0]):
        t = YQ @ T[i]
        r = 2 * (normal[i] @ view[i]) * normal[i] - view[i]
        cd, cw, ct = cap_quadrature(r)
        lobe = (params.exponent[i] + 1) / (2 * math.pi) * ct ** params.exponent[i]
        yc = sh.eval_basis(cd, BANDS)
        for c in range(3):
            Lp = YQ.T @ (QW * t * (YQ @ L[:, c]))            # projected product
            out[i, c] = (params.albedo[i, c] / math.pi * np.sum(QW * (YQ @ Lp))
                         + params.spec[i, c] * np.sum(cw * (yc @ Lp) * lobe))
    return out


def random_case(rng, n=6, exponent=(0.0, 1.0, 7.5, 40.0, 3.0, 12.0)):
    T = rng.standard_normal((n, BANDS * BANDS)) * 0.3
    T[:, 0] += 1.0
    L = rng.standard_normal((BANDS * BANDS, 3)) * 0.5
    L[0] += 3.0
    normal = random_dirs(rng, n)
    view = random_dirs(rng, n)
    view = np.where((np.sum(view * normal, 1) < 0)[:, None], -view, view)
    params = ShadingParams(rng.uniform(0, 1, (n, 3)), rng.uniform(0, 1, (n, 3)), np.array(exponent[:n], float))
    return T, L, normal, view, params


def test_tpfl_matches_brute_force(rng):
    T, L, n, v, p = random_case(rng)
    got = shade(T, n, v, L, p, clamp=False)
    ref = brute_force(T, L, n, v, p)
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-9)
    # the model before the layering, one argument away
    np.testing.assert_allclose(shade(T, n, v, L, p, clamp=False, layered=False),
                               brute_force(T, L, n, v, p, layered=False), rtol=1e-9, atol=1e-9)
    assert np.abs(got - shade(T, n, v, L, p, clamp=False, layered=False)).max() > 1e-3


def test_tp_tpfl_and_diffuse_agree(rng):
    T, L, n, v, p = random_case(rng)
    np.testing.assert_allclose(incident_tp(T, L), incident_tpfl(T, L), atol=1e-12)
    np.testing.assert_allclose(shade(T, n, v, L, p, method="tp", clamp=False),
                               shade(T, n, v, L, p, clamp=False), atol=1e-12)
    p0 = ShadingParams(p.albedo, np.zeros_like(p.spec), p.exponent)
    np.testing.assert_allclose(shade(T, n, v, L, p0, method="diffuse", clamp=False),
                               shade(T, n, v, L, p0, clamp=False), atol=1e-12)
    # the double product: rho_d / pi * T . L
    np.testing.assert_allclose(shade(T, n, v, L, p0, method="diffuse", clamp=False),
                               p.albedo / math.pi * (T @ L), atol=1e-12)


def test_bounce_adds_linearly(rng):
    T, L, n, v, p = random_case(rng)
    B = rng.standard_normal((T.shape[0], 3, BANDS * BANDS)) * 0.1
    with_b = shade(T, n, v, L, p, bounces=[B], clamp=False)
    only_b = outgoing(B, n, v, p, clamp=False)
    np.testing.assert_allclose(with_b, shade(T, n, v, L, p, clamp=False) + only_b, atol=1e-12)


def test_white_furnace():
    """Unoccluded, constant white light 1, white diffuse: radiance 1 (the lobe
    and the cosine integrate to 1 with albedo 1); a Phong lobe of any exponent
    with k_s = 1 gives the band-limited cosine-weighted light, close to 1 for
    a normal-facing reflection."""
    n = np.array([[0, 0, 1.0]])
    T = sh.zonal_to_sh(sh.clamped_cosine_factors(BANDS), n)
    L = np.zeros((BANDS * BANDS, 3))
    L[0] = math.sqrt(4 * math.pi)                  # radiance 1 everywhere
    diffuse = ShadingParams(np.ones((1, 3)), np.zeros((1, 3)), np.zeros(1))
    np.testing.assert_allclose(shade(T, n, n, L, diffuse), [[1.0, 1.0, 1.0]], atol=1e-12)


def test_reflection_convention():
    n = np.array([[0, 0, 1.0]])
    v = np.array([[math.sin(0.5), 0, math.cos(0.5)]])
    np.testing.assert_allclose(reflect(v, n), [[-math.sin(0.5), 0, math.cos(0.5)]], atol=1e-15)


def test_outputs_clamped_and_finite_for_extremes(rng):
    T, L, n, v, p = random_case(rng)
    L[0] = -5.0                                     # a light that rings negative
    p.exponent[:] = [0.0, 1e4, 1e4, 0.0, 5000.0, 1.0]
    out = shade(T, n, v, L, p)
    assert np.all(np.isfinite(out)) and out.min() >= 0.0
    T[:] = 0.0
    assert np.all(shade(T, n, v, L, p) == 0.0)


def test_principled_mapping():
    np.testing.assert_allclose(phong_exponent([1.0, 0.5, 0.1, 0.0]), [0.0, 7.5, 4999.5, 1e4])
    p = derive(np.array([[0.8, 0.5, 0.2], [0.8, 0.5, 0.2]]), np.array([0.0, 1.0]), np.array([0.5, 0.5]),
               np.array([0.5, 0.5]), np.array([1.5, 1.5]))
    np.testing.assert_allclose(p.albedo[0], [0.8, 0.5, 0.2])
    np.testing.assert_allclose(p.spec[0], [0.04] * 3)          # dielectric F0 at IOR 1.5
    np.testing.assert_allclose(p.albedo[1], 0.0)
    np.testing.assert_allclose(p.spec[1], [0.8, 0.5, 0.2])    # metal: coloured reflection
    with pytest.raises(ValueError, match="roughness must be in"):
        Material.from_dict({"roughness": 2.0})
    with pytest.raises(ValueError, match="unknown material fields"):
        Material.from_dict({"colour": [1, 1, 1]})


def test_light_validation(rng):
    T, L, n, v, p = random_case(rng)
    with pytest.raises(ValueError, match="light has 2 bands, shading needs 5"):
        shade(T, n, v, L[:4], p)
    with pytest.raises(ValueError, match=r"\(K, 3\)"):
        shade(T, n, v, L[:, :2], p)
    with pytest.raises(ValueError, match="unknown shading method"):
        shade(T, n, v, L, p, method="pbr")
