"""`prtt export` (issue 34): a baked .blend as a .glb through Blender's own
glTF exporter, with the PRTT_radiance_transfer extension, checked by reading
the .glb back (JSON, buffer views, KTX2 through ktx-parse too) and by
Blender's own glTF importer. The .blend is never modified."""
import json
import os
import shutil
import struct
import subprocess

import numpy as np
import pytest

from prtt_addon.core.io.exr_io import read_sh_exr
from prtt_addon.core.io.gltf_prtt import GLTF_TO_BAKE_FRAME, NAME
from prtt_addon.core.io.ktx2 import parse_ktx2
from tests import real_scenes as rs
from tests.blender_util import addon_bpy
from tests.test_headless_chain import digest, run
from tests.test_ktx2 import node

pytestmark = pytest.mark.blender
BAKE = ["--resolution", "32", "--rays", "16", "--bounces", "0"]


def glb(path):
    """(JSON, binary chunk) of a .glb."""
    data = open(path, "rb").read()
    magic, version, length = struct.unpack_from("<4sII", data)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    n, kind = struct.unpack_from("<II", data, 12)
    assert kind == 0x4E4F534A
    doc = json.loads(data[20:20 + n])
    m, kind2 = struct.unpack_from("<II", data, 20 + n)
    assert kind2 == 0x004E4942
    return doc, data[28 + n:28 + n + m]


def view(doc, binary, index):
    bv = doc["bufferViews"][index]
    return binary[bv.get("byteOffset", 0):bv.get("byteOffset", 0) + bv["byteLength"]]


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    """A folder with a baked scene.blend (floor and box unwrapped by the
    bake, a camera, the built-in light) and its textures."""
    tmp = tmp_path_factory.mktemp("gltf")
    bpy = addon_bpy()
    rs.floor(bpy, 6.0)
    rs.add_object(bpy, "Box", rs.cube_mesh(bpy, "box"), location=(0, 0, 0.5))
    rs.scene_camera(bpy, (0, -7, 4), (1.05, 0, 0))
    bpy.context.scene.prtt.light_source = "BUILTIN"
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp / "scene.blend"))
    r = run("bake", "scene.blend", "--out", "textures", "--unwrap", "SMART", *BAKE, cwd=tmp)
    assert r.returncode == 0, r.stderr + r.stdout
    return tmp


