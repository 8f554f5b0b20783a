"""`prtt export` (issue 34): a baked .blend as a .glb through Blender's own
glTF exporter, with the PRTT_radiance_transfer extension, checked by reading
the .glb back (JSON, buffer views, KTX2 through ktx-parse too, PNGs, the
World's image) against the EXRs, Blender's pixels and what the preview draws,
by the extension's JSON schema, and by Blender's own glTF importer. The .blend
is never modified."""
import io
import json
import math
import os
import shutil
import struct
import subprocess

import numpy as np
import pytest

from prtt_addon.core.io.exr_io import read_relight_exr, read_sh_exr
from prtt_addon.core.io.gltf_prtt import GLTF_TO_BAKE_FRAME, NAME
from prtt_addon.core.io.image_write import srgb_encode
from prtt_addon.core.io.ktx2 import parse_ktx2
from prtt_addon.core.light.envmap import compose_light, project_equirect
from prtt_addon.core.preview import pack as pp
from prtt_addon.core.shading.display import from_payload
from tests import real_scenes as rs
from tests.blender_util import addon_bpy
from tests.test_headless_chain import digest, run
from tests.test_ktx2 import node

pytestmark = pytest.mark.blender
BAKE = ["--resolution", "32", "--rays", "16", "--bounces", "0"]
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCHEMA = json.load(open(os.path.join(ROOT, "docs", "schema", "PRTT_radiance_transfer.schema.json")))


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


def ktx2_layers(doc, binary, meta, tmp_path=None, kind=None):
    """The (layers, H, W, 4) float16 of a payload, checked against its JSON
    (and, given tmp_path, by ktx-parse)."""
    blob = view(doc, binary, meta["bufferView"])
    assert len(blob) == meta["bytes"]
    (layers,), keys = parse_ktx2(blob)
    assert layers.shape == (meta["layers"], meta["height"], meta["width"], 4) and layers.dtype == np.float16
    assert keys["PRTTcoefficients"] == str(meta["coefficients"])
    if kind is not None:
        assert keys["PRTTkind"] == kind
    if tmp_path is not None:
        f = tmp_path / f"payload{meta['bufferView']}.ktx2"
        f.write_bytes(blob)
        info = json.loads(node("ktx_info.mjs", f))               # an independent parser agrees
        assert (info["vkFormat"], info["layerCount"], info["pixelWidth"]) == (97, meta["layers"], meta["width"])
    return layers


def same_half(got, want):
    """float16 ``got`` holds exactly ``want`` (float32) rounded to float16."""
    want16 = np.asarray(want, np.float32).astype(np.float16)
    return got.shape == want16.shape and np.array_equal(got.view(np.uint16), want16.view(np.uint16))


def png(doc, binary, image_index):
    from PIL import Image  # matplotlib's dependency (tests only)
    img = doc["images"][image_index]
    assert img["mimeType"] == "image/png"
    return np.asarray(Image.open(io.BytesIO(view(doc, binary, img["bufferView"]))).convert("RGBA"), np.float64) / 255


def accessor(doc, binary, index):
    acc = doc["accessors"][index]
    n = {"VEC2": 2, "VEC3": 3, "VEC4": 4, "SCALAR": 1}[acc["type"]]
    dtype = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5121: np.uint8}[acc["componentType"]]
    bv = doc["bufferViews"][acc["bufferView"]]
    assert bv.get("byteStride", n * np.dtype(dtype).itemsize) == n * np.dtype(dtype).itemsize
    return np.frombuffer(view(doc, binary, acc["bufferView"]), dtype, count=acc["count"] * n,
                         offset=acc.get("byteOffset", 0)).reshape(acc["count"], n)


# --- a small JSON Schema check (jsonschema is not a dependency): the keywords the schema uses ---

_KEYWORDS = {"$schema", "$id", "$defs", "title", "description", "type", "required", "properties", "items",
             "minItems", "maxItems", "const", "enum", "minimum", "maximum"}
_TYPES = {"object": dict, "array": list, "string": str, "boolean": bool, "integer": int, "number": (int, float)}


def schema_keywords(node_, out=None):
    out = set() if out is None else out
    if isinstance(node_, dict):
        for k, v in node_.items():
            out.add(k)
            if k in ("properties", "$defs"):
                for sub in v.values():
                    schema_keywords(sub, out)
            elif k == "items":
                schema_keywords(v, out)
    return out


def validate(value, schema, where="$"):
    """Raise AssertionError naming where ``value`` breaks ``schema``."""
    t = schema.get("type")
    if t is not None:
        ok = isinstance(value, _TYPES[t]) and not (t in ("integer", "number") and isinstance(value, bool))
        assert ok, f"{where}: {value!r} is not {t}"
    if "const" in schema:
        assert value == schema["const"], f"{where}: {value!r} != {schema['const']!r}"
    if "enum" in schema:
        assert value in schema["enum"], f"{where}: {value!r} not in {schema['enum']}"
    if "minimum" in schema:
        assert value >= schema["minimum"], f"{where}: {value} < {schema['minimum']}"
    if "maximum" in schema:
        assert value <= schema["maximum"], f"{where}: {value} > {schema['maximum']}"
    if isinstance(value, dict):
        for k in schema.get("required", []):
            assert k in value, f"{where}: {k!r} missing"
        for k, sub in schema.get("properties", {}).items():
            if k in value:
                validate(value[k], sub, f"{where}.{k}")
    if isinstance(value, list):
        assert len(value) >= schema.get("minItems", 0) and len(value) <= schema.get("maxItems", len(value)), where
        if "items" in schema:
            for i, v in enumerate(value):
                validate(v, schema["items"], f"{where}[{i}]")


