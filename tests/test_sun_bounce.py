"""The sun's bounce light (issue 48, item 2): bounce textures see a sun as its
SH projection (shade.sun_sh, E y_k(l)), a relightable bounce relit with it
live (PreviewScene.bounce_light, the page's bounceLight), a baked bounce
baked with it (BakeContext.bounce_light) and stale when the sun's light
changes; against an analytic band-limited cosine and against Cycles."""
import json
import math
import os

import numpy as np
import pytest
from scipy.special import eval_legendre

from prtt_addon.core.bake.estimators.transfer import unoccluded_transfer
from prtt_addon.core.light.sun import Sun
from prtt_addon.core.shading.shade import sun_sh


def test_a_sun_through_an_open_planes_transfer_is_the_band_limited_cosine():
    """T . sun_sh(l) for an unoccluded plane = E sum_l<5 (2l+1)/(4 pi) c_l P_l(cos t),
    c_l = 2 pi int_0^1 P_l(x) x dx (the clamped cosine's zonal coefficients, scipy)."""
    from scipy.integrate import quad
    bands = 5
    c = [2 * math.pi * quad(lambda x, l=l: eval_legendre(l, x) * x, 0, 1)[0] for l in range(bands)]
    E = np.array([2.0, 1.5, 1.0])
    T = unoccluded_transfer(np.array([[0.0, 0.0, 1.0]]), bands)
    for t in np.radians([0.0, 30.0, 60.0, 85.0, 120.0]):
        d = (math.sin(t), 0.0, math.cos(t))
        want = sum((2 * l + 1) / (4 * math.pi) * c[l] * eval_legendre(l, math.cos(t)) for l in range(bands))
        got = (T @ sun_sh(d, E, bands))[0]
        assert np.allclose(got, E * want, rtol=1e-9, atol=1e-12), (t, got, E * want)


def test_the_preview_relights_bounces_with_the_sun_and_only_with_it():
    from prtt_addon.core.preview import pack as pp
    light = np.random.default_rng(1).normal(size=(25, 3))
    sun = pp.PreviewSun((0.0, 0.6, 0.8), (3.0, 2.0, 1.0), math.radians(1.0))
    ps = pp.PreviewScene(bands=5, meshes=[], materials=[], sets={}, light=light, sun=sun)
    assert np.array_equal(ps.bounce_light, light + sun_sh(sun.direction, sun.irradiance, 5))
    assert pp.PreviewScene(bands=5, meshes=[], materials=[], sets={}, light=light).bounce_light is light


def test_a_baked_bounce_with_a_sun_is_the_bounce_of_its_light_and_its_projection(tmp_path):
    """bake_scene(light, sun): the baked bounce level holds exactly what a bake
    lit by light + sun_sh(sun) (and no sun) holds; the transfer is unchanged."""
    from prtt_addon.core.bake.pipeline.context import BakeSettings
    from prtt_addon.core.bake.pipeline.runner import bake_scene
    from prtt_addon.core.io.exr_io import read_sh_exr
    from prtt_addon.core.light.envmap import builtin_environment_path, environment_light
    from prtt_addon.dev.bench import contact_profile as cp
    sc = cp.build(32)
    st = BakeSettings(rays=16, bounces=1, bounce_rays=8, bounce_mode="baked", tuning="fixed", vertex_mode=False)
    light = environment_light(builtin_environment_path("forest"), 5)
    sun = Sun(direction=(0.5, 0.1, 0.8), angle=math.radians(3.0), strength=4.0)
    a, b, c = (str(tmp_path / x) for x in "abc")
    bake_scene(sc, a, st, light=light, sun=sun)
    bake_scene(sc, b, st, light=light + sun_sh(sun.direction, sun.irradiance, 5))
    bake_scene(sc, c, st, light=light)
    for name in ("floor", "box"):
        with_sun = read_sh_exr(os.path.join(a, f"{name}.bounce1.exr"))[0]
        as_light = read_sh_exr(os.path.join(b, f"{name}.bounce1.exr"))[0]
        without = read_sh_exr(os.path.join(c, f"{name}.bounce1.exr"))[0]
        assert np.array_equal(with_sun, as_light), name
        assert np.abs(with_sun - without).max() > 0.05 * np.abs(without).max(), name
        assert read_sh_exr(os.path.join(a, f"{name}.transfer.exr"))[0].tobytes() == \
            read_sh_exr(os.path.join(c, f"{name}.transfer.exr"))[0].tobytes()
    ma = json.load(open(os.path.join(a, "manifest.json")))
    mc = json.load(open(os.path.join(c, "manifest.json")))
    assert ma["bounce"]["light_hash"] == mc["bounce"]["light_hash"]        # the World's light, as before


@pytest.mark.blender
def test_the_suns_bounce_matches_cycles_indirect_light(tmp_path):
    """bench sun --bounces 1 at small sizes (a 5 degree Sun lamp, one
    relightable bounce, Cycles with one diffuse bounce): within 2 % of Cycles;
    without the sun's bounce the preview is several times farther."""
    pytest.importorskip("bpy")
    from prtt_addon.dev.bench.sun_cycles import compare
    r = compare(5.0, (160, 90), samples=64, resolution=256, work_dir=str(tmp_path), bounces=1)
    print(f"with the sun's bounce {r['rel_rmse']:.2%}, without {r['rel_rmse_without_sun_bounce']:.2%}")
    assert r["rel_rmse"] < 0.02, r["rel_rmse"]
    assert r["rel_rmse_without_sun_bounce"] > 2.5 * r["rel_rmse"], r


@pytest.mark.blender
def test_a_baked_bounce_is_stale_when_the_suns_light_changes(tmp_path):
    """--bounce-mode baked bakes the sun's bounce in: a stronger sun draws the
    same masks (no warning for them) but says the bounce textures are stale."""
    from tests import real_scenes as rs
    from tests.blender_util import addon_bpy
    from tests.test_headless_chain import run
    bpy = addon_bpy()
    rs.floor_and_box(bpy)
    ob = bpy.data.objects.new("Key", bpy.data.lights.new("Key", "SUN"))
    ob.data.energy, ob.rotation_euler = 2.0, (math.radians(40), 0.0, math.radians(30))
    bpy.context.scene.collection.objects.link(ob)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    r = run("bake", "scene.blend", "--out", "tex", "--unwrap", "SMART", "--resolution", "32", "--rays", "16",
            "--bounces", "1", "--bounce-rays", "8", "--bounce-mode", "baked", cwd=tmp_path, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    r = run("render", "scene.blend", "--size", "32x18", "--out", "a.png", cwd=tmp_path, timeout=600)
    assert r.returncode == 0 and "are stale" not in r.stdout + r.stderr, r.stdout + r.stderr      # (the folder's name has "stale")
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "scene.blend"))
    bpy.data.objects["Key"].data.energy = 5.0
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    r = run("render", "scene.blend", "--size", "32x18", "--out", "b.png", cwd=tmp_path, timeout=600)
    said = r.stdout + r.stderr
    assert r.returncode == 0 and "bounce textures are stale (the sun's colour or strength changed)" in said, said
    assert "the sun's shadows are stale" not in said
