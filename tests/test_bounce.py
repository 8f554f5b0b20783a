"""Bounce (inter-reflection) textures: brute force, energy, skipping, staleness."""
import math
import os

import numpy as np
import pytest

from prtt_addon.core import sh
from prtt_addon.core.bake.estimators.raytrace import RAY_EPSILON, RayScene
from prtt_addon.core.bake.estimators.sampling import sobol2, to_hemisphere
from prtt_addon.core.bake.estimators.transfer import Points, TransferSettings, bake_points
from prtt_addon.core.bake.pipeline.context import BakeSettings
from prtt_addon.core.bake.pipeline.runner import bake_scene
from prtt_addon.core.io import exr_io
from prtt_addon.core.shading.materials import eval_materials
from prtt_addon.core.shading.shade import shade
from prtt_addon.dev.bench import meshgen as mg
from tests.scenes_util import planar_uvs, scene_from


def sky(bands=5):
    """A bluish sky brighter towards +Z, as RGB SH (band-limited, positive)."""
    f = lambda d: np.stack([1.0 + 2.0 * np.clip(d[:, 2], 0, None) + 0.3 * d[:, 0],
                            1.2 + 2.2 * np.clip(d[:, 2], 0, None),
                            1.5 + 2.8 * np.clip(d[:, 2], 0, None) - 0.2 * d[:, 1]], -1)  # noqa: E731
    return sh.project_function(f, bands, degree=60)


def corner_scene(wall_material, res=32):
    floor = mg.plane(2.0)
    wall = mg.Mesh(np.array([[-1.0, -1, 0], [-1, 1, 0], [-1, 1, 2], [-1, -1, 2]]),
                   np.array([[0, 1, 2], [0, 2, 3]]))          # x = -1, facing +X
    sc = scene_from([("floor", floor, planar_uvs(floor)), ("wall", wall, planar_uvs(wall, (1, 2)))], res)
    sc.materials = [{"name": "floor", "base_color": [0.5, 0.5, 0.5]}, wall_material]
    sc.material_id = np.array([0, 0, 1, 1], np.int32)
    from prtt_addon.core.model.scene import validate
    validate(sc)
    return sc


def brute_force_bounce(sc, light, p, n_dirs=4096, q_rays=1024):
    """(3, K) one-bounce incident radiance at floor point p, with no textures:
    trace from p, at every hit q trace q's own transfer, shade it, project."""
    rs = RayScene(sc.positions)
    d, _ = to_hemisphere(sobol2(n_dirs, 7), "cosine")          # +Z is the floor normal
    o = np.repeat(rs.to_local(p[None]) + np.float32(RAY_EPSILON) * np.array([0, 0, 1], np.float32),
                  n_dirs, axis=0)
    prim, u, v, _ = rs.intersect(o, d.astype(np.float32))
    hit = prim >= 0
    tri = prim[hit].astype(np.int64)
    bary = np.stack([1 - u[hit] - v[hit], u[hit], v[hit]], 1).astype(np.float64)
    q = np.einsum("nk,nkc->nc", bary, sc.positions[tri])
    nq = np.einsum("nk,nkc->nc", bary, sc.normals[tri].astype(np.float64))
    nq /= np.linalg.norm(nq, axis=1, keepdims=True)
    Tq, _ = bake_points(rs, Points(q, nq, nq, np.arange(q.shape[0]), np.zeros(q.shape[0], bool)),
                        TransferSettings(rays=q_rays, analytic=False))
    Lq = shade(Tq, nq, -d[hit], light, eval_materials(sc, tri, bary), layered=False)  # the bake's hit model
    Y = sh.eval_basis(d[hit], 5)
    return (math.pi / n_dirs) * np.einsum("nc,nk->ck", Lq, Y)


@pytest.mark.parametrize("wall", [
    {"name": "diffuse", "base_color": [0.9, 0.6, 0.3], "roughness": 1.0, "specular": 0.0},
    {"name": "glossy", "base_color": [0.2, 0.3, 0.9], "roughness": 0.3, "specular": 1.0, "metallic": 0.5},
])
def test_one_bounce_matches_brute_force(tmp_path, wall):
    sc = corner_scene(wall, res=32)
    light = sky()
    m = bake_scene(sc, tmp_path, BakeSettings(rays=512, bounces=1, bounce_rays=2048, half=False, tuning="fixed",
                                              bounce_mode="baked"), light=light)
    assert "floor.bounce1.exr" in m["files"]
    data, attrs = exr_io.read_sh_exr(tmp_path / "floor.bounce1.exr")
    assert data.shape == (32, 32, 3, 25) and attrs["kind"] == "bounce" and attrs["level"] == 1
    worst = 0.0
    for i, j in [(4, 16), (8, 8), (12, 24), (20, 16)]:        # floor texels at x = -0.72 .. 0.28
        p = np.array([-1 + 2 * (i + 0.5) / 32, -1 + 2 * (j + 0.5) / 32, 0.0])
        ref = brute_force_bounce(sc, light, p)
        got = data[j, i]
        rel = np.abs(got[:, 0] - ref[:, 0]) / np.abs(ref[:, 0])
        worst = max(worst, rel.max())
        # measured: <= 0.8 % (MC noise of both sides + bilinear transfer at q)
        assert np.linalg.norm(got - ref) <= 0.03 * np.linalg.norm(ref), (i, j, got[:, :4], ref[:, :4])
    assert worst < 0.02


