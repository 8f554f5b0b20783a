"""Monte Carlo behaviour of the transfer bake: convergence, determinism, threads,
adaptive sampling, scale robustness, contacts, shared frames."""
import functools
import math

import numpy as np
import pytest

from prtt_addon.core.bake.estimators.raytrace import RayScene
from prtt_addon.core.bake.estimators.transfer import (
    Points,
    TransferSettings,
    bake_points,
    chunk_plan,
    unoccluded_transfer,
)
from prtt_addon.core.bake.pipeline.context import BakeSettings
from prtt_addon.core.bake.pipeline.stages import bake_points_input, scene_face_data
from prtt_addon.core.texels.gbuffer import build_gbuffer
from tests.scenes_util import floor_and_box
from tests.test_transfer_analytic import floor_points, hemisphere_integral, quad

WALL = np.array([[[0.1, -1e3, 0.0], [0.1, 1e3, 0.0], [0.1, 1e3, 1e3]],
                 [[0.1, -1e3, 0.0], [0.1, 1e3, 1e3], [0.1, -1e3, 1e3]]])


def wall_scene():
    rs = RayScene(np.concatenate([quad(0.0, 1e3), WALL]))
    ref = hemisphere_integral(lambda d: np.clip(d[:, 2], 0, None) * (d[:, 0] < 0), (0, 0, 1))
    return rs, ref


@pytest.mark.parametrize("sampler,estimator,lo,hi", [
    ("random", "plain", 0.4, 0.62),            # textbook Monte Carlo: 1/sqrt(N)
    ("sobol", "balanced", 0.45, 1.2),          # stratified + control variate: at least as fast
])
def test_error_follows_inverse_sqrt_n(sampler, estimator, lo, hi):
    rs, ref = wall_scene()
    n_pts = 600
    errs = []
    Ns = [16, 64, 256, 1024]
    for N in Ns:
        pts = floor_points(n_pts, spread=1e-9)
        pts.position[:, :2] = 0.0
        out, _ = bake_points(rs, pts, TransferSettings(rays=N, sampler=sampler, estimator=estimator,
                                                       analytic=False))
        errs.append(math.sqrt(np.mean((out - ref) ** 2)))
    slope = -np.polyfit(np.log(Ns), np.log(errs), 1)[0]
    assert lo <= slope <= hi, (errs, slope)


def test_same_inputs_bit_identical_any_thread_count():
    sc = floor_and_box(res=48)
    rs = RayScene(sc.positions)
    fn, grp, clear, _ = scene_face_data(sc)
    outs = []
    for threads in (1, 2, 1):
        gb = build_gbuffer(sc, 0)
        pts = bake_points_input(sc, 0, gb, fn, clear, grp)
        out, info = bake_points(rs, pts, TransferSettings(rays=128, threads=threads, chunk_rays=4096))
        outs.append(out)
        assert info["threads"] == threads
    assert all(np.array_equal(outs[0], o) for o in outs[1:])


def test_seed_changes_noise_not_mean():
    rs, ref = wall_scene()
    pts = floor_points(300, spread=1e-9)
    pts.position[:, :2] = 0.0
    a, _ = bake_points(rs, pts, TransferSettings(rays=256, seed=1, analytic=False))
    b, _ = bake_points(rs, pts, TransferSettings(rays=256, seed=2, analytic=False))
    assert not np.array_equal(a, b)
    assert np.abs(a.mean(0) - b.mean(0)).max() < 0.01


def test_adaptive_stops_early_and_stays_accurate():
    rs, ref = wall_scene()
    pts = floor_points(400, spread=1e-9)
    pts.position[:, :2] = 0.0
    # Half the points float above everything, facing up: nothing to hit.
    pts.position[200:, 2] = 2e3
    st = TransferSettings(rays=1024, adaptive_tol=0.004, min_rays=64, analytic=False)
    out, info = bake_points(rs, pts, st)
    assert info["adaptive_early_stops"] >= 200
    assert info["rays_traced"] < 0.6 * info["rays_naive"]
    fixed, _ = bake_points(rs, pts, TransferSettings(rays=1024, analytic=False))
    rms_adaptive = math.sqrt(np.mean((out[:200] - ref) ** 2))
    rms_fixed = math.sqrt(np.mean((fixed[:200] - ref) ** 2))
    assert rms_adaptive < max(3 * rms_fixed, 0.01)
    assert np.abs(out[200:] - unoccluded_transfer(pts.normal[200:], 5)).max() < 1e-5


