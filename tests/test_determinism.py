"""A bake's bits do not depend on how its work is scheduled (issue #38).

A cluster bake is the local bake's chunks run elsewhere: the client writes
each chunk's rows (texture columns) as its unit arrives, so the files are
the same bits whatever the order units finish in, provided that

1. every texel's rays lie in exactly one chunk (no sum across chunks or
   units: :func:`test_a_texels_rays_never_span_chunks_or_units`);
2. a chunk's result depends on the chunk alone: not on the order chunks run
   in, the thread that runs them, what that thread ran before (its scratch
   buffers), or where in memory the inputs lie (a Dask worker's come out of
   deserialisation at other addresses): the tests below;
3. tests/test_distributed.py: the cluster's units handed over in a forced,
   shuffled order, and a worker killed mid-bake, give the local files.

The issue's own case (a floor and a sphere, 384², 256 rays, a relightable
bounce, float storage, four cluster runs) could not be reproduced; what it
reported (an order-dependent sum) is ruled out by (1)-(2) for both bounce
modes and both storages.
"""
import dataclasses
import hashlib
import os
import random
import threading

import numpy as np
import pytest

from prtt_addon.core.bake.estimators import bounce, transfer
from prtt_addon.core.bake.estimators.raytrace import RayScene
from prtt_addon.core.bake.estimators.transfer import ChunkKernel, Points, TransferSettings, chunk_plan
from prtt_addon.core.bake.executors import dask_cluster as dd
from prtt_addon.core.bake.pipeline.context import BakeSettings
from prtt_addon.core.bake.pipeline.runner import bake_scene
from prtt_addon.core.bake.pipeline.stages import bake_points_input, scene_face_data
from prtt_addon.core.base import threads as base_threads
from prtt_addon.core.light.envmap import environment_light
from prtt_addon.core.texels.gbuffer import build_gbuffer
from prtt_addon.dev.bench import meshgen as mg


@pytest.fixture(scope="module")
def scene():
    """A floor (flat: shared-frame chunks at 96², where a frame group's
    pattern buckets reach transfer.SHARED_MIN texels), a flat-shaded
    icosphere (frame groups too small to share) and a smooth UV sphere (a
    frame per texel) on it."""
    return mg.assemble([("floor", mg.plane(4.0, subdiv=2)),
                        ("ico", mg.icosphere(0.5, subdiv=2, smooth=False).transformed(translate=(-0.8, 0, 0.5))),
                        ("sphere", mg.uv_sphere(0.5, 24, 12).transformed(translate=(0.8, 0, 0.5)))],
                       resolution=40, atlas=False, resolutions={"floor": 96})


def files(folder) -> dict:
    return {n: hashlib.sha256((folder / n).read_bytes()).hexdigest() for n in sorted(os.listdir(folder))
            if n.endswith((".exr", ".npz"))}


def set_points(sc, s):
    fn, grp, clear, _ = scene_face_data(sc)
    gb = build_gbuffer(sc, s)
    return bake_points_input(sc, s, gb, fn, clear, grp)


def elsewhere(a: np.ndarray, offset: int) -> np.ndarray:
    """A copy of ``a`` at ``offset`` bytes past a 64-byte boundary (aligned
    to its item size, as numpy requires, but not to a cache line or SIMD width)."""
    a = np.ascontiguousarray(a)
    buf = np.empty(a.nbytes + 128, np.uint8)
    start = (-buf.ctypes.data) % 64 + offset
    out = np.frombuffer(buf.data, a.dtype, a.size, start).reshape(a.shape)
    out[...] = a
    return out