def test_zero_albedo_gives_exact_zero(tmp_path):
    sc = corner_scene({"name": "black", "base_color": [0, 0, 0], "specular": 0.0})
    sc.materials[0] = {"name": "black", "base_color": [0, 0, 0], "specular": 0.0}
    m = bake_scene(sc, tmp_path, BakeSettings(rays=64, bounces=2, bounce_rays=64, tuning="fixed",
                                              bounce_mode="baked"), light=sky())
    for f in m["bounce"]["files"]:
        data, _ = exr_io.read_sh_exr(tmp_path / f)
        assert np.all(data == 0.0), f


def test_energy_decreases_with_bounces_and_stays_finite(tmp_path):
    """An open box (no lid) lit by the sky, albedo 0.8: every further bounce
    carries less light, DC terms are never negative, nothing is NaN."""
    b = mg.box((2, 2, 2), (0, 0, 1))
    inner = mg.Mesh(b.vertices, b.faces[[0, 1, 4, 5, 6, 7, 8, 9, 10, 11]][:, ::-1])   # no top, facing in
    from prtt_addon.core.texels.unwrap import unwrap
    uv = unwrap([(inner.vertices, inner.faces)], 64)[0]
    sc = scene_from([("box", inner, uv)], 64)
    sc.materials = [{"name": "white", "base_color": [0.8, 0.8, 0.8], "roughness": 0.6}]
    sc.material_id = np.zeros(sc.n_triangles, np.int32)
    from prtt_addon.core.model.scene import validate
    validate(sc)
    bake_scene(sc, tmp_path, BakeSettings(rays=128, bounces=3, bounce_rays=256, half=False,
                                          bounce_mode="baked"), light=sky())
    energy = []
    for level in (1, 2, 3):
        data, _ = exr_io.read_sh_exr(tmp_path / f"box.bounce{level}.exr")
        assert np.all(np.isfinite(data))
        assert data[..., 0].min() >= 0.0
        energy.append(data[..., 0].sum())
    assert energy[0] > energy[1] > energy[2] > 0
    assert energy[1] / energy[0] < 0.8


def test_skipping_and_stats(tmp_path):
    """A floor with nothing around: every texel is open, no bounce ray is traced,
    no file is written. The corner's floor texels are not all skipped."""
    floor = mg.plane(2.0)
    alone = scene_from([("floor", floor, planar_uvs(floor))], 16)
    m = bake_scene(alone, tmp_path / "alone", BakeSettings(rays=64, bounces=1), light=sky())
    (rep,) = m["bounce"]["sets"]
    assert rep["skipped"] == "sees no geometry" and rep["rays_traced"] == 0
    assert m["bounce"]["files"] == []
    sc = corner_scene({"name": "w", "base_color": [0.5, 0.5, 0.5]})
    m = bake_scene(sc, tmp_path / "corner", BakeSettings(rays=64, bounces=1, bounce_rays=32), light=sky())
    floor_rep = [r for r in m["bounce"]["sets"] if r["name"] == "floor"][0]
    assert 0 < floor_rep["hits_shaded"] < floor_rep["rays_traced"]
    rays = floor_rep["grid"]["rays"] if "grid" in floor_rep else 32     # tuning auto: 1.5x on a coarser grid
    assert rays == 48 and floor_rep["grid"]["resolution"] == [16, 16]
    assert floor_rep["rays_traced"] == (floor_rep["texels"] - floor_rep["skipped_texels"]) * rays


def test_light_or_material_change_rebakes_only_bounces(tmp_path):
    sc = corner_scene({"name": "w", "base_color": [0.5, 0.5, 0.5]})
    st = BakeSettings(rays=64, bounces=1, bounce_rays=32, bounce_mode="baked")
    first = bake_scene(sc, tmp_path, st, light=sky())
    t_before = (tmp_path / "floor.transfer.exr").read_bytes()
    b_before = (tmp_path / "floor.bounce1.exr").read_bytes()
    assert bake_scene(sc, tmp_path, st, light=sky())["skipped"]
    brighter = sky() * 2.0
    second = bake_scene(sc, tmp_path, st, light=brighter)
    assert second["skipped"] is False and second["transfer_reused"] is True
    assert second["bounce"]["light_hash"] != first["bounce"]["light_hash"]
    assert (tmp_path / "floor.transfer.exr").read_bytes() == t_before
    b_after, _ = exr_io.read_sh_exr(tmp_path / "floor.bounce1.exr")
    assert (tmp_path / "floor.bounce1.exr").read_bytes() != b_before
    sc.materials[1]["base_color"] = [0.9, 0.1, 0.1]
    third = bake_scene(sc, tmp_path, st, light=brighter)
    assert third["transfer_reused"] and third["bounce"]["materials_hash"] != second["bounce"]["materials_hash"]
    # fewer bounces: the old level's file is removed with the new manifest
    bake_scene(sc, tmp_path, BakeSettings(rays=64, bounces=2, bounce_rays=32, bounce_mode="baked"), light=brighter)
    assert os.path.exists(tmp_path / "floor.bounce2.exr")
    bake_scene(sc, tmp_path, st, light=brighter)
    assert not os.path.exists(tmp_path / "floor.bounce2.exr")


def test_no_light_skips_bounces_with_warning(tmp_path):
    sc = corner_scene({"name": "w", "base_color": [0.5, 0.5, 0.5]})
    m = bake_scene(sc, tmp_path, BakeSettings(rays=32, bounces=1, bounce_mode="baked"))
    assert m["bounce"] is None and any("no light given" in w for w in m["warnings"])
    with pytest.raises(ValueError, match="bounces must be an integer"):
        BakeSettings(bounces=-1, bounce_mode="baked").validate()