def validate_file(doc):
    """Every PRTT part of a .glb's JSON against the extension's schema."""
    assert schema_keywords(SCHEMA) <= _KEYWORDS, schema_keywords(SCHEMA) - _KEYWORDS
    validate(doc["extensions"][NAME], SCHEMA)
    parts = [("node", n) for n in doc["nodes"]] + [("material", m) for m in doc.get("materials", [])]
    parts += [("primitive", p) for m in doc["meshes"] for p in m["primitives"]]
    for kind, part in parts:
        ext = (part.get("extensions") or {}).get(NAME)
        if ext is not None:
            validate(ext, SCHEMA["$defs"][kind], f"{kind} {part.get('name', '')}")


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    """A folder with a baked scene.blend (floor and box unwrapped by the
    bake, a camera, the built-in light) and its textures."""
    tmp = tmp_path_factory.mktemp("gltf")
    bpy = addon_bpy()
    rs.floor_and_box(bpy)
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
    validate_file(doc)
    ext = doc["extensions"][NAME]
    table = ext["display"].pop("table")                                 # the factory file's AgX, sampled
    assert ext["display"] == {"exposure": 1.0, "stops": 0.0, "viewTransform": "AgX", "look": "None",
                              "displayDevice": "sRGB", "gamma": 1.0}
    assert table["size"] == 65 and table["encoding"] == "uint16-zstd" and table["shaper"] == [-12.0, 12.0]
    payload = view(doc, binary, table["bufferView"])
    agx = from_payload(payload, 65)                                     # what Blender's AgX makes of grey
    assert 0.3 < agx.encode(np.full((1, 3), 0.18))[0, 0] < 0.6
    assert len(payload) < 65 ** 3 * 6 / 2
    assert "view transform" not in r.stdout, r.stdout
    assert "bounce" not in r.stdout
    assert "sun" not in ext and not any("sun" in s for s in ext["sets"])    # no Sun lamp: no sun
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


# --- bounces, materials, the display and the World (issue 34, the export's second part) ---------------

def bumps(n=32):
    """A tangent-space normal map (file order, 0.5 + 0.5 n)."""
    y, x = (np.mgrid[0:n, 0:n] + 0.5) / n
    nx, ny = 0.4 * np.sin(2 * np.pi * x), 0.3 * np.cos(2 * np.pi * 3 * y)
    v = np.stack([nx, ny, np.ones_like(nx)], -1)
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    return (0.5 + 0.5 * v).astype(np.float32)


def bake_scene(tmp, *bake):
    """Floor and a box with a normal-mapped material (a float Non-Color image
    on the PRTT map, the box's only UV map), baked with ``bake``'s options."""
    bpy = addon_bpy()
    from prtt_addon.dev.bench import scene_build as sb  # needs bpy
    rs.floor(bpy, 6.0)
    box = rs.add_object(bpy, "Box", rs.cube_mesh(bpy, "box"), location=(0, 0, 0.5))
    mat = sb.principled("Bumpy", base_color=(0.6, 0.5, 0.4), roughness=0.3)
    nt = mat.node_tree
    bsdf = next(n for n in nt.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
    tex = nt.nodes.new("ShaderNodeTexImage")
    tex.image = sb.float_image("bumps", bumps(), non_color=True)
    nm = nt.nodes.new("ShaderNodeNormalMap")
    nm.inputs["Strength"].default_value = 0.7
    nt.links.new(tex.outputs["Color"], nm.inputs["Color"])
    nt.links.new(nm.outputs["Normal"], bsdf.inputs["Normal"])
    box.data.materials.append(mat)
    rs.scene_camera(bpy, (0, -7, 4), (1.05, 0, 0))
    bpy.context.scene.prtt.light_source = "BUILTIN"
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp / "scene.blend"))
    r = run("bake", "scene.blend", "--out", "textures", "--unwrap", "SMART", "--resolution", "32", "--rays", "16",
            *bake, cwd=tmp)
    assert r.returncode == 0, r.stderr + r.stdout
    return tmp


@pytest.fixture(scope="module")
def relit(tmp_path_factory):
    return bake_scene(tmp_path_factory.mktemp("relit"), "--bounces", "1", "--bounce-rays", "8")


