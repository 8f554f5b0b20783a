"""Transfer against analytic values: unoccluded, under a plane, by a wall, in a box."""
import math

import numpy as np
import pytest

from prtt_addon.core import sh
from prtt_addon.core.bake.estimators.raytrace import RayScene
from prtt_addon.core.bake.estimators.transfer import Points, TransferSettings, bake_points, unoccluded_transfer
from tests.conftest import random_dirs


def quad(z=0.0, half=1.0, flip=False):
    t = np.array([[[-half, -half, z], [half, -half, z], [half, half, z]],
                  [[-half, -half, z], [half, half, z], [-half, half, z]]], float)
    return t[:, ::-1] if flip else t


def floor_points(n, z=0.0, spread=0.5, rng=None, normal=(0, 0, 1.0)):
    rng = rng or np.random.default_rng(0)
    pos = np.c_[rng.uniform(-spread, spread, (n, 2)), np.full(n, z)]
    nrm = np.tile(np.asarray(normal, float), (n, 1))
    return Points(pos, nrm, nrm.copy(), np.arange(n, dtype=np.int64), np.zeros(n, bool))


def hemisphere_integral(f, normal, bands=5, n=200):
    """integral over w.normal > 0 of f(w) y(w) dw by Gauss-Legendre on the
    hemisphere's own polar grid (exact enough for piecewise-smooth f)."""
    x, wx = np.polynomial.legendre.leggauss(n)
    z = 0.5 * (x + 1)
    phi = np.pi * (x + 1)
    Z, P = np.meshgrid(z, phi, indexing="ij")
    W = np.outer(wx * 0.5, wx * np.pi)
    r = np.sqrt(1 - Z ** 2)
    local = np.stack([r * np.cos(P), r * np.sin(P), Z], -1).reshape(-1, 3)
    nz = np.asarray(normal, float)
    t = np.cross(nz, [1.0, 0, 0] if abs(nz[0]) < 0.9 else [0, 1.0, 0])
    t /= np.linalg.norm(t)
    b = np.cross(nz, t)
    d = local @ np.stack([t, b, nz])
    return sh.eval_basis(d, bands).T @ (W.ravel() * f(d))


@pytest.mark.parametrize("estimator", ["balanced", "control-variate"])
def test_unoccluded_traced_is_exact(estimator, rng):
    # The only geometry is a speck 1e3 away (solid angle ~1e-12): nothing occludes.
    rs = RayScene(quad(z=-1e3, half=1e-3))
    normals = random_dirs(rng, 300)
    pts = floor_points(300, z=0.0)
    pts.normal[:] = normals
    pts.geo_normal[:] = normals
    out, info = bake_points(rs, pts, TransferSettings(rays=256, estimator=estimator, analytic=False))
    assert np.abs(out - unoccluded_transfer(normals, 5)).max() <= 1e-6
    assert info["rays_traced"] == 300 * 256


def test_unoccluded_analytic_path_exact_and_ray_free(rng):
    rs = RayScene(quad())
    pts = floor_points(200)
    pts.analytic[:] = True
    out, info = bake_points(rs, pts, TransferSettings())
    assert info["rays_traced"] == 0 and info["analytic_points"] == 200
    ref = hemisphere_integral(lambda d: np.clip(d[:, 2], 0, None), (0, 0, 1))
    assert np.abs(out - ref[None, :]).max() <= 1e-6


def test_plain_estimator_unoccluded_within_mc_error():
    rs = RayScene(quad())
    pts = floor_points(400, z=1.0)
    out, _ = bake_points(rs, pts, TransferSettings(rays=256, estimator="plain", analytic=False))
    err = np.abs(out - unoccluded_transfer(pts.normal, 5))
    assert err.mean() < 0.02 and err.max() < 0.1          # quadrature error of 256 Sobol rays


def test_under_infinite_plane_is_dark():
    # A ceiling 0.05 above the floor, 1e3 wide: rays escape only below an
    # elevation of 5e-5 rad, whose cosine-weighted share is ~1e-9.
    rs = RayScene(np.concatenate([quad(0.0, 1.0), quad(0.05, 1e3, flip=True)]))
    pts = floor_points(300, spread=0.9)
    # balanced: exact by construction; plain: float32 sums of 256 terms (~1e-6).
    for est, tol in (("balanced", 1e-6), ("plain", 1e-5)):
        out, _ = bake_points(rs, pts, TransferSettings(rays=256, estimator=est, analytic=False))
        assert np.abs(out).max() <= tol, est


def test_next_to_wall_matches_analytic():
    """A floor point facing +Z beside an infinite wall at x = 0.1 (normal -X):
    V = [w_x < 0] on the upper hemisphere."""
    wall = np.array([[[0.1, -1e4, 0.0], [0.1, 1e4, 0.0], [0.1, 1e4, 1e4]],
                     [[0.1, -1e4, 0.0], [0.1, 1e4, 1e4], [0.1, -1e4, 1e4]]])
    rs = RayScene(np.concatenate([quad(0.0, 1e4), wall]))
    n = 400
    pts = floor_points(n, spread=1e-9)
    pts.position[:, :2] = 0.0
    ref = hemisphere_integral(lambda d: np.clip(d[:, 2], 0, None) * (d[:, 0] < 0), (0, 0, 1))
    out, _ = bake_points(rs, pts, TransferSettings(rays=1024, analytic=False))
    # n independent estimates (random patterns/azimuths) of the same texel:
    # their mean converges, their spread is the Monte Carlo error.
    mean = out.mean(axis=0)
    se = out.std(axis=0) / math.sqrt(n)
    assert np.all(np.abs(mean - ref) <= 5 * se + 1e-4)
    assert np.abs(out - ref).max() < 0.05


def test_inside_closed_box_is_dark():
    from prtt_addon.dev.bench import meshgen as mg
    box = mg.box((2, 2, 2)).corner_positions()
    rs = RayScene(box)
    pts = floor_points(200, z=-0.5, spread=0.8)
    out, _ = bake_points(rs, pts, TransferSettings(rays=256, analytic=False))
    assert np.abs(out).max() <= 1e-6


def test_rays_below_geometric_horizon_are_skipped(rng):
    """A tilted shading normal on a flat floor: the part of its hemisphere below
    the floor counts as blocked without tracing; the result is the clamped
    cosine restricted to the upper half-space."""
    rs = RayScene(quad(0.0, 1e4))
    n = 200
    tilt = np.array([math.sin(0.6), 0.0, math.cos(0.6)])
    pts = floor_points(n, spread=1e-9)
    pts.normal[:] = tilt
    out, info = bake_points(rs, pts, TransferSettings(rays=1024, analytic=False))
    assert info["rays_below_horizon_skipped"] > 0
    assert info["rays_traced"] + info["rays_below_horizon_skipped"] == n * 1024
    ref = hemisphere_integral(lambda d: np.clip(d @ tilt, 0, None) * (d[:, 2] > 0), tilt)
    mean = out.mean(axis=0)
    se = out.std(axis=0) / math.sqrt(n)
    assert np.all(np.abs(mean - ref) <= 5 * se + 1e-4)
