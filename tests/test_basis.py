"""SH basis vs scipy.special (an independent implementation), stress and bad input."""
import math

import numpy as np
import pytest
from scipy.special import sph_harm_y

from prtt_addon.core import sh
from tests.conftest import random_dirs


def scipy_real_sh(dirs, bands):
    """Real SH from scipy's complex Y_l^m (which carries the Condon-Shortley phase):
    y_lm = sqrt2 Re Y_l^m (m > 0), sqrt2 Im Y_l^|m| (m < 0), Y_l^0 (m = 0)."""
    # atan2 keeps theta accurate near the poles, where arccos(z) loses digits
    theta = np.arctan2(np.hypot(dirs[:, 0], dirs[:, 1]), dirs[:, 2])
    phi = np.mod(np.arctan2(dirs[:, 1], dirs[:, 0]), 2 * np.pi)
    out = np.empty((len(dirs), bands * bands))
    for l in range(bands):
        for m in range(-l, l + 1):
            Y = sph_harm_y(l, abs(m), theta, phi)
            k = l * l + l + m
            out[:, k] = Y.real if m == 0 else math.sqrt(2) * (Y.real if m > 0 else Y.imag)
    return out


POLES_AND_AXES = np.array([
    [0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0],
    [1 / math.sqrt(2), 0, 1 / math.sqrt(2)], [0, 1e-9, math.sqrt(1 - 1e-18)],
], dtype=np.float64)


def test_basis_matches_scipy_up_to_band_10(rng):
    dirs = np.vstack([POLES_AND_AXES, random_dirs(rng, 2000)])
    ours = sh.eval_basis(dirs, 11)
    ref = scipy_real_sh(dirs, 11)
    assert np.abs(ours - ref).max() <= 1e-12


def test_sloan_band1_signs():
    c = math.sqrt(3 / (4 * math.pi))
    d = np.array([0.36, 0.48, 0.8])
    y = sh.eval_basis(d, 2)
    np.testing.assert_allclose(y[1:], [-c * 0.48, c * 0.8, -c * 0.36], rtol=0, atol=1e-15)
    assert abs(c - 0.4886025119) < 1e-9


def test_orthonormal_by_quadrature():
    d, w = sh.gauss_sphere(2 * 15)
    y = sh.eval_basis(d, 16)
    gram = y.T @ (w[:, None] * y)
    assert np.abs(gram - np.eye(256)).max() < 1e-12
    assert abs(w.sum() - 4 * math.pi) < 1e-12


def test_index_helpers():
    for k in range(400):
        l, m = sh.lm_of(k)
        assert sh.sh_index(l, m) == k and -l <= m <= l
    assert sh.n_coeffs(5) == 25 and sh.bands_of(25) == 5
    np.testing.assert_array_equal(sh.band_of_coeffs(3), [0, 1, 1, 1, 2, 2, 2, 2, 2])


def test_bands_16_at_poles_finite_and_exact():
    y = sh.eval_basis(np.array([[0, 0, 1.0], [0, 0, -1.0]]), 16)
    assert np.all(np.isfinite(y))
    # At the poles only m = 0 survives: y_l0(+-1) = +-^l sqrt((2l+1)/4pi).
    for l in range(16):
        for m in range(-l, l + 1):
            k = l * l + l + m
            want = math.sqrt((2 * l + 1) / (4 * math.pi)) if m == 0 else 0.0
            assert abs(y[0, k] - want) < 1e-13
            assert abs(y[1, k] - want * (-1) ** l) < 1e-13


def test_float32_error_within_documented_bound(rng):
    dirs = np.vstack([POLES_AND_AXES, random_dirs(rng, 20000)])
    d32 = dirs.astype(np.float32)
    worst = 0.0
    for bands in (2, 5, 8, 12, 16):
        # same (float32-rounded) input on both paths: the bound is on arithmetic
        y64 = sh.eval_basis(d32.astype(np.float64), bands, normalize=True)
        y32 = sh.eval_basis(d32, bands, dtype=np.float32)
        assert y32.dtype == np.float32
        err = np.abs(y32.astype(np.float64) - y64).max()
        assert err <= sh.float32_error_bound(bands), (bands, err)
        worst = max(worst, err / sh.float32_error_bound(bands))
    assert worst > 0.1   # the bound is tight enough to mean something


def test_single_direction_returns_vector():
    y = sh.eval_basis([0.0, 0.0, 1.0], 3)
    assert y.shape == (9,)


def test_normalize_option_and_near_unit():
    d = np.array([[0.0, 0.0, 2.0], [3.0, 4.0, 0.0]])
    np.testing.assert_allclose(sh.eval_basis(d, 4, normalize=True),
                               sh.eval_basis(d / np.linalg.norm(d, axis=1, keepdims=True), 4))
    tiny = np.array([[1e-9, 0.0, 0.0]])           # short but non-zero: normalisable
    assert np.all(np.isfinite(sh.eval_basis(tiny, 5, normalize=True)))


@pytest.mark.parametrize("dirs, match", [
    (np.array([[0.0, 0.0, 0.5]]), r"dirs\[0\] has length 0.5.*normalize=True"),
    (np.array([[0.0, 0.0, 0.0]]), r"dirs\[0\] has length 0.*zero vector"),
    (np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]), r"dirs\[1\].*zero vector"),
    (np.array([[np.nan, 0.0, 1.0]]), r"dirs\[0\] is not finite"),
    (np.array([[1.0, 0.0]]), r"shape \(N, 3\)"),
    (np.zeros((2, 3, 3)), r"shape \(N, 3\)"),
])
def test_bad_directions_are_named(dirs, match):
    with pytest.raises(ValueError, match=match):
        sh.eval_basis(dirs, 3)


def test_zero_vector_rejected_even_with_normalize():
    with pytest.raises(ValueError, match="zero vector"):
        sh.eval_basis(np.zeros(3), 3, normalize=True)


@pytest.mark.parametrize("bands, exc", [(0, ValueError), (-2, ValueError), (2.5, TypeError),
                                        ("5", TypeError), (True, TypeError)])
def test_bad_bands(bands, exc):
    with pytest.raises(exc, match="bands"):
        sh.eval_basis([0.0, 0.0, 1.0], bands)


def test_string_directions_rejected():
    with pytest.raises(TypeError, match="numeric"):
        sh.eval_basis(np.array([["a", "b", "c"]]), 2)