@pytest.mark.parametrize("rays, chunk_rays", [(256, 1 << 19), (256, 4096), (64, 2048)])
def test_a_texels_rays_never_span_chunks_or_units(scene, rays, chunk_rays):
    """Every traced texel of every set is in exactly one chunk, with all its
    rays (a chunk is a list of texels); a Dask unit is whole chunks, also when
    units hold fewer rays than one chunk."""
    st = TransferSettings(rays=rays, chunk_rays=chunk_rays)
    for s in range(scene.n_sets):
        pts = set_points(scene, s)
        chunks, _ = chunk_plan(pts, st)
        ids = np.concatenate([c.idx for c in chunks])
        traced = np.flatnonzero(~pts.analytic)
        assert ids.size == traced.size and np.array_equal(np.sort(ids), traced)
        assert any(c.shared for c in chunks) == (s == 0)
        for unit_rays in (1, rays * 3, 1 << 15):
            units = dd.units_of(chunks, rays, 2, unit_rays)
            assert [c for u in units for c in u] == chunks


@pytest.mark.parametrize("adaptive", [0.0, 0.02])
def test_a_chunk_depends_only_on_itself(scene, adaptive):
    """Each chunk's rows, bit for bit: planned order on a fresh kernel; reversed
    order on one kernel (its per-thread scratch grown by earlier chunks) on
    another thread; and a kernel whose points and BVH vertices lie at other
    addresses (what a Dask worker receives)."""
    st = TransferSettings(rays=128, chunk_rays=2048, adaptive_tol=adaptive, min_rays=32)
    for s in range(scene.n_sets):
        pts = set_points(scene, s)
        chunks, G = chunk_plan(pts, st)
        assert len(chunks) > 4
        rs = RayScene(scene.positions)
        ref = [ChunkKernel(rs, pts, st, G).run(c)[0] for c in chunks]

        kernel = ChunkKernel(rs, pts, st, G)
        rev = {}

        def backwards(kernel=kernel, chunks=chunks, rev=rev):
            rev.update({i: kernel.run(chunks[i])[0] for i in reversed(range(len(chunks)))})

        t = threading.Thread(target=backwards)
        t.start()
        t.join()
        moved = Points(**{f.name: None if getattr(pts, f.name) is None else elsewhere(getattr(pts, f.name), 8)
                          for f in dataclasses.fields(pts)})
        far = ChunkKernel(RayScene(elsewhere(scene.positions, 24)), moved, st, G)
        for i, c in enumerate(chunks):
            assert np.array_equal(ref[i], rev[i]), (s, i)
            assert np.array_equal(ref[i], far.run(c)[0]), (s, i)


@pytest.mark.parametrize("mode, half", [("baked", True), ("baked", False), ("relightable", True),
                                        ("relightable", False)])
def test_files_do_not_depend_on_chunk_order_or_threads(scene, tmp_path, monkeypatch, mode, half):
    """The whole bake (transfer, per-vertex transfer, two bounce levels) with
    its chunks run in two seeded shuffled orders, on one thread and on two,
    gives the planned order's files byte for byte."""
    light = environment_light("forest", 5, 1.0, 0.0)
    st = dict(rays=64, chunk_rays=2048, bounces=2, bounce_rays=32, bounce_tolerance=0.0, bounce_mode=mode,
              half=half, vertex_mode=True)
    bake_scene(scene, tmp_path / "planned", BakeSettings(**st), light=light)
    real = base_threads.run_chunks
    for seed, threads in ((1, 1), (2, 2)):
        calls = []

        def shuffled(fn, items, n_threads, on_result=None, cancel=None, seed=seed, calls=calls):
            items = list(items)
            random.Random(seed + len(calls)).shuffle(items)
            calls.append(len(items))
            return real(fn, items, n_threads, on_result, cancel)

        monkeypatch.setattr(transfer, "run_chunks", shuffled)
        monkeypatch.setattr(bounce, "run_chunks", shuffled)
        out = tmp_path / f"shuffled{seed}"
        bake_scene(scene, out, BakeSettings(threads=threads, **st), light=light)
        monkeypatch.undo()
        assert sum(n > 2 for n in calls) >= 4, calls       # the sets' transfer and both levels were shuffled
        assert files(tmp_path / "planned") == files(out), (seed, threads)