@pytest.fixture(scope="module")
def bounced(tmp_path_factory):
    return bake_scene(tmp_path_factory.mktemp("bounced"), "--bounces", "2", "--bounce-rays", "8",
                      "--bounce-mode", "baked")


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The demo scene (prtt_addon/dev/demo.py: the plank floor's float base colour
    and roughness images, the forest World through a Mapping node, exposure
    -0.7 with the Standard view transform), baked small."""
    tmp = tmp_path_factory.mktemp("demo")
    bpy = addon_bpy()
    from prtt_addon.dev.bench.scene_build import demo_scene
    demo_scene()
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp / "demo.blend"))
    r = run("bake", "demo.blend", "--out", "textures", "--unwrap", "SMART", *BAKE, cwd=tmp)
    assert r.returncode == 0, r.stderr + r.stdout
    return tmp


def export(folder, blend="scene.blend", out="room.glb", *args):
    """`prtt export` of ``blend`` in ``folder`` (its bytes unchanged): (JSON, binary, stdout)."""
    before = digest(folder / blend)
    r = run("export", blend, "--out", out, *args, cwd=folder)
    assert r.returncode == 0, r.stderr + r.stdout
    assert digest(folder / blend) == before                            # the .blend is never modified
    doc, binary = glb(folder / out)
    validate_file(doc)
    return doc, binary, r.stdout


def preview_scene(path):
    """What the Blender preview draws for the .blend at ``path``: (bpy, PreviewScene)."""
    bpy = addon_bpy()
    bpy.ops.wm.open_mainfile(filepath=str(path))
    from prtt_addon.blender.preview.drawlist import clear_caches, collect
    clear_caches()
    ps, status = collect(bpy.context, use_bounces=True)
    assert ps is not None, status.messages
    return bpy, ps


def test_relightable_bounce_dc_and_glossy_rows(relit, tmp_path):
    doc, binary, out = export(relit)
    assert "glossy" not in out and "stale" not in out, out
    ext = doc["extensions"][NAME]
    K = ext["sh"]["coefficients"]
    for s in ext["sets"]:
        dc, glossy, attrs = read_relight_exr(relit / "textures" / f"{s['name']}.relight.exr")
        assert attrs["glossy_bands"] > 0 and "bounce" not in s
        H, W = dc.shape[:2]
        K4, Kg = pp.layers(K), glossy.shape[-1]
        op = pp.pack_relight_operator(dc, glossy)[:, ::-1]         # the preview's layers, rows top first
        got = ktx2_layers(doc, binary, s["relightDC"], tmp_path, "relight-dc")
        assert s["relightDC"]["colours"] == 3 and s["relightDC"]["layersPerColour"] == K4
        assert same_half(got, op[:3 * K4]), s["name"]
        for c in range(3):                                         # the documented layout, coefficient by coefficient
            for i in (0, K - 1):
                want = dc[::-1, :, c, i].astype(np.float16)
                assert np.array_equal(got[c * K4 + i // 4, :, :, i % 4], want)
        meta = s["relightGlossy"]
        Kg4 = pp.layers(Kg)
        assert (meta["coefficients"], meta["glossyBands"], meta["glossyCoefficients"], meta["layersPerRow"],
                meta["colours"]) == (K, attrs["glossy_bands"], Kg, Kg4, 3)
        got = ktx2_layers(doc, binary, meta, tmp_path, "relight-glossy")
        if attrs.get("glossy_colour") == "shared":
            # stored once for all colours, as the EXR holds them: a third of the bytes
            assert meta["glossyColour"] == "shared"
            _, stored, _ = read_relight_exr(relit / "textures" / f"{s['name']}.relight.exr", expand=False)
            assert got.shape == ((Kg - 1) * Kg4, H, W, 4)
            for o, i in ((1, 0), (Kg - 1, Kg - 1), (3, 5)):
                layer = (o - 1) * Kg4 + i // 4
                assert np.array_equal(got[layer, :, :, i % 4], stored[::-1, :, o - 1, i].astype(np.float16))
            # the documented tint (kappa_c = DC_c,0 / mean_c DC_c,0) gives the preview's rows back
            got_dc = ktx2_layers(doc, binary, s["relightDC"], tmp_path, "relight-dc")
            d0 = np.stack([got_dc[c * K4, :, :, 0] for c in range(3)], -1).astype(np.float64)
            m = d0.mean(-1, keepdims=True)
            kappa = np.divide(d0, m, out=np.ones_like(d0), where=np.abs(m) > 1e-3 * np.abs(d0).max(-1, keepdims=True))
            rows = got.astype(np.float32).reshape(Kg - 1, Kg4, H, W, 4)
            for c, o, i in ((0, 1, 0), (1, Kg - 1, Kg - 1), (2, 3, 5)):
                tinted = kappa[..., c] * rows[o - 1, i // 4, :, :, i % 4]
                np.testing.assert_allclose(tinted, glossy[::-1, :, c, o - 1, i], rtol=2e-3, atol=1e-7)
        else:
            assert meta["glossyColour"] == "per-colour"
            assert got.shape == (3 * (Kg - 1) * Kg4, H, W, 4)
            assert same_half(got, op[3 * K4:]), s["name"]
            for c, o, i in ((0, 1, 0), (1, Kg - 1, Kg - 1), (2, 3, 5)):
                layer = (c * (Kg - 1) + o - 1) * Kg4 + i // 4
                assert np.array_equal(got[layer, :, :, i % 4], glossy[::-1, :, c, o - 1, i].astype(np.float16))


def test_baked_bounce_levels_summed_as_the_preview_draws_them(bounced, tmp_path):
    doc, binary, out = export(bounced)
    assert "not in the glTF" not in out, out
    ext = doc["extensions"][NAME]
    K = ext["sh"]["coefficients"]
    bpy, ps = preview_scene(bounced / "scene.blend")
    for s in ext["sets"]:
        pset = ps.sets[s["name"]]
        assert len(pset.bounces) == 2 and "relightDC" not in s
        b = pset.load_bounce(K)                                    # (H, W, 3, K), every level summed
        parts = [read_sh_exr(p)[0] for p in pset.bounces]
        assert np.allclose(b, sum(parts))
        meta = s["bounce"]
        assert (meta["coefficients"], meta["colours"], meta["layersPerColour"], meta["levels"]) == \
            (K, 3, pp.layers(K), 2)
        got = ktx2_layers(doc, binary, meta, tmp_path, "bounce")
        assert same_half(got, pp.pack_bounce(b)[:, ::-1]), s["name"]
        assert np.array_equal(got[2 * pp.layers(K) + 1, :, :, 2], b[::-1, :, 2, 6].astype(np.float16))


def test_normal_mapped_material(relit, tmp_path):
    """The Box's material: its PreviewMaterial's parameters, a normalTexture
    with the preview's pixels to 8 bits, tangents exported."""
    doc, binary, out = export(relit)
    assert "bumps" in out                                          # written from the preview's pixels
    bpy, ps = preview_scene(relit / "scene.blend")
    pm = ps.materials[ps.material_names.index("Bumpy")]
    assert pm.normal_texture >= 0
    mat = next(m for m in doc["materials"] if m["name"] == "Bumpy")
    ext = mat["extensions"][NAME]
    assert ext == {"baseColor": [float(c) for c in pm.base_color[:3]], "metallic": pm.metallic,
                   "roughness": pm.roughness, "f0": pm.f0, "normalStrength": pm.normal_strength,
                   "baseColorTexture": False, "roughnessTexture": False, "normalTexture": True}
    assert abs(ext["normalStrength"] - 0.7) < 1e-6
    nt = mat["normalTexture"]
    node_ = {n["name"]: n for n in doc["nodes"]}["Box"]
    prim = doc["meshes"][node_["mesh"]]["primitives"][0]
    assert f"TEXCOORD_{nt.get('texCoord', 0)}" in prim["attributes"] and "TANGENT" in prim["attributes"]
    got = png(doc, binary, doc["textures"][nt["index"]]["source"])
    want = ps.images[pm.normal_texture][..., :3]                    # file order, the preview's values
    err = np.abs(got[..., :3] - want).max()
    assert err <= 0.5 / 255 + 1e-6, err


