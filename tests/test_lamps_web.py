"""Point and spot lamps in the glTF and on the web page (issue 49, item 4):
`prtt export` carries the baked lamps (the root's ``lamps``, each set's
masks as one RGBA8 KTX2, a lamp a channel) and the three.js page draws their
light with those masks as Blender's preview does: relative RMSE against
`prtt render` of the same .blend within 1 % in TPFL and diffuse, and after a
lamp is dimmed and recoloured live on the page and in Blender."""
import math

import numpy as np
import pytest

from tests import real_scenes as rs
from tests.blender_util import addon_bpy
from tests.test_gltf_export import glb, validate_file, view
from tests.test_headless_chain import run
from tests.test_web_viewer import RH, RW, read_png, room_shot, serve, surface_rmse

pytestmark = pytest.mark.blender
NAME = "PRTT_radiance_transfer"
#: The point lamp's power and colour in the .blend, and what the page and Blender change them to (no rebake).
POWER, DIMMER, GREEN = 150.0, 60.0, (0.3, 1.0, 0.4)


@pytest.fixture(scope="module")
def lamplit(tmp_path_factory):
    """A glossy floor with a box and a plank under a dim forest World, a 10 cm
    point lamp and a spot, baked without bounces, exported, and rendered by
    Blender in TPFL and diffuse, and with the point lamp dimmed and recoloured."""
    from prtt_addon.core.light.envmap import builtin_environment_path
    from prtt_addon.dev.bench.scene_build import environment_world, principled
    tmp = tmp_path_factory.mktemp("lampweb")
    bpy = addon_bpy()
    import mathutils  # Blender's, once bpy is imported
    floor = rs.floor(bpy, 6.0)
    floor.data.materials.append(principled("Floor", base_color=(0.45, 0.40, 0.33), roughness=0.35, specular=0.5))
    box = rs.add_object(bpy, "Box", rs.cube_mesh(bpy, "box"), location=(-0.6, 0.3, 0.5))
    box.data.materials.append(principled("Box", base_color=(0.10, 0.20, 0.45), roughness=0.6, specular=0.5))
    plank = rs.add_object(bpy, "Plank", rs.cube_mesh(bpy, "plank"), location=(1.0, -0.4, 0.6))
    plank.scale = (1.2, 0.12, 0.04)
    plank.data.materials.append(principled("Plank", base_color=(0.5, 0.3, 0.2), roughness=1.0, specular=0.0))
    rs.scene_camera(bpy, (0.5, -6, 3.5), (1.1, 0, 0.1))
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = RW, RH
    scene.world = environment_world("Forest", builtin_environment_path("forest"), strength=0.2)
    bulb = bpy.data.objects.new("Bulb", bpy.data.lights.new("Bulb", "POINT"))
    bulb.data.energy, bulb.data.shadow_soft_size, bulb.data.color = POWER, 0.1, (1.0, 0.85, 0.7)
    bulb.location = (0.6, -1.2, 1.8)
    spot = bpy.data.objects.new("Spot", bpy.data.lights.new("Spot", "SPOT"))
    spot.data.energy, spot.data.shadow_soft_size, spot.data.color = 400.0, 0.05, (0.7, 0.85, 1.0)
    spot.data.spot_size, spot.data.spot_blend = math.radians(55.0), 0.3
    spot.location = (-2.5, -2.0, 3.0)
    spot.rotation_euler = (mathutils.Vector((-0.6, 0.3, 0.0)) - spot.location).to_track_quat("-Z", "Y").to_euler()
    for ob in (bulb, spot):
        scene.collection.objects.link(ob)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp / "scene.blend"))
    r = run("bake", "scene.blend", "--out", "textures", "--unwrap", "SMART", "--resolution", "128", "--rays", "64",
            "--bounces", "0", cwd=tmp, timeout=600)
    assert r.returncode == 0, r.stderr + r.stdout
    r = run("export", "scene.blend", "--out", "lamps.glb", cwd=tmp)
    assert r.returncode == 0, r.stderr + r.stdout
    bpy.ops.wm.open_mainfile(filepath=str(tmp / "scene.blend"))
    bulb = bpy.data.objects["Bulb"]
    bulb.data.energy, bulb.data.color = DIMMER, GREEN
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp / "dimmed.blend"))
    for blend, modes in (("scene", ("tpfl", "diffuse")), ("dimmed", ("tpfl",))):
        for mode in modes:
            r = run("render", f"{blend}.blend", "--mode", mode, "--size", f"{RW}x{RH}", "--out",
                    f"{blend}_{mode}.png", cwd=tmp)
            assert r.returncode == 0, r.stderr + r.stdout
    return tmp


@pytest.fixture(scope="module")
def lamp_server(lamplit):
    yield from serve(lamplit, "lamps.glb")