def test_export_writes_blenders_gltf_with_prtts_textures(baked, tmp_path):
    work = tmp_path / "p"
    shutil.copytree(baked, work)
    before = digest(work / "scene.blend")
    r = run("export", "scene.blend", "--out", "room.glb", cwd=work)
    assert r.returncode == 0, r.stderr + r.stdout
    assert "exported 2 object(s) in 2 texture set(s)" in r.stdout, r.stdout
    assert digest(work / "scene.blend") == before                     # the .blend is never modified
    doc, binary = glb(work / "room.glb")
    assert NAME in doc["extensionsUsed"] and NAME not in doc.get("extensionsRequired", [])
    ext = doc["extensions"][NAME]
    assert ext["sh"]["bands"] == 5 and ext["sh"]["gltfToBakeFrame"] == [list(r) for r in GLTF_TO_BAKE_FRAME]
    assert np.asarray(ext["light"]["rgb"]).shape == (25, 3)
    names = [s["name"] for s in ext["sets"]]
    assert sorted(names) == ["Box", "Floor"]
    for i, s in enumerate(ext["sets"]):
        blob = view(doc, binary, s["transfer"]["bufferView"])
        (layers,), keys = parse_ktx2(blob)
        assert keys["PRTTkind"] == "transfer" and layers.shape == (7, 32, 32, 4)
        planes = layers.transpose(0, 3, 1, 2).reshape(28, 32, 32)[:25]
        data, _ = read_sh_exr(work / "textures" / f"{s['name']}.transfer.exr")
        want = data[::-1].transpose(2, 0, 1).astype(np.float16)        # rows top first, as glTF samples them
        assert np.array_equal(planes.view(np.uint16), want.view(np.uint16)), s["name"]
        (tmp_path / f"{i}.ktx2").write_bytes(blob)
        info = json.loads(node("ktx_info.mjs", tmp_path / f"{i}.ktx2"))   # an independent parser agrees
        assert (info["vkFormat"], info["layerCount"], info["pixelWidth"]) == (97, 7, 32)
    # each baked object's node names its set; its primitives name the PRTT TEXCOORD
    nodes = {n["name"]: n for n in doc["nodes"]}
    for obj in ("Floor", "Box"):
        n = nodes[obj]
        assert n["extensions"][NAME]["set"] == names.index(obj)
        for prim in doc["meshes"][n["mesh"]]["primitives"]:
            tc = prim["extensions"][NAME]["texCoord"]
            acc = doc["accessors"][prim["attributes"][f"TEXCOORD_{tc}"]]
            assert acc["type"] == "VEC2" and acc["componentType"] == 5126
    assert "extensions" not in nodes["Cam"]
    # Blender's own importer opens it (the extension is optional: ignored there)
    code = ("import bpy; bpy.ops.wm.read_factory_settings(use_empty=True); "
            f"r = bpy.ops.import_scene.gltf(filepath={str(work / 'room.glb')!r}); "
            "print('IMPORTED', r, sorted(o.name for o in bpy.data.objects))")
    r = subprocess.run([os.sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert "IMPORTED {'FINISHED'}" in r.stdout and "'Box'" in r.stdout and "'Floor'" in r.stdout, r.stdout + r.stderr


def test_texcoord_is_the_prtt_map_v_flipped(baked, tmp_path):
    work = tmp_path / "p"
    shutil.copytree(baked, work)
    assert run("export", "scene.blend", "--out", "room.glb", cwd=work).returncode == 0
    doc, binary = glb(work / "room.glb")
    n = {x["name"]: x for x in doc["nodes"]}["Floor"]
    prim = doc["meshes"][n["mesh"]]["primitives"][0]
    acc = doc["accessors"][prim["attributes"][f"TEXCOORD_{prim['extensions'][NAME]['texCoord']}"]]
    bv = doc["bufferViews"][acc["bufferView"]]
    uv = np.frombuffer(view(doc, binary, acc["bufferView"]), np.float32,
                       count=acc["count"] * 2, offset=acc.get("byteOffset", 0)).reshape(-1, 2)
    assert bv.get("byteStride", 8) == 8
    bpy = addon_bpy()
    bpy.ops.wm.open_mainfile(filepath=str(work / "scene.blend"))
    me = bpy.data.objects["Floor"].data
    prtt = np.array([d.vector[:] for d in me.uv_layers["PRTT"].uv])
    got = {(round(float(u), 5), round(float(1.0 - v), 5)) for u, v in uv}
    assert got == {(round(float(u), 5), round(float(v), 5)) for u, v in prtt}


def test_refusals_say_what_to_do(baked, tmp_path):
    work = tmp_path / "p"
    shutil.copytree(baked, work)
    r = run("export", "scene.blend", "--out", "room.gltf", cwd=work)
    assert r.returncode == 2 and "writes .glb files" in r.stderr
    # an unbaked scene
    bpy = addon_bpy()
    rs.floor(bpy, 4.0)
    bpy.ops.wm.save_as_mainfile(filepath=str(work / "fresh.blend"))
    r = run("export", "fresh.blend", "--out", "fresh.glb", cwd=work)
    assert r.returncode == 1 and "nothing baked" in r.stderr and not (work / "fresh.glb").exists()
    # a stale bake: an object moved since
    bpy.ops.wm.open_mainfile(filepath=str(work / "scene.blend"))
    bpy.data.objects["Box"].location.x += 1.0
    bpy.ops.wm.save_as_mainfile(filepath=str(work / "moved.blend"))
    r = run("export", "moved.blend", "--out", "moved.glb", cwd=work)
    assert r.returncode == 1 and "moved since the bake" in r.stderr and "bake again" in r.stderr, r.stderr
    assert not (work / "moved.glb").exists()


def test_the_users_own_gltf_exports_are_untouched(baked, tmp_path):
    """With PRTT enabled, Blender's glTF export outside `prtt export` writes no PRTT data."""
    bpy = addon_bpy()
    bpy.ops.wm.open_mainfile(filepath=str(baked / "scene.blend"))
    prefs = bpy.context.preferences
    added = prefs.addons.new()
    added.module = "prtt_addon"
    try:
        assert bpy.ops.export_scene.gltf(filepath=str(tmp_path / "plain.glb"), export_format="GLB") == {"FINISHED"}
    finally:
        prefs.addons.remove(added)
    doc, _ = glb(tmp_path / "plain.glb")
    assert NAME not in doc.get("extensionsUsed", []) and "extensions" not in doc


def test_panel_export_button(baked, tmp_path):
    """The Preview panel's Export glTF (PRTT): the operator the button runs,
    with the file browser's path; the same file as the command line's."""
    work = tmp_path / "p"
    shutil.copytree(baked, work)
    bpy = addon_bpy()
    bpy.ops.wm.open_mainfile(filepath=str(work / "scene.blend"))
    before = digest(work / "scene.blend")
    assert bpy.ops.prtt.export_gltf(filepath=str(work / "panel.glb")) == {"FINISHED"}
    assert run("export", "scene.blend", "--out", "cli.glb", cwd=work).returncode == 0
    a, _ = glb(work / "panel.glb")
    b, _ = glb(work / "cli.glb")
    assert a["extensions"][NAME] == b["extensions"][NAME]
    assert digest(work / "scene.blend") == before