def test_demo_floor_textures_and_materials(demo, tmp_path):
    """The demo's plank floor: base colour and roughness texels of the .glb's
    PNGs equal Blender's image pixels to 8-bit rounding (base colour
    sRGB-encoded, as glTF says), at the UVs the preview uses; every material
    of a baked object carries the preview's parameters."""
    doc, binary, out = export(demo, "demo.blend", "demo.glb")
    ext = doc["extensions"][NAME]
    assert ext["display"] == {"exposure": 2 ** ext["display"]["stops"], "stops": pytest.approx(-0.7),
                              "viewTransform": "Standard"}
    assert "view transform" not in out
    bpy, ps = preview_scene(demo / "demo.blend")
    gl_mats = {m["name"]: m for m in doc["materials"]}
    assert {n for n in ps.material_names if n is not None} == {n for n, m in gl_mats.items()
                                                               if NAME in m.get("extensions", {})}
    for name, pm in zip(ps.material_names, ps.materials):
        if name is None:                                           # objects without a material: no glTF material
            continue
        e = gl_mats[name]["extensions"][NAME]
        assert e["baseColor"] == [float(c) for c in pm.base_color[:3]] and e["f0"] == pm.f0, name
        assert (e["metallic"], e["roughness"], e["normalStrength"]) == (pm.metallic, pm.roughness,
                                                                         pm.normal_strength), name
        assert (e["baseColorTexture"], e["roughnessTexture"], e["normalTexture"]) == \
            (pm.base_texture >= 0, pm.roughness_texture >= 0, pm.normal_texture >= 0), name
    floor = gl_mats["floor"]
    assert floor["extensions"][NAME]["baseColorTexture"] and floor["extensions"][NAME]["roughnessTexture"]
    pbr = floor["pbrMetallicRoughness"]
    blender = {n: np.array(bpy.data.images[n].pixels[:], np.float64).reshape(512, 512, 4)[::-1]
               for n in ("floor_color", "floor_roughness")}          # Blender's pixels, file order
    base = png(doc, binary, doc["textures"][pbr["baseColorTexture"]["index"]]["source"])
    err_base = np.abs(base[..., :3] - srgb_encode(blender["floor_color"][..., :3])).max()
    rough = png(doc, binary, doc["textures"][pbr["metallicRoughnessTexture"]["index"]]["source"])
    err_rough = np.abs(rough[..., 1] - blender["floor_roughness"][..., 0]).max()
    print(f"floor texels: base colour {err_base * 255:.4f} levels (sRGB), roughness {err_rough * 255:.4f} levels")
    assert err_base <= 0.5 / 255 + 1e-6 and err_rough <= 0.5 / 255 + 1e-6, (err_base, err_rough)
    # the texture's TEXCOORD is the preview's material UVs (and the PRTT one its PRTT UVs), v flipped
    node_ = {n["name"]: n for n in doc["nodes"]}["floor"]
    prim = doc["meshes"][node_["mesh"]]["primitives"][0]
    assert pbr["baseColorTexture"].get("texCoord", 0) == pbr["metallicRoughnessTexture"].get("texCoord", 0)
    tc = accessor(doc, binary, prim["attributes"][f"TEXCOORD_{pbr['baseColorTexture'].get('texCoord', 0)}"])
    prtt = accessor(doc, binary, prim["attributes"][f"TEXCOORD_{prim['extensions'][NAME]['texCoord']}"])
    got = {(round(float(a), 4), round(1 - float(b), 4), round(float(c), 4), round(1 - float(d), 4))
           for (a, b), (c, d) in zip(prtt, tc)}
    dm = next(m for m in ps.meshes if m.name == "floor")
    want = {(round(float(a), 4), round(float(b), 4), round(float(c), 4), round(float(d), 4))
            for (a, b), (c, d) in zip(dm.uv, dm.mat_uv)}
    assert got == want


