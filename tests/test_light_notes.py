"""Light PRTT does not carry yet is named, not dropped without a word (issues
48 and 49): area lamps and emissive materials light Cycles' render but not
the bake (a Sun, Point and Spot lamps are baked); the bake warns, the preview and `render` note the
lamps, the export still runs (Blender's exporter carries the lamps as glTF
lights). A Sun lamp is baked (its mask: tests/test_sun_blender.py)."""
import pytest

from tests import real_scenes as rs
from tests.blender_util import addon_bpy
from tests.test_headless_chain import run

pytestmark = pytest.mark.blender


def test_lamps_and_emission_are_named(tmp_path):
    bpy = addon_bpy()
    rs.floor_and_box(bpy)
    for name, kind in (("Key", "SUN"), ("Bulb", "POINT"), ("Panel", "AREA")):
        ob = bpy.data.objects.new(name, bpy.data.lights.new(name, kind))
        bpy.context.scene.collection.objects.link(ob)
    off = bpy.data.objects.new("Off", bpy.data.lights.new("Off", "AREA"))
    off.data.energy = 0.0                               # no power: not named
    bpy.context.scene.collection.objects.link(off)
    mat = bpy.data.materials.new("Glow")
    if bpy.app.version < (5, 0, 0):
        mat.use_nodes = True
    mat.node_tree.nodes["Principled BSDF"].inputs["Emission Strength"].default_value = 5.0
    bpy.data.objects["Box"].data.materials.append(mat)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    r = run("bake", "scene.blend", "--out", "tex", "--unwrap", "SMART", "--resolution", "64", "--rays", "32",
            "--bounces", "0", cwd=tmp_path, timeout=600)
    out = r.stdout + r.stderr
    assert r.returncode == 0, out
    assert "1 lamp(s) light Cycles' render but not PRTT's" in out and "Area 'Panel'" in out
    assert "Sun 'Key'" not in out and "'Bulb'" not in out      # the sun and the point lamp are baked
    import json
    manifest = json.load(open(tmp_path / "tex" / "manifest.json"))
    assert manifest["sun"]["name"] == "Key" and [lp["name"] for lp in manifest["lamps"]["lamps"]] == ["Bulb"]
    assert "'Off'" not in out
    assert "material 'Glow': its emission lights Cycles' render but not PRTT's" in out
    r = run("render", "scene.blend", "--size", "64x36", "--out", "shot.png", cwd=tmp_path, timeout=600)
    assert r.returncode == 0 and "1 lamp(s) light Cycles' render" in r.stdout, r.stdout + r.stderr
    r = run("export", "scene.blend", "--out", "scene.glb", cwd=tmp_path, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr


def test_a_dim_world_is_said(tmp_path):
    """Blender's default World (a grey of 0.05) previews near black: `render`
    says why; the forest HDRI draws without the note."""
    bpy = addon_bpy()
    rs.floor_and_box(bpy)
    sc = bpy.context.scene
    sc.prtt.light_source = "WORLD"
    w = bpy.data.worlds.new("Default grey")
    if bpy.app.version < (5, 0, 0):
        w.use_nodes = True
    w.node_tree.nodes["Background"].inputs["Color"].default_value = (0.05, 0.05, 0.05, 1.0)
    sc.world = w
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    r = run("bake", "scene.blend", "--out", "tex", "--unwrap", "SMART", "--resolution", "64", "--rays", "32",
            "--bounces", "0", cwd=tmp_path, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    r = run("render", "scene.blend", "--size", "64x36", "--out", "shot.png", cwd=tmp_path, timeout=600)
    assert r.returncode == 0 and "the light is dim (mean radiance 0.05" in r.stdout, r.stdout + r.stderr
    from prtt_addon.blender.scene.world import dim_light_note
    from prtt_addon.core.light import envmap
    assert dim_light_note(envmap.environment_light("forest", 3)) == ""
    assert dim_light_note(envmap.constant_light([0.05] * 3, 3), exposure=2.0) == ""     # 0.2 once exposed
