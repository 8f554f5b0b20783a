"""Guided rays (core/bake/estimators/guided.py, issue 53 item 1), against the
exact light through an opening and against the bake without them.

The scene: a closed 4 x 4 x 2.5 m room whose only opening is a 1.0 x 0.6 m
hole in its ceiling. A floor point's transfer DC is sqrt(pi)/2 times its view
factor to the hole, which has a closed form (a differential area to a
parallel rectangle, summed over the four corner rectangles with signs).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from prtt_addon.core.bake.estimators import guided
from prtt_addon.core.bake.estimators.raytrace import RayScene
from prtt_addon.core.bake.estimators.transfer import Points, TransferSettings, bake_points

H = 2.5                       # ceiling height
HOLE = (-0.5, 0.5, -0.3, 0.3)  # x0, x1, y0, y1 of the opening


def _quad(a, b, c, d):
    return [[a, b, c], [a, c, d]]


def room_triangles() -> np.ndarray:
    X = 2.0
    tris = []
    tris += _quad((-X, -X, 0), (X, -X, 0), (X, X, 0), (-X, X, 0))
    for (x0, y0), (x1, y1) in [((-X, -X), (X, -X)), ((X, -X), (X, X)), ((X, X), (-X, X)), ((-X, X), (-X, -X))]:
        tris += _quad((x0, y0, 0), (x1, y1, 0), (x1, y1, H), (x0, y0, H))
    hx0, hx1, hy0, hy1 = HOLE
    # The ceiling around the hole: four rectangles.
    for xa, xb, ya, yb in [(-X, X, -X, hy0), (-X, X, hy1, X), (-X, hx0, hy0, hy1), (hx1, X, hy0, hy1)]:
        tris += _quad((xa, ya, H), (xb, ya, H), (xb, yb, H), (xa, yb, H))
    return np.asarray(tris, np.float64)


def view_factor(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """View factor from an up-facing differential area at (x, y, 0) to the hole at height H."""
    def corner(a, b):      # odd in a and in b: the signed corner rectangle [0, a] x [0, b]
        ra, rb = np.sqrt(H * H + a * a), np.sqrt(H * H + b * b)
        return (a / ra * np.arctan(b / ra) + b / rb * np.arctan(a / rb)) / (2.0 * math.pi)
    x0, x1, y0, y1 = HOLE
    return (corner(x1 - x, y1 - y) - corner(x0 - x, y1 - y) - corner(x1 - x, y0 - y)
            + corner(x0 - x, y0 - y))


def floor_points(side: int = 96) -> Points:
    g = np.linspace(-1.9, 1.9, side)
    x, y = np.meshgrid(g, g)
    n = x.size
    pos = np.stack([x.ravel(), y.ravel(), np.zeros(n)], axis=-1)
    up = np.tile([0.0, 0.0, 1.0], (n, 1))
    return Points(pos, up, up.copy(), np.arange(n, dtype=np.int64), np.zeros(n, bool), area=3.8 * 3.8)


@pytest.fixture(scope="module")
def room():
    return RayScene(room_triangles()), floor_points()


def test_view_factor_formula_against_quadrature():
    """The closed form against a brute-force integral over the hole (scipy-free midpoint rule)."""
    x0, x1, y0, y1 = HOLE
    u = np.linspace(x0, x1, 801)
    v = np.linspace(y0, y1, 481)
    um, vm = (u[1:] + u[:-1]) / 2, (v[1:] + v[:-1]) / 2
    for px, py in [(0.0, 0.0), (1.3, -0.7), (-1.8, 1.9)]:
        dx, dy = um[None, :] - px, vm[:, None] - py
        r2 = dx * dx + dy * dy + H * H
        f = (H * H / (math.pi * r2 * r2)).sum() * (u[1] - u[0]) * (v[1] - v[0])
        assert view_factor(np.array(px), np.array(py)) == pytest.approx(f, rel=1e-5)


def test_guided_is_unbiased_and_quieter_than_cosine_rays(room):
    rs, pts = room
    exact = math.sqrt(math.pi) / 2 * view_factor(pts.position[:, 0], pts.position[:, 1])
    on, info = bake_points(rs, pts, TransferSettings(rays=256, guiding=True, analytic=False))
    off, _ = bake_points(rs, pts, TransferSettings(rays=256, guiding=False, analytic=False))
    # Every floor point sees the sky through the hole only: all are guided.
    # One point in PILOT_EVERY sends the pilot rays.
    assert info["guided_points"] == pts.n
    assert info["pilot_rays"] == pytest.approx(pts.n * guided.PILOT_RAYS / guided.PILOT_EVERY, rel=0.05)
    err_on = (on[:, 0] - exact) / exact
    err_off = (off[:, 0] - exact) / exact
    rms_on, rms_off = np.sqrt(np.mean(err_on ** 2)), np.sqrt(np.mean(err_off ** 2))
    # Unbiased: the mean error within 4 standard errors of zero (and small).
    assert abs(err_on.mean()) < 4 * err_on.std() / math.sqrt(pts.n) + 1e-3, (err_on.mean(), err_on.std())
    # Quieter: measured RMS 6.2 % against 25.8 %, mean error -0.007 % (cosine rays find the hole by chance).
    assert rms_on < 0.35 * rms_off, (rms_on, rms_off)
    assert rms_on < 0.1, rms_on


def hole_transfer(point: np.ndarray, bands: int = 5, n: int = 96) -> np.ndarray:
    """(K,) transfer of an up-facing floor point: the integral over the hole of
    y_k(w) cos(theta_p) cos(theta_hole) / r^2 dA (midpoint rule, n x n cells);
    nothing else is in the way inside the room."""
    from prtt_addon.core.sh.basis import eval_basis
    x0, x1, y0, y1 = HOLE
    u = x0 + (np.arange(n) + 0.5) * (x1 - x0) / n
    v = y0 + (np.arange(n) + 0.5) * (y1 - y0) / n
    X, Y = np.meshgrid(u, v)
    d = np.stack([X.ravel() - point[0], Y.ravel() - point[1], np.full(X.size, H - point[2])], axis=-1)
    r = np.linalg.norm(d, axis=1)
    w = d / r[:, None]
    weight = w[:, 2] * w[:, 2] / r ** 2 * ((x1 - x0) * (y1 - y0) / n / n)
    return weight @ eval_basis(w, bands)


def test_every_coefficient_is_unbiased(room):
    """All 25 coefficients against the hole's integral: each one's mean error
    over 300 points within 4 standard errors (the DC test above checks one)."""
    rs, pts = room
    on, _ = bake_points(rs, pts, TransferSettings(rays=256, guiding=True, analytic=False))
    rng = np.random.default_rng(5)
    pick = rng.choice(pts.n, 300, replace=False)
    exact = np.stack([hole_transfer(pts.position[i]) for i in pick])
    assert np.abs(hole_transfer(np.zeros(3))[0] - math.sqrt(math.pi) / 2 * view_factor(np.array(0.0), np.array(0.0))) < 1e-4
    err = on[pick].astype(np.float64) - exact
    se = err.std(axis=0) / math.sqrt(pick.size)
    scale = np.abs(exact).mean(axis=0).max()
    assert np.all(np.abs(err.mean(axis=0)) < 4 * se + 1e-3 * scale), (err.mean(axis=0) / se)


def test_same_rows_for_any_threads_and_chunks(room):
    rs, pts = room
    a, _ = bake_points(rs, pts, TransferSettings(rays=64, threads=1, chunk_rays=1 << 19))
    b, _ = bake_points(rs, pts, TransferSettings(rays=64, threads=2, chunk_rays=1 << 12))
    assert np.array_equal(a, b)


def test_open_and_closed_scenes_bake_as_without_guiding():
    """Where no cell escapes at a rate in (0, OPEN_MAX], no point is guided and
    the rows are the unguided bake's, bit for bit: an open floor, a closed box."""
    rs_closed = RayScene(np.concatenate([room_triangles(), np.asarray(
        _quad((-0.5, -0.3, H), (0.5, -0.3, H), (0.5, 0.3, H), (-0.5, 0.3, H)), np.float64)]))
    X = 2.0
    rs_open = RayScene(np.asarray(_quad((-X, -X, 0), (X, -X, 0), (X, X, 0), (-X, X, 0)), np.float64))
    pts = floor_points(24)
    for rs in (rs_closed, rs_open):
        a, info = bake_points(rs, pts, TransferSettings(rays=64, guiding=True, analytic=False))
        b, _ = bake_points(rs, pts, TransferSettings(rays=64, guiding=False, analytic=False))
        assert info["guided_points"] == 0
        assert np.array_equal(a, b)