def test_the_glb_carries_the_baked_lamps_and_their_masks(lamplit):
    """The root's lamps as Blender has them (place, radius, power, colour,
    axis, cone), brightest first; each set's masks the EXR's to 8 bits."""
    from prtt_addon.core.io.exr_io import read_lamp_exr
    from prtt_addon.core.io.ktx2 import parse_ktx2
    doc, binary = glb(lamplit / "lamps.glb")
    validate_file(doc)
    ext = doc["extensions"][NAME]
    lamps = ext["lamps"]
    assert [lp["name"] for lp in lamps] == ["Spot", "Bulb"] and [lp["kind"] for lp in lamps] == ["SPOT", "POINT"]
    bulb = lamps[1]
    assert bulb["power"] == POWER and bulb["radius"] == pytest.approx(0.1) and bulb["position"] == pytest.approx(
        [0.6, -1.2, 1.8])
    assert np.allclose(bulb["intensity"], POWER * np.array(bulb["color"]) / (4 * math.pi))
    assert lamps[0]["spotSize"] == pytest.approx(math.radians(55.0)) and lamps[0]["spotBlend"] == pytest.approx(0.3)
    shadowed = 0.0
    for s in ext["sets"]:
        meta = s["lamps"]
        (q,), keys = parse_ktx2(view(doc, binary, meta["bufferView"]))
        masks = read_lamp_exr(lamplit / "textures" / f"{s['name']}.lamps.exr", 2)[0][::-1]    # rows top first
        assert meta["format"] == "RGBA8" and meta["lamps"] == 2 and keys["PRTTkind"] == "lamp_mask", meta
        assert q.dtype == np.uint8 and q.shape == (1, meta["height"], meta["width"], 4)
        assert np.abs(q[0, ..., :2] / 255.0 - masks).max() <= 1 / 510 + 1e-7 and not q[0, ..., 2:].any()
        shadowed += float((masks < 0.5).mean())
    assert shadowed > 0.0


@pytest.mark.parametrize("mode,blend,query", [
    ("tpfl", "scene", {}), ("diffuse", "scene", {}),
    ("tpfl", "dimmed", {"lamp": f"Bulb:{DIMMER}:{','.join(map(str, GREEN))}"})])
def test_the_page_draws_the_lamps_as_blender_does(lamplit, lamp_server, tmp_path, mode, blend, query):
    """The page against `prtt render` (same camera, mode and World): the
    lamps' light, their masked shadows and (TPFL) their highlights on the
    glossy floor, and a lamp dimmed and recoloured on both sides: within 1 %;
    the page without the lamps is far off."""
    title = room_shot(lamp_server, tmp_path / "web.png", src="/lamps.glb", mode=mode, **query)
    assert title == "ready 3", title
    addon_bpy()
    ref = read_png(lamplit / f"{blend}_{mode}.png")
    rel, plain, p99 = surface_rmse(read_png(tmp_path / "web.png"), ref)
    print(f"{mode} {blend}: relative RMSE {rel:.4%} (plain {plain:.4%}, p99 {p99} levels)")
    assert rel <= 0.01, (rel, plain, p99)
    if blend == "scene" and mode == "tpfl":
        assert room_shot(lamp_server, tmp_path / "nolamps.png", src="/lamps.glb", mode=mode, lamps=0) == "ready 3"
        off, _, _ = surface_rmse(read_png(tmp_path / "nolamps.png"), ref)
        assert off > 20 * max(rel, 0.002), (off, rel)
    if blend == "dimmed":
        before, _, _ = surface_rmse(read_png(tmp_path / "web.png"), read_png(lamplit / "scene_tpfl.png"))
        assert before > 10 * max(rel, 0.002), (before, rel)


def _count(doc, binary):
    doc["extensions"][NAME]["sets"][0]["lamps"]["lamps"] = 3


def _kind(doc, binary):
    doc["extensions"][NAME]["lamps"][0]["kind"] = "AREA"


def _format(doc, binary):
    doc["extensions"][NAME]["sets"][0]["lamps"]["format"] = "R8"


def _power(doc, binary):
    doc["extensions"][NAME]["lamps"][1]["power"] = -1.0


def _too_many(doc, binary):
    ext = doc["extensions"][NAME]
    ext["lamps"] = ext["lamps"] * 3


BAD_LAMPS = {
    "count": (_count, "lamp masks: 3 lamps, the file has 2"),
    "kind": (_kind, "lamp 0: kind must be POINT or SPOT"),
    "format": (_format, "unknown format R8 (lamp masks are RGBA8)"),
    "power": (_power, "lamp 1: radius, power, colour, spotSize and spotBlend must be finite and in range"),
    "too many": (_too_many, "lamps must be a list of 1 to 4"),
}


@pytest.mark.parametrize("case", sorted(BAD_LAMPS))
def test_damaged_lamps_are_a_message_on_the_page(lamplit, lamp_server, case):
    from tests.test_web_viewer import page_run, read_glb, write_glb
    edit, expected = BAD_LAMPS[case]
    doc, binary = read_glb(lamplit / "lamps.glb")
    edit(doc, binary)
    name = "lamps_" + case.replace(" ", "_") + ".glb"
    write_glb(lamplit / "site" / name, doc, binary)
    title, shown, errors, console = page_run(lamp_server, f"/{name}")
    assert title.startswith("error: ") and expected in title, title
    assert expected in shown, shown
    assert not errors and not console, (errors, console)
