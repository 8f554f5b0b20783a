"""Zonal lobes vs analytic values and scipy.integrate.quad; convolution; windows."""
import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.special import eval_legendre

from prtt_addon.core import sh
from tests.conftest import random_dirs


def test_clamped_cosine_analytic_values():
    A = sh.clamped_cosine_factors(7)
    want = [math.pi, 2 * math.pi / 3, math.pi / 4, 0.0, -math.pi / 24, 0.0, math.pi / 64]
    np.testing.assert_allclose(A, want, rtol=0, atol=1e-15)


@pytest.mark.parametrize("a", [0.0, 1.0, 2.5, 10.0, 100.0, 1000.0])
def test_power_cosine_integrals_vs_quad(a):
    I = sh.power_cosine_integrals(a, 12)
    for l in range(12):
        ref, _ = quad(lambda t, l=l: t ** a * eval_legendre(l, t), 0, 1, epsabs=1e-14, epsrel=1e-12, limit=200)
        assert abs(I[l] - ref) < 1e-11, (a, l)


@pytest.mark.parametrize("s", [0.0, 1.0, 8.0, 64.0, 512.0, 5000.0])
def test_phong_lobe_normalised(s):
    total, _ = quad(lambda t: (s + 1) / (2 * math.pi) * t ** s * 2 * math.pi, 0, 1, epsabs=1e-14)
    assert abs(total - 1.0) < 1e-10
    assert sh.phong_factors(s, 6)[0] == pytest.approx(1.0, abs=1e-15)
    A = sh.phong_factors(s, 6)
    for l in range(6):
        ref, _ = quad(lambda t, l=l: (s + 1) * t ** s * eval_legendre(l, t), 0, 1, epsabs=1e-13, limit=400)
        assert abs(A[l] - ref) < 1e-9


def test_phong_factors_vectorised():
    s = np.array([[1.0, 10.0], [100.0, 0.0]])
    A = sh.phong_factors(s, 5)
    assert A.shape == (2, 2, 5)
    np.testing.assert_allclose(A[1, 0], sh.phong_factors(100.0, 5))


def test_convolution_is_funk_hecke(rng):
    """(h * f)(d) = integral f(w) h(w.d) dw, checked by brute-force quadrature."""
    bands = 5
    f_coeffs = rng.standard_normal(bands * bands)
    s = 12.0
    conv = sh.convolve(f_coeffs, sh.phong_factors(s, bands))
    qd, qw = sh.gauss_sphere(60)
    f_at_q = sh.eval_basis(qd, bands) @ f_coeffs
    for d in random_dirs(rng, 5):
        t = np.clip(qd @ d, 0, None)
        ref = np.sum(qw * f_at_q * (s + 1) / (2 * math.pi) * t ** s)
        got = sh.eval_basis(d, bands) @ conv
        # the lobe is not band-limited, so compare against its band-limited part
        lobe = sh.zonal_to_sh(sh.phong_factors(s, bands), d)
        assert abs(got - lobe @ f_coeffs) < 1e-12
        assert abs(got - ref) < 2e-3


def test_zonal_to_sh_is_rotated_clamped_cosine(rng):
    d = random_dirs(rng, 1)[0]
    c = sh.zonal_to_sh(sh.clamped_cosine_factors(6), d)
    ref = sh.project_function(lambda w: np.clip(w @ d, 0, None), 6, degree=200)
    assert np.abs(c - ref).max() < 1e-5   # quadrature of a kinked function: O(1/degree^2)


def test_convolve_axis_and_errors():
    c = np.ones((3, 9))
    out = sh.convolve(c, [1, 2, 3], axis=1)
    np.testing.assert_array_equal(out[0], [1, 2, 2, 2, 3, 3, 3, 3, 3])
    with pytest.raises(ValueError, match="need 3 per-band factors"):
        sh.convolve(c, [1, 2], axis=1)
    with pytest.raises(ValueError, match="exponent"):
        sh.power_cosine_integrals(-1, 3)
    with pytest.raises(ValueError, match="Phong exponents"):
        sh.phong_factors(np.nan, 3)


def test_windows():
    np.testing.assert_array_equal(sh.window_factors(5), np.ones(5))
    h = sh.window_factors(5, "hanning")
    assert h[0] == 1.0 and np.all(np.diff(h) < 0) and h[-1] > 0
    lz = sh.window_factors(5, "lanczos", width=5)
    np.testing.assert_allclose(lz[1], math.sin(math.pi / 5) / (math.pi / 5))
    assert sh.window_factors(5, "hanning", width=2)[3] == 0.0
    with pytest.raises(ValueError, match="unknown window"):
        sh.window_factors(5, "gauss")


def test_hanning_window_reduces_ringing():
    """A sharp cap projected to 5 bands rings negative; the window reduces it."""
    cap = sh.project_function(lambda w: (w[:, 2] > 0.7).astype(float), 5, degree=300)
    d, _ = sh.gauss_sphere(80)
    raw = sh.eval_basis(d, 5) @ cap
    win = sh.eval_basis(d, 5) @ sh.convolve(cap, sh.window_factors(5, "hanning"))
    assert win.min() > raw.min() * 0.5
