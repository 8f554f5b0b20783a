"""Surface texels built at the valid texels' rows (#35): texels.dilate.dilate_rows
fills rows with the same values, bit for bit, as the planes' dilation
(texels.dilate.dilate, the reference), and bounce.surface_texels, which now
uses it, returns what the planes-then-gather construction returned."""
import sys

import numpy as np
import pytest

from prtt_addon.core.bake.estimators.bounce import surface_texels
from prtt_addon.core.shading.materials import eval_materials
from prtt_addon.core.texels.dilate import dilate, dilate_rows, dilation_rings
from prtt_addon.core.texels.gbuffer import build_gbuffer
from prtt_addon.dev.bench.scene_library import room_scene
from tests.scenes_util import random_islands


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("iterations", [0, 1, 3, 6])
def test_dilate_rows_equals_the_planes_dilation(dtype, iterations):
    rng = np.random.default_rng(iterations)
    H, W = 37, 53
    m = random_islands(rng, H, W, rects=10, most=11, margin=3, singles=15)
    planes = np.zeros((4, H, W), dtype)
    planes[:, m] = rng.normal(size=(4, int(m.sum()))) * 10.0 ** rng.integers(-30, 30, size=(4, 1))
    ref = planes.copy()
    grown = dilate(ref, m, iterations)
    rings, grown2 = dilation_rings(m, iterations)
    assert np.array_equal(grown, grown2)
    valid = np.flatnonzero(grown)
    row_of = np.full(H * W, valid.size, np.int32)
    row_of[valid] = np.arange(valid.size, dtype=np.int32)
    flat = planes.reshape(4, -1)
    rows3 = np.ascontiguousarray(flat[:3, valid].T)      # (M, 3)
    rows1 = np.ascontiguousarray(flat[3, valid])         # (M,)
    dilate_rows([rows3, rows1], row_of, W, rings)
    want = ref.reshape(4, -1)[:, valid]
    assert rows3.tobytes() == np.ascontiguousarray(want[:3].T).tobytes()
    assert rows1.tobytes() == np.ascontiguousarray(want[3]).tobytes()


def _planes_reference(sc, gb, iterations, diffuse_only):
    """The construction surface_texels replaced: (channels, H, W) float64 planes, dilated, gathered."""
    H, W = gb.height, gb.width
    n = 3 if diffuse_only else 10
    planes = np.zeros((n, H * W))
    p = eval_materials(sc, gb.tri, gb.bary)
    planes[0:3, gb.texel] = p.albedo.T
    if not diffuse_only:
        planes[3:6, gb.texel] = p.spec.T
        planes[6, gb.texel] = p.exponent
        planes[7:10, gb.texel] = gb.normal.T
    grown = dilate(planes.reshape(n, H, W), gb.mask(), iterations).reshape(-1)
    valid = np.flatnonzero(grown)
    rows = planes[:, valid].T
    out = {"valid": valid, "albedo": rows[:, 0:3]}
    if not diffuse_only:
        nn = rows[:, 7:10]
        out.update(spec=rows[:, 3:6], exponent=rows[:, 6],
                   normal=nn / np.maximum(np.linalg.norm(nn, axis=1, keepdims=True), 1e-300))
    return out


@pytest.mark.parametrize("diffuse_only", [False, True])
def test_surface_texels_match_the_planes_construction(diffuse_only):
    sc = room_scene(48, atlas=True, materials=True)
    for res in ((48, 48), (40, 56)):
        gb = build_gbuffer(sc, 0, resolution=res)
        for iterations in (0, 2):
            got = surface_texels(sc, gb, iterations, diffuse_only=diffuse_only)
            want = _planes_reference(sc, gb, iterations, diffuse_only)
            assert np.array_equal(got.valid, want["valid"])
            assert np.array_equal(got.row_of[got.valid], np.arange(got.valid.size))
            assert (np.delete(got.row_of, got.valid) == got.valid.size).all()
            for f, v in want.items():
                assert np.ascontiguousarray(getattr(got, f)).tobytes() == np.ascontiguousarray(v).tobytes(), f
            assert got.glossy == (not diffuse_only and bool((want.get("spec", np.zeros(1)) > 0).any()))


@pytest.mark.parametrize("seed", [1, 2])
def test_a_consumed_incident_set_copies_the_same_rows_and_gives_its_pages_back(monkeypatch, seed):
    """IncidentSet.at(..., consume=True) (the coarse grid's set, taken at the
    surface's texels, #35): the rows at(...) copies, zeros where the set has
    none, a block at a time, the set's pages given back behind it."""
    from prtt_addon.core.bake.estimators.bounce import IncidentSet
    monkeypatch.setattr(IncidentSet, "AT_BLOCK", 5000)
    rng = np.random.default_rng(seed)
    H, W, C = 300, 400, 25
    valid = np.flatnonzero(rng.random(H * W) < 0.7)
    rows = np.zeros((valid.size + 1, C), np.float32)
    rows[:-1] = rng.standard_normal((valid.size, C))
    # The surface's texels: most of the set's, some it lacks, some it has that they lack.
    texels = np.flatnonzero((rng.random(H * W) < 0.7) | np.isin(np.arange(H * W), valid[::3]))
    want = IncidentSet(rows.copy(), valid, W, H).at(texels, padded=True)
    s = IncidentSet(rows, valid, W, H)
    got = s.at(texels, padded=True, consume=True)
    assert got.tobytes() == want.tobytes()
    if sys.platform.startswith("linux"):          # madvise zeroes given-back pages there
        assert np.count_nonzero(s.rows) < 0.05 * s.rows.size
