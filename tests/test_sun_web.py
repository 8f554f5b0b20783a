"""The Sun lamp in the glTF and on the web page (issue 48, item 4): `prtt
export` carries the baked sun (the root's ``sun``, each set's mask as an R8
KTX2, the lamp's node tagged beside its KHR_lights_punctual light) and the
three.js page draws its light with those masks as Blender's preview does:
relative RMSE against `prtt render` of the same .blend within 1 % in TPFL
and diffuse, with the World turned, and with the sun's strength changed live
on the page and in Blender."""
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
TURN = 90.0
#: The sun's strength in the .blend, and the one the page and Blender are changed to (no rebake).
STRENGTH, STRONGER = 3.0, 6.0


@pytest.fixture(scope="module")
def sunny(tmp_path_factory):
    """A floor (glossy) with a box and a plank, a dim forest World and a warm
    5 degree Sun, baked with one relightable bounce, exported, and rendered by
    Blender in TPFL and diffuse, with the World turned and with the sun stronger."""
    from prtt_addon.core.light.envmap import builtin_environment_path
    from prtt_addon.dev.bench.scene_build import environment_world, principled
    tmp = tmp_path_factory.mktemp("sunweb")
    bpy = addon_bpy()
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
    scene.world = environment_world("Forest", builtin_environment_path("forest"), strength=0.3)
    sun = bpy.data.objects.new("Key", bpy.data.lights.new("Key", "SUN"))
    sun.data.energy, sun.data.angle, sun.data.color = STRENGTH, math.radians(5.0), (1.0, 0.85, 0.65)
    sun.rotation_euler = (math.radians(50), 0.0, math.radians(35))
    scene.collection.objects.link(sun)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp / "scene.blend"))
    r = run("bake", "scene.blend", "--out", "textures", "--unwrap", "SMART", "--resolution", "128", "--rays", "64",
            "--bounces", "1", "--bounce-rays", "16", cwd=tmp, timeout=600)
    assert r.returncode == 0, r.stderr + r.stdout
    r = run("export", "scene.blend", "--out", "sun.glb", cwd=tmp)
    assert r.returncode == 0, r.stderr + r.stdout
    bpy.ops.wm.open_mainfile(filepath=str(tmp / "scene.blend"))
    mapping = next(n for n in bpy.context.scene.world.node_tree.nodes if n.bl_idname == "ShaderNodeMapping")
    mapping.inputs["Rotation"].default_value[2] = math.radians(TURN)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp / "turned.blend"))
    mapping.inputs["Rotation"].default_value[2] = 0.0
    bpy.data.objects["Key"].data.energy = STRONGER
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp / "stronger.blend"))
    bpy.data.objects["Key"].hide_render = True
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp / "nosun.blend"))
    for blend, modes in (("scene", ("tpfl", "diffuse")), ("turned", ("tpfl", "diffuse")), ("stronger", ("tpfl",)),
                         ("nosun", ("tpfl",))):
        for mode in modes:
            r = run("render", f"{blend}.blend", "--mode", mode, "--size", f"{RW}x{RH}", "--out",
                    f"{blend}_{mode}.png", cwd=tmp)
            assert r.returncode == 0, r.stderr + r.stdout
    return tmp


@pytest.fixture(scope="module")
def sun_server(sunny):
    yield from serve(sunny, "sun.glb")