def test_guide_memory_is_bounded():
    """Cells are capped (the voxel edge doubles), so the tables stay within
    guide_bytes whatever the point count."""
    rng = np.random.default_rng(1)
    n = 200_000
    pos = rng.uniform(-1, 1, (n, 3))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    cell, keys = guided.cell_ids(pos, nrm, np.arange(n), area=1e-6)     # a tiny area asks for tiny cells
    assert keys.size <= guided.MAX_CELLS and cell.max() + 1 == keys.size
    assert guided.guide_bytes(n) < 64 << 20


def test_texels_not_guided_keep_their_rows():
    """The demo room (128²): guiding changes the guided texels' rows only; the
    others, shared frames included, are the unguided bake's, bit for bit."""
    from prtt_addon.core.bake.pipeline.stages import bake_points_input, scene_face_data
    from prtt_addon.core.texels.gbuffer import build_gbuffer
    from prtt_addon.dev.bench.scene_library import room_scene

    sc = room_scene(128, atlas=True, materials=True)
    fn, grp, clear, _ = scene_face_data(sc)
    pts = bake_points_input(sc, 0, build_gbuffer(sc, 0), fn, clear, grp)
    rs = RayScene(sc.positions)
    on, info = bake_points(rs, pts, TransferSettings(rays=64, guiding=True))
    off, _ = bake_points(rs, pts, TransferSettings(rays=64, guiding=False))
    guide = guided.build_guide(rs, pts.position, pts.normal, pts.geo_normal, pts.ids, ~pts.analytic, pts.area,
                               0, 2, 1 << 19)
    hit = guide.cell >= 0
    assert 0 < info["guided_points"] == hit.sum() < pts.n // 4
    # Bit for bit where BLAS gives a row the same bits whatever its chunk's height
    # (the guided texels leave their chunks shorter); OpenBLAS on an AMD EPYC picks
    # other kernels by height: 903 of 2,809 rows differ there, by at most 3.6e-7.
    # Either way a changed row is a few float32 roundings of the sums' scale (the
    # unoccluded DC is sqrt(pi)/2: terms of order 1, near-zero rows by cancellation).
    assert np.abs(on[~hit] - off[~hit]).max() <= 8 * np.finfo(np.float32).eps
    assert not np.allclose(on[hit], off[hit], rtol=0, atol=1e-4)