def _box_on_floor(scale):
    sc = floor_and_box(scale=scale, res=32, subdiv=8)
    rs = RayScene(sc.positions)
    fn, grp, clear, _ = scene_face_data(sc)
    gb = build_gbuffer(sc, 0)
    pts = bake_points_input(sc, 0, gb, fn, clear, grp)
    out, _ = bake_points(rs, pts, TransferSettings(rays=256))
    return sc, gb, pts, out


@functools.lru_cache(maxsize=1)
def _unit_scale_transfer():
    return _box_on_floor(1.0)[3]


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e4])
def test_scale_invariant_no_acne_no_leaks(scale):
    """A box on a floor, from millimetres to kilometres: the same transfer, floor
    texels under the box dark (no leak), a lone tessellated floor unoccluded (no acne).
    Every scale is compared with the unit scale's bake (computed here whatever
    order or subset of the parametrisations runs)."""
    sc, gb, pts, out = _box_on_floor(scale)
    ref = _unit_scale_transfer()
    assert ref.shape == out.shape
    assert np.abs(out - ref).max() < 2e-3
    # Floor texel centres strictly inside the box footprint (|x|, |y| < 0.5 scale).
    p = gb.position / scale
    under = (np.abs(p[:, 0]) < 0.45) & (np.abs(p[:, 1]) < 0.45)
    assert under.sum() > 0
    assert np.abs(out[under]).max() <= 1e-5
    # The floor alone: every texel unoccluded, traced exactly.
    rs_floor = RayScene(sc.positions[sc.set_id == 0])
    pts.analytic[:] = False
    alone, _ = bake_points(rs_floor, pts, TransferSettings(rays=256))
    assert np.abs(alone - unoccluded_transfer(pts.normal, 5)).max() <= 1e-5


def test_shared_frames_agree_with_per_point_frames():
    """Flat texels traced with shared frames and with their own frames agree
    within Monte Carlo error (same estimator, different patterns)."""
    sc = floor_and_box(res=192)
    rs = RayScene(sc.positions)
    fn, grp, clear, _ = scene_face_data(sc)
    gb = build_gbuffer(sc, 0)
    pts = bake_points_input(sc, 0, gb, fn, clear, grp)
    st = TransferSettings(rays=256)
    chunks, _ = chunk_plan(pts, st)
    assert sum(c.idx.size for c in chunks if c.shared) > 0.9 * pts.n
    shared, _ = bake_points(rs, pts, st)
    solo_pts = Points(pts.position, pts.normal, pts.geo_normal, pts.ids, pts.analytic, None)
    assert not any(c.shared for c in chunk_plan(solo_pts, st)[0])
    solo, _ = bake_points(rs, solo_pts, st)
    d = shared - solo
    assert abs(d.mean()) < 2e-3
    assert math.sqrt(np.mean(d ** 2)) < 0.02


def test_threads_use_both_cores():
    sc = floor_and_box(res=64)
    rs = RayScene(sc.positions)
    fn, grp, clear, _ = scene_face_data(sc)
    pts = bake_points_input(sc, 0, build_gbuffer(sc, 0), fn, clear, grp)
    _, info = bake_points(rs, pts, BakeSettings(rays=64, threads=2, chunk_rays=2048))
    assert info["threads"] == 2


@pytest.mark.parametrize("hi", [7, 70_000])
def test_chunk_plan_ordering_equals_stable_argsort(hi):
    """The radix path (keys < 2^16) and the fallback both give numpy's stable order."""
    from prtt_addon.core.bake.estimators.transfer import _stable_order
    rng = np.random.default_rng(hi)
    major, minor = rng.integers(0, hi, 50_000), rng.integers(0, 64, 50_000)
    assert np.array_equal(_stable_order(major, minor), np.argsort(major * 64 + minor, kind="stable"))
    assert np.array_equal(_stable_order(major), np.argsort(major, kind="stable"))
    assert _stable_order(major[:0], minor[:0]).size == 0