def test_the_glb_carries_the_baked_sun_and_its_masks(sunny):
    from prtt_addon.core.io.exr_io import read_edge_exr, read_mask_exr
    from prtt_addon.core.io.ktx2 import parse_ktx2
    doc, binary = glb(sunny / "sun.glb")
    validate_file(doc)
    ext = doc["extensions"][NAME]
    sun = ext["sun"]
    bpy = addon_bpy()
    bpy.ops.wm.open_mainfile(filepath=str(sunny / "scene.blend"))
    lamp = bpy.data.objects["Key"]
    towards = np.array(lamp.matrix_world.to_3x3().col[2])            # the lamp shines along its -Z
    assert np.allclose(sun["direction"], towards, atol=1e-9)
    assert sun["name"] == "Key" and math.isclose(sun["angle"], math.radians(5.0), rel_tol=1e-6)
    assert sun["strength"] == STRENGTH and np.allclose(sun["color"], (1.0, 0.85, 0.65), atol=1e-6)
    assert np.allclose(sun["irradiance"], STRENGTH * np.array(sun["color"]), atol=1e-8)
    # the node of the sun's name is the lamp: Blender's directional light, no PRTT part
    # (a viewer of an older version reads every node's PRTT part as a set)
    node = next(n for n in doc["nodes"] if n.get("name") == sun["name"])
    assert NAME not in node["extensions"]
    light = doc["extensions"]["KHR_lights_punctual"]["lights"][node["extensions"]["KHR_lights_punctual"]["light"]]
    assert light["type"] == "directional"
    lit = edged = 0.0
    for s in ext["sets"]:
        meta = s["sun"]
        (q,), keys = parse_ktx2(view(doc, binary, meta["bufferView"]))
        mask = read_mask_exr(sunny / "textures" / f"{s['name']}.sun.exr")[0][::-1]    # rows top first
        # the default bake has sub-texel edges: the very halves Blender's preview uploads
        assert meta["format"] == "RGBA16F" and keys["PRTTkind"] == "sun_mask_edges", meta
        assert q.dtype == np.float16 and q.shape == (1, meta["height"], meta["width"], 4)
        edge = read_edge_exr(sunny / "textures" / f"{s['name']}.sun_edge.exr")[0][::-1]
        want = np.stack([mask, edge[..., 0], edge[..., 2], edge[..., 1]], axis=-1).astype(np.float16)
        assert np.array_equal(q[0], want), s["name"]
        assert meta["maxError"] == 0.0                    # the EXR's mask is half already
        assert meta["bytes"] < 0.5 * meta["uncompressedBytes"]
        lit += float((mask > 0.5).mean())
        edged += float((edge[..., 2] >= 1.0).mean())
    assert edged > 0.0                                   # some texels draw their edge's line
    assert 0.2 < lit / len(ext["sets"]) < 0.95                       # shadows and light both present


@pytest.mark.parametrize("mode,blend,query", [
    ("tpfl", "scene", {}), ("diffuse", "scene", {}), ("tpfl", "turned", {"turn": TURN}),
    ("diffuse", "turned", {"turn": TURN}), ("tpfl", "stronger", {"sunstrength": STRONGER})])
def test_the_page_draws_the_sun_as_blender_does(sunny, sun_server, tmp_path, mode, blend, query):
    """The page against `prtt render` (same camera, mode and World): the
    sun's light, its masked shadows and (TPFL) its highlight on the glossy
    floor, the World turned on both sides, the sun's strength changed on
    both sides: within 1 %; the page without the sun is far off."""
    title = room_shot(sun_server, tmp_path / "web.png", src="/sun.glb", mode=mode, **query)
    assert title == "ready 3", title
    addon_bpy()
    ref = read_png(sunny / f"{blend}_{mode}.png")
    rel, plain, p99 = surface_rmse(read_png(tmp_path / "web.png"), ref)
    print(f"{mode} {blend}: relative RMSE {rel:.4%} (plain {plain:.4%}, p99 {p99} levels)")
    assert rel <= 0.01, (rel, plain, p99)
    if blend == "scene" and mode == "tpfl":
        # the sun is most of the picture: the page without it is far from Blender with it,
        # and close to Blender without it
        assert room_shot(sun_server, tmp_path / "nosun.png", src="/sun.glb", mode=mode, sun=0) == "ready 3"
        off, _, _ = surface_rmse(read_png(tmp_path / "nosun.png"), ref)
        assert off > 20 * max(rel, 0.002), (off, rel)
        rel_nosun, _, _ = surface_rmse(read_png(tmp_path / "nosun.png"), read_png(sunny / "nosun_tpfl.png"))
        assert rel_nosun <= 0.01, rel_nosun
    if blend == "stronger":
        before, _, _ = surface_rmse(read_png(tmp_path / "web.png"), read_png(sunny / "scene_tpfl.png"))
        assert before > 10 * max(rel, 0.002), (before, rel)