def test_many_rays_at_many_bands_project_in_pieces(room, monkeypatch):
    """A point whose visible rays outgrow a projection group is summed in
    pieces (bounded memory at 16 bands and many rays): the same transfer as
    in one piece, to float32 rounding."""
    rs, pts = room
    st = TransferSettings(rays=512, bands=6, guiding=True, analytic=False, threads=1)
    whole, _ = bake_points(rs, pts, st)
    monkeypatch.setattr(guided, "PROJECT_BYTES", 8 * 36 * 40)     # 40 rays a piece at 36 coefficients
    sizes = []
    basis = guided.basis_unchecked
    monkeypatch.setattr(guided, "basis_unchecked", lambda d, *a, **k: sizes.append(len(d)) or basis(d, *a, **k))
    pieces, _ = bake_points(rs, pts, st)
    # Every projection held at most 40 rays, and points were split: more pieces than points.
    assert max(sizes) <= 40 and len(sizes) > pts.n
    np.testing.assert_allclose(pieces, whole, rtol=0, atol=2e-6 * float(np.abs(whole).max()))


def test_inversion_matches_a_per_sample_search():
    """guided._invert (one integer search over every row) against each sample
    inverted alone in its own row: the same bin, the same place in it."""
    from prtt_addon.core.bake.estimators.guided import _invert
    rng = np.random.default_rng(4)
    p = rng.random((7, 32)) * (rng.random((7, 32)) < 0.3)
    p[:, 5] += 0.01
    cdf = np.cumsum(p / p.sum(axis=1, keepdims=True), axis=1).astype(np.float32)
    cdf[:, -1] = 1.0
    group = rng.integers(0, 7, 5000)
    u = rng.random(5000)
    u[:10] = 0.0
    b, f = _invert(cdf, group, u)
    for k in range(u.size):
        row = np.round(cdf[group[k]].astype(np.float64) * 2.0 ** 32)
        bk = min(int(np.searchsorted(row, np.floor(u[k] * 2.0 ** 32), side="right")), 31)
        lo = float(cdf[group[k], bk - 1]) if bk else 0.0
        width = float(cdf[group[k], bk]) - lo
        assert b[k] == bk
        assert f[k] == (min(max((u[k] - lo) / width, 0.0), np.nextafter(1.0, 0.0)) if width > 0 else 0.0)


def test_coefficient_major_projection_sums_as_the_row_major_one():
    """guided_transfer's projection: reduceat along each point's rays of the
    (K, rays) basis gives the bits the (rays, K) basis summed over rows gave,
    for segments of 1 to ~3000 rays."""
    from prtt_addon.core.sh.basis import basis_unchecked
    rng = np.random.default_rng(5)
    d = rng.normal(size=(60_000, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    w = rng.random(60_000).astype(np.float32)
    starts = np.unique(np.r_[0, rng.integers(1, 60_000, 300), np.arange(1, 40)])
    rows = basis_unchecked(d, 5, np.float32)
    rows *= w[:, None]
    cols = basis_unchecked(d, 5, np.float32, coeff_major=True)
    cols *= w[None, :]
    assert np.add.reduceat(rows, starts, axis=0).tobytes() == np.ascontiguousarray(
        np.add.reduceat(cols, starts, axis=1).T).tobytes()
