"""Projection of sampled functions: exact quadrature, Monte Carlo, Parseval."""
import math

import numpy as np
import pytest

from prtt_addon.core import sh
from tests.conftest import random_dirs


def poly(d):
    """A band-limited (degree 3) test function written without SH."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    return 1.0 + 0.5 * x - 0.3 * y * z + 0.8 * z * z * x + 0.25 * x * y


def test_quadrature_is_exact_for_polynomials():
    d, w = sh.gauss_sphere(6)
    # integral of z^2 = 4 pi / 3, of x^2 y^2 z^2 = 4 pi / 105
    assert abs(np.sum(w * d[:, 2] ** 2) - 4 * math.pi / 3) < 1e-13
    assert abs(np.sum(w * (d[:, 0] * d[:, 1] * d[:, 2]) ** 2) - 4 * math.pi / 105) < 1e-14


def test_projection_reconstructs_band_limited_function(rng):
    c = sh.project_function(poly, 4)
    d = random_dirs(rng, 500)
    assert np.abs(sh.reconstruct(c, d) - poly(d)).max() < 1e-13
    # and nothing above band 3
    c6 = sh.project_function(poly, 6)
    assert np.abs(c6[16:]).max() < 1e-14


def test_parseval():
    c = sh.project_function(poly, 4)
    d, w = sh.gauss_sphere(10)
    assert abs(np.sum(c * c) - np.sum(w * poly(d) ** 2)) < 1e-12


def test_monte_carlo_projection_converges(rng):
    exact = sh.project_function(poly, 4)
    errs = []
    for n in (4000, 64000):
        d = random_dirs(rng, n)
        est = sh.project(poly(d), d, np.full(n, 4 * math.pi / n), 4)
        errs.append(np.abs(est - exact).max())
    # 16x the samples -> ~4x less error; allow generous noise.
    assert errs[1] < errs[0] / 2
    assert errs[1] < 0.05


def test_projection_shape_errors():
    d, w = sh.gauss_sphere(4)
    with pytest.raises(ValueError, match="disagree on Q"):
        sh.project(np.ones(len(d) - 1), d, w, 3)