def test_environment_reprojects_to_the_light(demo, tmp_path):
    """The World's image travels as its file's bytes; projected and turned with
    the environment's numbers it gives the root's light (a turned Mapping node
    of type Texture here)."""
    bpy = addon_bpy()
    bpy.ops.wm.open_mainfile(filepath=str(demo / "demo.blend"))
    mapping = next(n for n in bpy.context.scene.world.node_tree.nodes if n.bl_idname == "ShaderNodeMapping")
    mapping.inputs["Rotation"].default_value = (0.3, -0.2, 1.1)
    mapping.vector_type = "TEXTURE"
    bpy.context.scene.world.node_tree.nodes["Background"].inputs["Strength"].default_value = 1.7
    work = tmp_path / "p"
    shutil.copytree(demo, work)
    bpy.ops.wm.save_as_mainfile(filepath=str(work / "turned.blend"))
    doc, binary, _ = export(work, "turned.blend", "turned.glb")
    ext = doc["extensions"][NAME]
    env = ext["environment"]
    assert env["rotation"] == pytest.approx([0.3, -0.2, 1.1]) and env["vectorType"] == "TEXTURE"
    assert env["strength"] == pytest.approx(1.7)
    image = env["image"]
    data = view(doc, binary, image["bufferView"])
    src = bpy.path.abspath(bpy.data.worlds["Forest"].node_tree.nodes["Environment Texture"].image.filepath)
    assert data == open(src, "rb").read() and image["bytes"] == len(data) and image["mimeType"] == "image/x-exr"
    f = tmp_path / ("env" + os.path.splitext(src)[1])
    f.write_bytes(data)
    light = compose_light(project_equirect(str(f), ext["sh"]["bands"]), env["strength"],
                          np.asarray(env["lookupRotation"]))
    want = np.asarray(ext["light"]["rgb"])
    rel = np.abs(light - want).max() / np.abs(want).max()
    assert rel < 1e-6, rel
    # (the unturned light is far from it: the test sees the turn)
    assert np.abs(compose_light(project_equirect(str(f), 5), 1.7) - want).max() / np.abs(want).max() > 0.05


def test_environment_without_an_image_and_over_the_bound(baked, tmp_path, monkeypatch):
    """A constant World: its colour, no image, a note; an image over the bound:
    left out with a note (in-process, the bound lowered)."""
    from prtt_addon.blender.gltf import export as gx
    bpy = addon_bpy()
    work = tmp_path / "p"
    shutil.copytree(baked, work)
    bpy.ops.wm.open_mainfile(filepath=str(work / "scene.blend"))
    before = digest(work / "scene.blend")
    monkeypatch.setattr(gx, "ENVIRONMENT_MAX_BYTES", 1000)
    summary = gx.export_glb(bpy.context, str(work / "small.glb"))
    assert any("MiB the glTF carries" in n for n in summary["notes"]), summary["notes"]
    doc, _ = glb(work / "small.glb")
    assert "image" not in doc["extensions"][NAME]["environment"]
    world = bpy.data.worlds.new("Plain")
    world.color = (0.2, 0.3, 0.4)
    if world.node_tree:                                  # Blender 5: a Background node, its colour unlinked
        world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.2, 0.3, 0.4, 1.0)
    bpy.context.scene.world = world
    bpy.context.scene.prtt.light_source = "WORLD"
    summary = gx.export_glb(bpy.context, str(work / "plain.glb"))
    assert any("constant colour" in n for n in summary["notes"]), summary["notes"]
    doc, _ = glb(work / "plain.glb")
    validate_file(doc)
    env = doc["extensions"][NAME]["environment"]
    assert "image" not in env and env["color"] == pytest.approx([0.2, 0.3, 0.4])
    L = np.asarray(doc["extensions"][NAME]["light"]["rgb"])
    assert L[0] == pytest.approx(np.array([0.2, 0.3, 0.4]) * math.sqrt(4 * math.pi)) and np.abs(L[1:]).max() == 0
    assert digest(work / "scene.blend") == before


# --- instances (tiles) and UVs generated at bake time ------------------------------------------------

#: Blender's frame -> glTF's: (x, y, z) -> (x, z, -y).
TO_GLTF = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])


def gltf_tile(uv, tile):
    """docs/gltf.md's formula: a node's tile applied to glTF texture
    coordinates (u, v) (v down from the top row), giving where to sample the
    set's KTX2 (same convention)."""
    columns, rows, column, row, inset = tile
    s = 1.0 - 2.0 * inset
    return np.stack([(column + inset + uv[:, 0] * s) / columns,
                     1.0 - (row + inset + (1.0 - uv[:, 1]) * s) / rows], axis=1)


def world_matrices(doc):
    """{node index: 4 x 4 world matrix} in glTF's frame."""
    def local(n):
        if "matrix" in n:
            return np.asarray(n["matrix"], np.float64).reshape(4, 4).T
        x, y, z, w = n.get("rotation", (0, 0, 0, 1))
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        M = np.eye(4)
        M[:3, :3] = R * np.asarray(n.get("scale", (1, 1, 1)))
        M[:3, 3] = n.get("translation", (0, 0, 0))
        return M
    out = {}

    def walk(i, parent):
        out[i] = parent @ local(doc["nodes"][i])
        for c in doc["nodes"][i].get("children", []):
            walk(c, out[i])
    for i in doc["scenes"][doc.get("scene", 0)]["nodes"]:
        walk(i, np.eye(4))
    return out


