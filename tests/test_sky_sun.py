"""A Sky Texture's sun disc as the bake's sun (issue 48, item 3): its
direction, size and energy measured from Cycles' render of the World, its
mask baked, the World's SH made of the sky without it; against Cycles (the
bench's scene at small sizes: bench sun --sky prints the full-size numbers),
the option that keeps the old meaning (``sky_sun`` off: the disc in the SH),
and a Sun lamp that takes precedence."""
import json
import math

import numpy as np
import pytest

from tests import real_scenes as rs
from tests.blender_util import addon_bpy
from tests.test_headless_chain import run

pytestmark = pytest.mark.blender


def sky_scene(bpy, tmp_path, *, lamp: bool = False, sky_sun: bool = True):
    from prtt_addon.dev.bench.sun_cycles import sky_world
    rs.floor_and_box(bpy)
    scene = bpy.context.scene
    scene.world = sky_world(bpy, 0.5)
    scene.prtt.light_source, scene.prtt.sky_sun = "WORLD", sky_sun
    if lamp:
        ob = bpy.data.objects.new("Key", bpy.data.lights.new("Key", "SUN"))
        ob.data.energy = 2.0
        scene.collection.objects.link(ob)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))


def test_the_sky_sun_is_measured_where_the_node_puts_it_and_left_out_of_the_sh():
    """Direction within 0.01 degrees of the node's (cos e sin r, cos e cos r,
    sin e), size the node's, and the World's SH without the disc differ from
    those with it by the disc's energy in the DC term (exactly: Y_00 is 1/sqrt(4 pi))."""
    bpy = addon_bpy()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    from prtt_addon.blender.scene import lamps, world_panorama
    from prtt_addon.blender.scene.world import world_light
    from prtt_addon.dev.bench.sun_cycles import SUN_ELEVATION, sky_world, sun_direction
    scene = bpy.context.scene
    scene.world = sky_world(bpy, 0.5)
    scene.prtt.light_source = "WORLD"
    sun, ob, notes = lamps.scene_sun(scene)
    assert ob is None and not notes and sun.name == "Sky: Sky Texture"
    turned = math.degrees(math.acos(min(1.0, float(np.dot(sun.direction, sun_direction())))))
    assert turned < 0.01, turned
    assert math.isclose(sun.angle, math.radians(0.5), rel_tol=1e-6)
    assert max(sun.color) == 1.0 and sun.color[2] < sun.color[0]      # a sun low in the sky is warm
    without, desc = world_light(scene, 5)
    assert "its sun disc is the sun" in desc
    scene.prtt.sky_sun = False
    assert lamps.scene_sun(scene)[0] is None
    with_disc, desc_old = world_light(scene, 5)
    assert "sun disc" not in desc_old
    energy = world_panorama.sky_sun(scene.world).energy
    dc = (with_disc - without)[0]
    assert np.allclose(dc, energy / math.sqrt(4 * math.pi), rtol=1e-4), (dc, energy)
    # and the old meaning is the old bytes: the panorama with its disc put back, as before the option
    assert world_panorama.panorama(scene.world).tobytes() == world_panorama.panorama(scene.world, disc=True).tobytes()
    assert SUN_ELEVATION == 40.0


def test_bake_and_render_take_the_sky_sun_and_a_lamp_comes_first(tmp_path):
    """A bake of a Sky World writes sun masks and names the sky's sun in the
    manifest; render draws it with no note; with a Sun lamp the lamp is the
    sun and a note says the sky's disc stays soft; with sky_sun off nothing
    is baked for it."""
    bpy = addon_bpy()
    bake = ("bake", "scene.blend", "--out", "tex", "--unwrap", "SMART", "--resolution", "32", "--rays", "16",
            "--bounces", "0")
    for case in ("sky", "lamp", "off"):
        d = tmp_path / case
        d.mkdir()
        bpy.ops.wm.read_factory_settings(use_empty=True)
        sky_scene(bpy, d, lamp=case == "lamp", sky_sun=case != "off")
        r = run(*bake, cwd=d, timeout=600)
        assert r.returncode == 0, r.stdout + r.stderr
        m = json.load(open(d / "tex" / "manifest.json"))
        said = r.stdout + r.stderr
        if case == "sky":
            assert m["sun"]["name"] == "Sky: Sky Texture" and "Box.sun.exr" in m["files"]
            r = run("render", "scene.blend", "--size", "64x36", "--out", "a.png", cwd=d, timeout=600)
            assert r.returncode == 0 and "stale" not in r.stdout + r.stderr and "not in the bake" not in (
                r.stdout + r.stderr), r.stdout + r.stderr
        elif case == "lamp":
            assert m["sun"]["name"] == "Key"
            assert "the World's Sky Texture sun stays in the World's soft light" in said, said
        else:
            assert "sun" not in m and not any(f.endswith(".sun.exr") for f in m["files"])


@pytest.mark.parametrize("angle", [0.5, 5.0])
def test_the_sky_sun_matches_cycles_and_beats_the_sun_in_sh(tmp_path, angle):
    """bench sun --sky at small sizes: with the disc baked as the sun the
    preview is within 2 % of Cycles over the image; with the disc in the
    World's SH (the old way) it is several times farther, and has no shadow edge."""
    pytest.importorskip("bpy")
    from prtt_addon.dev.bench.sun_cycles import compare
    r = compare(angle, (160, 90), samples=64, resolution=256, work_dir=str(tmp_path / "a"), light="sky")
    assert r["sun"] is not None and r["pixels"] > 5000
    assert r["rel_rmse"] < 0.02, r["rel_rmse"]
    old = compare(angle, (160, 90), samples=64, resolution=256, work_dir=str(tmp_path / "b"), light="sky",
                  sky_sun=False)
    assert old["sun"] is None
    assert old["rel_rmse"] > 3 * r["rel_rmse"], (old["rel_rmse"], r["rel_rmse"])
    print(f"angle {angle}: sky sun {r['rel_rmse']:.2%} (shadow {r['rel_rmse_shadow']:.2%}), in SH "
          f"{old['rel_rmse']:.2%} (shadow {old['rel_rmse_shadow']:.2%}); penumbrae {r['penumbra_m']}")
