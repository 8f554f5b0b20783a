"""The sun's direct light in the preview's material model
(shading.shade.sun_direct) against quadrature over its disc: the Phong lobe
of exponent s seen through a disc of uniform radiance, which sun_direct
approximates by one widened lobe (sun_exponent)."""
import math

import numpy as np
import pytest

from prtt_addon.core.shading.materials import ShadingParams
from prtt_addon.core.shading.shade import sun_direct, sun_exponent


def _disc(angle, n=40_000, seed=0):
    """Directions uniform over a disc of full ``angle`` about +z."""
    rng = np.random.default_rng(seed)
    u = (np.arange(n) + rng.random(n)) / n
    ct = 1.0 - u * (1.0 - math.cos(angle / 2))
    phi = 2 * math.pi * rng.random(n)
    st = np.sqrt(1 - ct * ct)
    return np.stack([st * np.cos(phi), st * np.sin(phi), ct], 1)


def _integral(f, x):
    return float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(x)))


def _params(n, albedo, spec, s):
    return ShadingParams(np.full((n, 3), albedo), np.full((n, 3), spec), np.full(n, float(s)))


def test_diffuse_is_the_cosine_times_the_mask():
    n = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.0, -1.0]])
    v = np.array([[0.0, 0.0, 1.0]] * 3)
    out = sun_direct(n, v, _params(3, 0.5, 0.0, 1.0), [1.0, 0.5, 1.0], (0.0, 0.0, 1.0), (2.0, 2.0, 2.0), 0.01)
    assert np.allclose(out[:, 0], [0.5 / math.pi * 2.0, 0.5 / math.pi * 2.0 * 0.8 * 0.5, 0.0])


@pytest.mark.parametrize("s", [1.0, 10.0, 100.0, 1000.0])
@pytest.mark.parametrize("angle_deg", [0.5, 5.0])
def test_the_widened_lobe_keeps_the_highlights_energy(s, angle_deg):
    """Over the mirror directions r near the sun, the glossy term integrates to
    the same energy as the lobe integrated over the disc (within 1 %), and
    where the lobe is wider than the disc (s^-1/2 >> angle) it is the same
    highlight point by point (within 2 %)."""
    angle = math.radians(angle_deg)
    d = _disc(angle)
    # Mirror directions r on a grid about the sun (z), in the plane x-z.
    width = max(4.0 / math.sqrt(s), angle)
    th = np.linspace(-width, width, 401)
    r = np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], 1)
    exact = np.array([((s + 1) / (2 * math.pi) * np.maximum(d @ ri, 0.0) ** s).mean() for ri in r])
    sp = sun_exponent(s, angle)
    approx = (sp + 1) / (2 * math.pi) * np.maximum(r[:, 2], 0.0) ** sp
    # 2-D energy of a radially symmetric profile: integral of f(theta) |theta| dtheta.
    e_exact = _integral(exact * np.abs(th), th)
    e_approx = _integral(approx * np.abs(th), th)
    assert abs(e_approx / e_exact - 1) < 0.01, (e_approx, e_exact)
    if 1.0 / math.sqrt(s) > 10 * angle:
        assert np.abs(approx - exact).max() < 0.02 * exact.max()
    # sun_direct is that lobe times the cosine and the irradiance.
    n = np.array([[0.0, 0.0, 1.0]])
    v = np.array([[0.0, 0.0, 1.0]])
    got = sun_direct(n, v, _params(1, 0.0, 1.0, s), [1.0], (0.0, 0.0, 1.0), (1.0, 1.0, 1.0), angle)
    assert np.allclose(got, approx[200])