def _mask_cut(doc, binary):
    meta = doc["extensions"][NAME]["sets"][0]["sun"]
    meta["width"] = meta["width"] // 2


def _mask_garbage(doc, binary):
    from tests.test_web_viewer import view_bytes
    o, _ = view_bytes(doc, binary, doc["extensions"][NAME]["sets"][0]["sun"]["bufferView"])
    binary[o:o + 12] = b"NOT A KTX2!!"


def _mask_is_a_transfer(doc, binary):
    s = doc["extensions"][NAME]["sets"][0]
    s["sun"]["bufferView"] = s["transfer"]["bufferView"]


def _mask_says_r8(doc, binary):
    doc["extensions"][NAME]["sets"][0]["sun"]["format"] = "R8"


def _mask_unknown_format(doc, binary):
    doc["extensions"][NAME]["sets"][0]["sun"]["format"] = "RGB9E5"


def _sun_direction(doc, binary):
    doc["extensions"][NAME]["sun"]["direction"] = [0.0, 0.0, 0.0]


def _sun_angle(doc, binary):
    doc["extensions"][NAME]["sun"]["angle"] = 3.0


def _sun_strength(doc, binary):
    doc["extensions"][NAME]["sun"]["strength"] = -1.0


BAD_SUNS = {
    "mask size": (_mask_cut, "sun mask: 128x128 in 1 layers, the extension says 64x128 in 1"),
    "mask not KTX2": (_mask_garbage, "sun mask: not a readable KTX2 file"),
    "mask is a transfer": (_mask_is_a_transfer, "sun mask: 128x128 in 7 layers, the extension says 128x128 in 1"),
    "mask of another format": (_mask_says_r8, "sun mask: not an R8 texture (vkFormat 97)"),
    "mask of no format": (_mask_unknown_format, "sun mask: unknown format RGB9E5 (R8, RGBA8 or RGBA16F)"),
    "direction": (_sun_direction, "the sun's direction must be a unit vector"),
    "angle": (_sun_angle, "the sun's angle 3 is not 0 to 0.5236 radians"),
    "strength": (_sun_strength, "the sun's colour and strength must be finite and not negative"),
}


@pytest.mark.parametrize("case", sorted(BAD_SUNS))
def test_a_damaged_sun_is_a_message_on_the_page(sunny, sun_server, case):
    from tests.test_web_viewer import page_run, read_glb, write_glb
    edit, expected = BAD_SUNS[case]
    doc, binary = read_glb(sunny / "sun.glb")
    edit(doc, binary)
    name = "sun_" + case.replace(" ", "_") + ".glb"
    write_glb(sunny / "site" / name, doc, binary)
    title, shown, errors, console = page_run(sun_server, f"/{name}")
    assert title.startswith("error: ") and expected in title, title
    assert expected in shown, shown
    assert not errors and not console, (errors, console)


def test_the_pages_sun_control_changes_its_strength_live(sunny, sun_server, tmp_path):
    """The sun slider (a multiple of the export's strength) redraws with the
    new strength and no reload: at 2x it is Blender's render at 2x."""
    from playwright.sync_api import sync_playwright

    from tests.test_web_viewer import BROWSER, BROWSER_ARGS, canvas_png
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=BROWSER, args=BROWSER_ARGS)
        try:
            page = b.new_page(viewport={"width": RW, "height": RH + 80})
            errors = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(f"{sun_server}/viewer/index.html?src=/sun.glb&w={RW}&h={RH}&mode=tpfl")
            page.wait_for_function("document.title.startsWith('ready') || document.title.startsWith('error')",
                                   timeout=120_000)
            assert page.title() == "ready 3", page.title()
            frames = page.evaluate("window.prttFrameCount()")
            page.locator("#sunstrength").fill(str(STRONGER / STRENGTH))
            page.wait_for_function(f"window.prttFrameCount() > {frames}", timeout=60_000)
            canvas_png(page, tmp_path / "slid.png")
            assert not errors, errors
        finally:
            b.close()
    addon_bpy()
    rel, _, _ = surface_rmse(read_png(tmp_path / "slid.png"), read_png(sunny / "stronger_tpfl.png"))
    assert rel <= 0.01, rel
