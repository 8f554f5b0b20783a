"""The zero-ray analytic path's triangle test vs brute force, and occluder-only triangles."""
import numpy as np

from prtt_addon.core.bake.estimators.hemisphere_clear import PLANE_EPSILON, clear_triangles
from prtt_addon.core.bake.pipeline.context import BakeSettings
from prtt_addon.core.bake.pipeline.runner import bake_scene
from prtt_addon.core.bake.pipeline.stages import scene_face_data
from prtt_addon.core.texels.gbuffer import face_normals
from prtt_addon.dev.bench import meshgen as mg
from tests.scenes_util import floor_and_box


def brute_force(P, n):
    V = P.reshape(-1, 3)
    lo, hi = V.min(0), V.max(0)
    c, h = 0.5 * (lo + hi), 0.5 * (hi - lo).max()
    Vn = (V - c) / h
    out = np.zeros(P.shape[0], bool)
    for t in range(P.shape[0]):
        if not n[t].any():
            continue
        out[t] = np.max(Vn @ n[t]) - n[t] @ ((P[t, 0] - c) / h) <= PLANE_EPSILON
    return out


def test_matches_brute_force_on_mixed_geometry(rng):
    objs = [mg.box((1, 1, 1), (0, 0, 0.5)), mg.icosphere(0.4, 2, smooth=False).transformed(translate=(2, 0, 0.4)),
            mg.plane(6.0), mg.torus(0.5, 0.15, 16, 8).transformed(translate=(-2, 1, 0.15))]
    P = np.concatenate([m.corner_positions() for m in objs])
    fn, _ = face_normals(P)
    clear, stats = clear_triangles(P, fn)
    np.testing.assert_array_equal(clear, brute_force(P, fn))
    assert stats["clear_triangles"] > 0
    # the box's top (triangles 2, 3; the highest face) is clear, the floor is not
    assert clear[2:4].all()
    n_ico = objs[1].n_faces
    assert not clear[12 + n_ico:12 + n_ico + 2].any()


def test_convex_object_alone_is_entirely_clear():
    ico = mg.icosphere(1.0, 3, smooth=False)
    P = ico.corner_positions()
    fn, _ = face_normals(P)
    clear, _ = clear_triangles(P, fn)
    assert clear.all()
    # turned inward, nothing is clear (the rest of the sphere is above every face)
    clear_in, _ = clear_triangles(P, -fn)
    assert not clear_in.any()


def test_budget_never_claims_clear():
    ico = mg.icosphere(1.0, 3, smooth=False)
    P = ico.corner_positions()
    fn, _ = face_normals(P)
    clear, stats = clear_triangles(P, fn, budget=10)
    assert not clear.any() and stats["unchecked_over_budget"] == P.shape[0]


def test_occluder_only_triangles_cast_shadows_without_texels(tmp_path):
    sc = floor_and_box(res=16)
    bake_scene(sc, tmp_path / "a", BakeSettings(rays=64, bounce_mode="baked"))
    sc.set_id[sc.set_id == 1] = -1                     # the box: occluder only
    from prtt_addon.core.model.scene import validate
    sc.set_names, sc.set_resolution = ["floor"], sc.set_resolution[:1]
    validate(sc)
    m = bake_scene(sc, tmp_path / "b", BakeSettings(rays=64, bounce_mode="baked"))
    assert m["files"] == ["floor.transfer.exr"]
    from prtt_addon.core.io.exr_io import read_sh_exr
    a, _ = read_sh_exr(tmp_path / "a" / "floor.transfer.exr")
    b, _ = read_sh_exr(tmp_path / "b" / "floor.transfer.exr")
    np.testing.assert_array_equal(a, b)                 # the same shadow of the box
    fn, grp, clear, stats = scene_face_data(sc)
    assert stats["tested_triangles"] == 2 and np.all(grp[sc.set_id < 0] == -1)