@pytest.fixture(scope="module")
def instanced(tmp_path_factory):
    """test_headless_chain's scene (collection instances of an excluded
    collection's cube: UVs generated per instance group; a geometry-nodes
    grid: generated; a faceless helper) with an extruded curve, a text and
    geometry-nodes instances of an unwrapped cube, baked."""
    tmp = tmp_path_factory.mktemp("instanced")
    bpy = addon_bpy()
    rs.chain_scene(bpy, generated=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp / "scene.blend"))
    r = run("bake", "scene.blend", "--out", "textures", "--unwrap", "SMART", *BAKE, cwd=tmp)
    assert r.returncode == 0, r.stderr + r.stdout
    return tmp


def test_instances_and_generated_uvs_as_the_preview_draws_them(instanced):
    """Each drawn object's and instance's node: its set and tile; its mesh's
    PRTT TEXCOORD, the tile applied by docs/gltf.md's formula, at each
    vertex equal to the UVs the Blender preview draws there (collect());
    generated UVs (instances of a mesh without a PRTT map, geometry-nodes
    faces, a curve, a text) reach a TEXCOORD; nothing Blender does not render."""
    doc, binary, out = export(instanced)
    assert "left out of the glTF" in out and "SrcCube" in out, out       # the excluded source collection
    ext = doc["extensions"][NAME]
    bpy, ps = preview_scene(instanced / "scene.blend")
    info = json.loads(bpy.context.scene.prtt.last_bake)
    assert {r["uv"] for r in info["objects"].values()} == {"map", "generated"}
    assert sum(1 for r in info["objects"].values() if r.get("tile")) == 5
    worlds = world_matrices(doc)
    C = np.eye(4)
    C[:3, :3] = TO_GLTF
    drawn = {m.name: m for m in ps.meshes}
    seen = set()
    for i, M in worlds.items():
        n = doc["nodes"][i]
        e = (n.get("extensions") or {}).get(NAME)
        if "mesh" not in n:
            continue
        assert e is not None, f"node {n.get('name')}: a mesh without PRTT data (not rendered by Blender?)"
        B = np.linalg.inv(C) @ M @ C                                   # the node's world matrix, Blender's frame
        name = next(k for k, m in drawn.items() if k not in seen and np.allclose(m.matrix, B, atol=1e-5)
                    and ext["sets"][e["set"]]["name"] == m.set_name)
        seen.add(name)
        rec = info["objects"][name]
        assert e.get("tile") == (list(rec["tile"]) if rec.get("tile") else None), name
        dm = drawn[name]
        want = {}
        for p, u, nrm in zip(dm.positions, dm.uv, dm.normals):
            want.setdefault(tuple(np.round(np.r_[p, u].astype(np.float64), 4)), []).append(nrm)
        got = set()
        for prim in doc["meshes"][n["mesh"]]["primitives"]:
            pos = accessor(doc, binary, prim["attributes"]["POSITION"]) @ TO_GLTF    # glTF -> Blender: p T
            nor = accessor(doc, binary, prim["attributes"]["NORMAL"]) @ TO_GLTF
            uv = accessor(doc, binary, prim["attributes"][f"TEXCOORD_{prim['extensions'][NAME]['texCoord']}"])
            uv = gltf_tile(uv.astype(np.float64), e["tile"]) if "tile" in e else uv.astype(np.float64)
            uv[:, 1] = 1.0 - uv[:, 1]                                   # glTF's v -> Blender's
            for p, u, nrm in zip(pos, uv, nor):
                k = tuple(np.round(np.r_[p, u].astype(np.float64), 4))
                got.add(k)
                assert k not in want or min(np.abs(nrm - w).max() for w in want[k]) < 1e-3, (name, k, nrm)
        assert got == set(want), (name, sorted(got - set(want))[:4], sorted(set(want) - got)[:4])
    assert seen == set(drawn) == set(info["objects"])
    # Blender's own importer opens it
    code = ("import bpy; bpy.ops.wm.read_factory_settings(use_empty=True); "
            f"r = bpy.ops.import_scene.gltf(filepath={str(instanced / 'room.glb')!r}); print('IMPORTED', r)")
    r = subprocess.run([os.sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert "IMPORTED {'FINISHED'}" in r.stdout, r.stdout + r.stderr


def test_instances_export_leaves_blenders_data_as_it_was(instanced, tmp_path):
    """In the same Blender session: the temporary meshes that carry generated
    UVs are gone after the export, nothing else in bpy.data changed."""
    from prtt_addon.blender.gltf.export import export_glb
    bpy = addon_bpy()
    bpy.ops.wm.open_mainfile(filepath=str(instanced / "scene.blend"))

    def state():
        return {kind: sorted(x.name for x in getattr(bpy.data, kind))
                for kind in ("meshes", "objects", "materials", "images", "collections", "node_groups")}
    before = state()
    summary = export_glb(bpy.context, str(tmp_path / "room.glb"))
    assert summary["objects"] == 11
    assert state() == before


def test_the_8_bit_encoding_keeps_its_stated_error(relit, tmp_path):
    """--encoding u8: each payload RGBA8 (ktx-parse reads vkFormat 37), each
    plane decoding as offset + scale * q, within maxError <= scale / 2 of the
    half-float payload's values (which equal the EXRs to float16), valid
    against the schema; fewer bytes."""
    from prtt_addon.core.io.gltf_prtt import decode_u8
    doc_h, bin_h, _ = export(relit, "scene.blend", "half.glb")
    doc, binary, _ = export(relit, "scene.blend", "u8.glb", "--encoding", "u8")
    ext, ext_h = doc["extensions"][NAME], doc_h["extensions"][NAME]
    n = 0
    for s, s_h in zip(ext["sets"], ext_h["sets"]):
        for key in ("transfer", "relightDC", "relightGlossy"):
            meta = s[key]
            assert (meta["format"], meta["encoding"]) == ("RGBA8", "u8")
            blob = view(doc, binary, meta["bufferView"])
            (q,), _ = parse_ktx2(blob)
            f = tmp_path / f"u8_{n}.ktx2"
            f.write_bytes(blob)
            info = json.loads(node("ktx_info.mjs", f))
            assert (info["vkFormat"], info["typeSize"], info["layerCount"]) == (37, 1, meta["layers"])
            want = ktx2_layers(doc_h, bin_h, s_h[key]).astype(np.float32)
            got = decode_u8(q, meta["scale"], meta["offset"])
            err = float(np.abs(got - want).max())
            scale = np.asarray(meta["scale"]).reshape(-1, 4)
            assert err <= meta["maxError"] * (1 + 1e-6) + 1e-7, (key, err, meta["maxError"])
            # float16 rounding of the reference aside, each plane within half its step
            per_plane = np.abs(got - want).max(axis=(1, 2))
            assert np.all(per_plane <= scale / 2 + np.abs(want).max(axis=(1, 2)) * 2.0 ** -10 + 1e-7), key
            n += 1
    assert n >= 3
    assert (relit / "u8.glb").stat().st_size < (relit / "half.glb").stat().st_size


def test_a_missing_world_image_exports_with_a_named_stand_in(tmp_path):
    """A transfer-only bake under a World whose HDRI file is then lost (issue
    50, defect 6): export refused it ("has no pixels ... bake again", and
    baking again did not help). It exports, lit by the studio HDRI that
    FALLBACK_LIGHT names, and says so in a note and in the light's description."""
    from prtt_addon.blender.gltf.export import FALLBACK_LIGHT
    from prtt_addon.core.light.envmap import builtin_environment_path
    from prtt_addon.dev.bench.scene_build import environment_world
    bpy = addon_bpy()
    rs.floor(bpy, 6.0)
    rs.add_object(bpy, "Box", rs.cube_mesh(bpy, "box"), location=(0, 0, 0.5))
    hdri = tmp_path / "sky.exr"
    shutil.copy(builtin_environment_path("city"), hdri)
    bpy.context.scene.world = environment_world("Sky", str(hdri))
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    r = run("bake", "scene.blend", "--out", "textures", "--unwrap", "SMART", *BAKE, cwd=tmp_path)
    assert r.returncode == 0, r.stderr + r.stdout
    hdri.unlink()
    doc, binary, out = export(tmp_path)
    assert f"the glTF is lit by the studio HDRI {FALLBACK_LIGHT!r} instead" in out and "sky.exr" in out, out
    light = doc["extensions"][NAME]["light"]
    assert FALLBACK_LIGHT in light["description"] and "cannot be read" in light["description"], light
    want = project_equirect(builtin_environment_path(FALLBACK_LIGHT), 5)
    got = np.array(light["rgb"], dtype=np.float64).reshape(-1, 3)
    assert np.allclose(got[0], want[0], rtol=1e-3), (got[0], want[0])          # DC: any rotation


def _lamp_and_udim_scene(tmp, *, lamp: bool, udim: bool):
    bpy = addon_bpy()
    _, box = rs.floor_and_box(bpy, camera=False)
    if lamp:
        data = bpy.data.lights.new("Bulb", "POINT")
        if hasattr(data, "normalize"):
            data.normalize = False            # what trips bpy 5.0.1's exporter (its Light.area() call)
        ob = bpy.data.objects.new("Bulb", data)
        ob.location = (1, 1, 3)
        bpy.context.scene.collection.objects.link(ob)
    if udim:
        from prtt_addon.dev.bench.scene_build import principled
        img = bpy.data.images.new("tiles", 8, 8, tiled=True)
        img.source = "TILED"
        img.filepath = str(tmp / "test.<UDIM>.png")        # no such files
        mat = principled("Tiled")
        nt = mat.node_tree
        tex = nt.nodes.new("ShaderNodeTexImage")
        tex.image = img
        nt.links.new(tex.outputs["Color"], next(n for n in nt.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
                     .inputs["Base Color"])
        box.data.materials.append(mat)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp / "scene.blend"))
    r = run("bake", "scene.blend", "--out", "textures", "--unwrap", "SMART", *BAKE, cwd=tmp)
    assert r.returncode == 0, r.stderr + r.stdout


def test_a_lamp_the_exporter_fails_on_is_left_out_with_a_note(tmp_path):
    """bpy 5.0.1's exporter raises on a point lamp with Normalize off (the
    glTF-Blender-IO test scenes' lamps: "PointLight.area(): ... (world_matrix)",
    issue 50 defect 7): the lamp is left out, not the export."""
    _lamp_and_udim_scene(tmp_path, lamp=True, udim=False)
    doc, _, out = export(tmp_path)
    assert NAME in doc["extensions"] and "Traceback" not in out
    import bpy
    if bpy.app.version[:2] == (5, 0):                   # the exporter's bug: the note says so
        assert "lamps left out of the glTF" in out, out


def test_an_exporter_failure_is_one_line_saying_what_to_do(tmp_path):
    """A UDIM image Blender's exporter cannot take: it raised a traceback into
    the user's console; now one line says what it said was wrong."""
    _lamp_and_udim_scene(tmp_path, lamp=False, udim=True)
    r = run("export", "scene.blend", "--out", "room.glb", cwd=tmp_path)
    assert r.returncode == 1 and not (tmp_path / "room.glb").exists(), r.stdout + r.stderr
    err = [ln for ln in r.stderr.splitlines() if ln.startswith("prtt: error:")]
    assert len(err) == 1 and "Blender's glTF exporter failed: UDIM" in err[0], r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    # --verbose shows what the exporter printed, then the same one line
    r = run("export", "scene.blend", "--out", "room.glb", "--verbose", cwd=tmp_path)
    assert r.returncode == 1 and "Starting glTF 2.0 export" in r.stderr, r.stderr[-2000:]
    assert r.stderr.rstrip().splitlines()[-1].startswith("prtt: error: Blender's glTF exporter failed: UDIM")


def test_exporter_failures_are_read_for_their_cause():
    """What Blender's exporter printed names the cause: a file it could not
    read (a missing UDIM tile), its own ERROR line, a lamp it failed on."""
    from prtt_addon.blender.gltf.export import _ExporterFailed
    tb = "Error: Python: Traceback (most recent call last):\n  File \"x.py\", line 1\nAssertionError\nLocation: ops.py:109"
    e = _ExporterFailed(tb, "INFO: Starting\nCannot read '/p/test.1001.png': No such file or directory\n")
    assert "/p/test.1001.png" in e.message and "missing" in e.message and not e.in_lights
    e = _ExporterFailed(tb, "19:01 | ERROR: UDIM packed images are not supported for export.\n")
    assert e.message.startswith("Blender's glTF exporter failed: UDIM packed images") and e.last == "AssertionError"
    e = _ExporterFailed("  File \".../blender/exp/lights.py\", line 130\nTypeError: PointLight.area(): was called "
                        "with invalid keyword argument(s) (world_matrix)")
    assert e.in_lights and "world_matrix" in e.last


def test_armatures_export_in_the_pose_they_were_baked_in(tmp_path):
    """A posed, moved armature with a skinned box (Armature modifier) and a
    bone-parented ball (issue 50, defect 5: refused, "PRTT's data did not
    reach the file (objects without it: Ball)", Blender's exporter having put
    the armature in its rest position): exported as the bake saw them, every
    vertex of the glTF in world space where Blender's evaluated mesh has it."""
    bpy = addon_bpy()
    _, box = rs.floor_and_box(bpy, camera=False)
    ball = rs.add_object(bpy, "Ball", rs.cube_mesh(bpy, "ball"), location=(2, 0, 0.5))
    rig = bpy.data.objects.new("Rig", bpy.data.armatures.new("Rig"))
    bpy.context.scene.collection.objects.link(rig)
    bpy.context.view_layer.objects.active = rig
    bpy.ops.object.mode_set(mode="EDIT")
    bone = rig.data.edit_bones.new("Bone")
    bone.head, bone.tail = (0, 0, 0), (0, 0, 1)
    bpy.ops.object.mode_set(mode="OBJECT")
    mod = box.modifiers.new("Armature", "ARMATURE")
    mod.object = rig
    box.vertex_groups.new(name="Bone").add(list(range(len(box.data.vertices))), 1.0, "REPLACE")
    ball.parent, ball.parent_type, ball.parent_bone = rig, "BONE", "Bone"
    rig.location, rig.rotation_euler = (1.0, 2.0, 0.3), (0, 0, 0.5)
    rig.pose.bones["Bone"].rotation_mode = "XYZ"
    rig.pose.bones["Bone"].rotation_euler = (0.2, 0, 0)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    r = run("bake", "scene.blend", "--out", "textures", "--unwrap", "SMART", *BAKE, cwd=tmp_path)
    assert r.returncode == 0, r.stderr + r.stdout
    doc, binary, _ = export(tmp_path)
    tagged = {n["name"] for n in doc["nodes"] if NAME in (n.get("extensions") or {})}
    assert tagged == {"Floor", "Box", "Ball"}, tagged
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "scene.blend"))
    dg = bpy.context.evaluated_depsgraph_get()
    worlds = world_matrices(doc)
    to_blender = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], np.float64)      # glTF Y-up -> Blender Z-up
    for i, n in enumerate(doc["nodes"]):
        if n.get("name") not in ("Box", "Ball"):
            continue
        ob = bpy.data.objects[n["name"]].evaluated_get(dg)
        me = ob.to_mesh()
        want = np.array([ob.matrix_world @ v.co for v in me.vertices], np.float64)
        ob.to_mesh_clear()
        pos = np.concatenate([accessor(doc, binary, p["attributes"]["POSITION"])
                              for p in doc["meshes"][n["mesh"]]["primitives"]]).astype(np.float64)
        got = (pos @ worlds[i][:3, :3].T + worlds[i][:3, 3]) @ to_blender.T
        d = np.linalg.norm(got[:, None] - want[None], axis=2)
        assert d.min(axis=1).max() < 1e-4 and d.min(axis=0).max() < 1e-4, (n["name"], d.min(axis=1).max())


def test_an_out_in_a_missing_folder_is_refused_before_any_work(baked, tmp_path):
    """`export --out missing/room.glb` worked 4 s, then named its temporary
    file; the folder is checked first, as `render` checks it."""
    r = run("export", str(baked / "scene.blend"), "--out", "missing/room.glb", cwd=tmp_path)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "prtt: error: --out missing/room.glb: the folder missing does not exist" in r.stderr, r.stderr
    assert "Read blend" not in r.stdout + r.stderr                   # refused before the .blend is opened
