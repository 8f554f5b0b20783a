"""The viewer's SH maths in JavaScript (viewer/prtt_sh.js, viewer/prtt_env.js)
against the Python core it ports: basis, Gaunt non-zeros, the PRTTLight /
PRTTRelight / Gaunt-table layouts, SH rotation and the World's Z turn, and the
equirect projection (random pixels, Blender's forest.exr through three's
EXRLoader, Radiance .hdr files flat and run-length encoded), plus bad input.

Each test runs `node` on a small ES module that imports the real files by
file URL (a resolve hook sends `three` to tools/js/node_modules) and prints
JSON; Python computes the same with prtt_addon.core and compares."""
import json
import math
import pathlib
import shutil
import subprocess

import numpy as np
import pytest

from prtt_addon.core.io.image_io import ImageReadError, read_hdr_image
from prtt_addon.core.light import envmap
from prtt_addon.core.preview import pack
from prtt_addon.core.sh.basis import eval_basis
from prtt_addon.core.sh.gaunt import sparse_gaunt, tpfl_matrix
from prtt_addon.core.sh.rotation import rotate, sh_rotation

ROOT = pathlib.Path(__file__).resolve().parent.parent
NODE = shutil.which("node")
pytestmark = pytest.mark.skipif(NODE is None, reason="node is not installed: the viewer's JavaScript cannot run")

SH_URL = (ROOT / "viewer" / "prtt_sh.js").as_uri()
ENV_URL = (ROOT / "viewer" / "prtt_env.js").as_uri()
THREE_PARENT = (ROOT / "tools" / "js" / "package.json").as_uri()

HOOKS = """
let parent;
export async function initialize(data) { parent = data.parent; }
export async function resolve(specifier, context, next) {
  if (specifier === 'three' || specifier.startsWith('three/')) return next(specifier, { ...context, parentURL: parent });
  return next(specifier, context);
}
"""

PRELUDE = f"""
import fs from 'node:fs';
import * as S from {json.dumps(SH_URL)};
const {{ environmentFromBytes }} = await import({json.dumps(ENV_URL)});
const IN = JSON.parse(fs.readFileSync(new URL('./in.json', import.meta.url), 'utf8'));
const arr = (a) => Array.from(a);
const out = (x) => process.stdout.write(JSON.stringify(x));
const errorOf = async (f) => {{
  try {{ await f(); return null; }} catch (e) {{ return (e instanceof Error ? 'Error: ' : 'not an Error: ') + e.message; }}
}};
"""


def run_js(tmp_path, body: str, inputs=None, timeout: float = 60.0):
    """Run PRELUDE + body as an ES module in tmp_path; returns its printed JSON."""
    (tmp_path / "hooks.mjs").write_text(HOOKS)
    (tmp_path / "register.mjs").write_text(
        "import { register } from 'node:module';\n"
        f"register(new URL('./hooks.mjs', import.meta.url), {{ data: {{ parent: {json.dumps(THREE_PARENT)} }} }});\n")
    (tmp_path / "in.json").write_text(json.dumps(inputs if inputs is not None else {}))
    script = tmp_path / "run.mjs"
    script.write_text(PRELUDE + body)
    proc = subprocess.run([NODE, "--import", (tmp_path / "register.mjs").as_uri(), str(script)],
                          cwd=tmp_path, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"node failed ({proc.returncode}):\n{proc.stderr[-4000:]}"
    return json.loads(proc.stdout)


def max_rel(js, py) -> float:
    """max |js - py| / max |py| (the error relative to the array's scale)."""
    js, py = np.asarray(js, np.float64), np.asarray(py, np.float64)
    assert js.shape == py.shape, (js.shape, py.shape)
    return float(np.abs(js - py).max() / max(np.abs(py).max(), 1e-300))


def random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


# --- basis and quadrature ----------------------------------------------------------------

def test_basis_matches_eval_basis(tmp_path):
    rng = np.random.default_rng(1)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:6] = [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]]   # poles and axes
    res = run_js(tmp_path, """
      const r = {};
      for (let n = 1; n <= 8; n++) r[n] = IN.dirs.map((d) => arr(S.shBasis(d, n)));
      r.errors = [await errorOf(() => S.shBasis([0, 0, 2], 3)), await errorOf(() => S.shBasis([0, 0, 0], 3)),
                  await errorOf(() => S.shBasis([0, 0, 1], 0))];
      r.normalized = arr(S.shBasis([0, 0, 2], 3, true));
      out(r);
    """, {"dirs": d.tolist()})
    worst = 0.0
    for n in range(1, 9):
        ref = eval_basis(d, n)
        js = np.array(res[str(n)])
        assert js.shape == ref.shape
        np.testing.assert_allclose(js, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
        worst = max(worst, max_rel(js, ref))
    print(f"shBasis max error / max |y| (bands 1..8): {worst:.3g}")
    assert all(e and e.startswith("Error: ") for e in res["errors"]), res["errors"]
    assert "not 1" in res["errors"][0] and "zero vector" in res["errors"][1] and "1..64" in res["errors"][2]
    np.testing.assert_allclose(res["normalized"], eval_basis([0, 0, 1], 3), rtol=0, atol=1e-15)


def test_gauss_legendre_matches_numpy(tmp_path):
    ns = [1, 2, 3, 5, 9, 16, 40]
    res = run_js(tmp_path, "out(IN.ns.map((n) => { const g = S.gaussLegendre(n); return [arr(g.x), arr(g.w)]; }));",
                 {"ns": ns})
    worst = 0.0
    for n, (x, w) in zip(ns, res):
        rx, rw = np.polynomial.legendre.leggauss(n)
        np.testing.assert_allclose(x, rx, rtol=0, atol=1e-14)
        # numpy's weights (eigenvalues, one Newton step) are off by up to 7e-13
        # at n = 40; the Newton-converged ones here are within 2e-14 of mpmath's.
        np.testing.assert_allclose(w, rw, rtol=1e-12, atol=0)
        worst = max(worst, float(np.abs(np.array(x) - rx).max()), max_rel(w, rw))
    print(f"gaussLegendre max error: {worst:.3g}")


# --- Gaunt tensor and the uniform blocks --------------------------------------------------

def test_gaunt_nonzeros_match_sparse_gaunt(tmp_path):
    res = run_js(tmp_path, """
      const r = {};
      for (let n = 1; n <= 6; n++) { const g = S.gauntNonzeros(n); r[n] = [arr(g.i), arr(g.j), arr(g.k), arr(g.value), g.nnz]; }
      r.cached = S.gauntNonzeros(4) === S.gauntNonzeros(4);
      r.tooMany = await errorOf(() => S.gauntNonzeros(17));
      out(r);
    """)
    worst = 0.0
    for n in range(1, 7):
        g = sparse_gaunt(n)
        i, j, k, v, nnz = res[str(n)]
        assert nnz == g.nnz
        np.testing.assert_array_equal(i, g.i)
        np.testing.assert_array_equal(j, g.j)
        np.testing.assert_array_equal(k, g.k)
        np.testing.assert_allclose(v, g.value, rtol=0, atol=1e-12)
        worst = max(worst, float(np.abs(np.array(v) - g.value).max()))
    print(f"gauntNonzeros max |error| (bands 1..6): {worst:.3g}")
    assert res["cached"] is True
    assert res["tooMany"].startswith("Error: ") and "1..16" in res["tooMany"]


@pytest.mark.parametrize("bands", [3, 5])
def test_light_blocks_match_pack(tmp_path, bands):
    rng = np.random.default_rng(bands)
    K = bands * bands
    L = rng.normal(size=(K, 3))
    longer = rng.normal(size=(25 + 11, 3))[:25]        # a 5-band light drawn into a 3-band block
    res = run_js(tmp_path, """
      out({light: arr(S.lightBlock(IN.L, IN.bands)), relight: arr(S.relightBlock(IN.L, IN.bands)),
           tpfl: S.tpflMatrix(IN.L, IN.bands).map((M) => M.map(arr)),
           lightLong: arr(S.lightBlock(IN.longer, 3)), relightLong: arr(S.relightBlock(IN.longer, 3)),
           isF32: S.lightBlock(IN.L, IN.bands) instanceof Float32Array});
    """, {"L": L.tolist(), "bands": bands, "longer": longer.tolist()})
    assert res["isF32"] is True
    errors = {}
    for key, js, ref in [("lightBlock", res["light"], pack.light_block(L, bands)),
                         ("relightBlock", res["relight"], pack.relight_block(L, bands)),
                         ("lightBlock(5-band light, 3)", res["lightLong"], pack.light_block(longer, 3)),
                         ("relightBlock(5-band light, 3)", res["relightLong"], pack.relight_block(longer, 3))]:
        js = np.array(js)
        assert js.shape == ref.shape, key
        np.testing.assert_allclose(js, ref, rtol=1e-6, atol=1e-7 * np.abs(ref).max(), err_msg=key)
        errors[key] = float(np.abs(js - ref).max())
    M = tpfl_matrix(L, bands)
    np.testing.assert_allclose(res["tpfl"], M, rtol=0, atol=1e-13 * np.abs(M).max())
    errors["tpflMatrix"] = float(np.abs(np.array(res["tpfl"]) - M).max())
    print(f"bands {bands} max |error|: " + ", ".join(f"{k} {v:.3g}" for k, v in errors.items()))


@pytest.mark.parametrize("bands,width", [(1, 4), (3, 7), (5, 64), (5, 4096)])
def test_gaunt_table_matches_pack(tmp_path, bands, width):
    res = run_js(tmp_path, "const t = S.gauntTable(IN.bands, IN.width); out({...t, data: arr(t.data)});",
                 {"bands": bands, "width": width})
    ref = pack.gaunt_table(bands, width)
    assert (res["rows"], res["width"], res["nnz"]) == (ref.shape[0], width, sparse_gaunt(bands).nnz)
    js = np.array(res["data"]).reshape(ref.shape)
    np.testing.assert_array_equal(js[..., :3], ref[..., :3])
    np.testing.assert_allclose(js[..., 3], ref[..., 3], rtol=1e-6, atol=1e-7)
    print(f"gauntTable({bands}, {width}) max |error|: {np.abs(js - ref).max():.3g}")


# --- rotation and the World's turn ------------------------------------------------------------

def test_rotation_matches_python(tmp_path):
    rng = np.random.default_rng(7)
    Rs = [random_rotation(rng) for _ in range(6)] + [np.eye(3), np.diag([-1.0, -1.0, 1.0])]
    L = rng.normal(size=(25, 3))
    angles = [0.0, 30.0, -70.0, 90.0, 180.0, 275.5]
    eulers = [rng.uniform(-math.pi, math.pi, size=3).tolist() for _ in range(3)]
    res = run_js(tmp_path, """
      out({D: IN.Rs.map((R) => S.shRotation(R, 5).map(arr)), rot: IN.Rs.map((R) => S.rotateLight(IN.L, R)),
           turn: IN.angles.map((a) => S.turnLightZ(IN.L, a)),
           mapping: IN.eulers.map((e) => [S.mappingRotation(e, 'POINT'), S.mappingRotation(e, 'TEXTURE')]),
           composed: IN.eulers.map((e) => [S.composeLight(IN.L, 2.5, S.mappingRotation(e, 'POINT')),
                                           S.composeLight(IN.L, 0.5, S.mappingRotation(e, 'TEXTURE'))]),
           plain: S.composeLight(IN.L, 3.0, null),
           errors: [await errorOf(() => S.shRotation([[1, 0, 0], [0, 1, 0], [0, 0, -1]], 3)),
                    await errorOf(() => S.shRotation([[2, 0, 0], [0, 1, 0], [0, 0, 1]], 3)),
                    await errorOf(() => S.mappingRotation([0, 0, 1], 'VECTOR'))]});
    """, {"Rs": [R.tolist() for R in Rs], "L": L.tolist(), "angles": angles, "eulers": eulers})
    err = {}
    for R, D, rot in zip(Rs, res["D"], res["rot"]):
        ref = sh_rotation(R, 5)
        np.testing.assert_allclose(D, ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(rot, rotate(L, R), rtol=0, atol=1e-12 * np.abs(L).max())
        err["shRotation"] = max(err.get("shRotation", 0.0), float(np.abs(np.array(D) - ref).max()))
        err["rotateLight"] = max(err.get("rotateLight", 0.0), float(np.abs(np.array(rot) - rotate(L, R)).max()))
    for a, turned in zip(angles, res["turn"]):
        ref = envmap.compose_light(L, 1.0, envmap.mapping_rotation((0.0, 0.0, math.radians(a))))
        np.testing.assert_allclose(turned, ref, rtol=0, atol=1e-12 * np.abs(L).max(), err_msg=f"turn {a}")
        err["turnLightZ"] = max(err.get("turnLightZ", 0.0), float(np.abs(np.array(turned) - ref).max()))
    # The sign is not a matter of taste: turning by -a is a different light.
    assert np.abs(np.array(res["turn"][2]) - envmap.compose_light(
        L, 1.0, envmap.mapping_rotation((0.0, 0.0, math.radians(70.0))))).max() > 0.1
    for e, (mp, mt), (cp, ct) in zip(eulers, res["mapping"], res["composed"]):
        Rp, Rt = envmap.mapping_rotation(e, "POINT"), envmap.mapping_rotation(e, "TEXTURE")
        np.testing.assert_allclose(mp, Rp, rtol=0, atol=1e-15)
        np.testing.assert_allclose(mt, Rt, rtol=0, atol=1e-15)
        np.testing.assert_allclose(cp, envmap.compose_light(L, 2.5, Rp), rtol=0, atol=1e-11)
        np.testing.assert_allclose(ct, envmap.compose_light(L, 0.5, Rt), rtol=0, atol=1e-11)
        err["composeLight"] = max(err.get("composeLight", 0.0),
                                  float(np.abs(np.array(cp) - envmap.compose_light(L, 2.5, Rp)).max()),
                                  float(np.abs(np.array(ct) - envmap.compose_light(L, 0.5, Rt)).max()))
    np.testing.assert_array_equal(res["plain"], L * 3.0)
    assert "reflection" in res["errors"][0] and "orthonormal" in res["errors"][1] and "POINT" in res["errors"][2]
    print("max |error|: " + ", ".join(f"{k} {v:.3g}" for k, v in err.items()))


# --- equirect projection -------------------------------------------------------------------------

def test_project_equirect_random(tmp_path):
    rng = np.random.default_rng(11)
    img = rng.uniform(-0.2, 3.0, size=(16, 32, 4)).astype(np.float32)   # negatives clamp to 0
    img[3, 5, :3] = [40.0, 20.0, 10.0]                                      # a small sun
    tall = rng.uniform(0.0, 1.0, size=(9, 5, 3)).astype(np.float32)       # odd sizes, not 2:1
    res = run_js(tmp_path, """
      const rgba = Float32Array.from(IN.img), rgb = Float32Array.from(IN.tall);
      const r = {};
      for (let n = 1; n <= 8; n++) r[n] = [S.projectEquirect(rgba, 32, 16, 4, n), S.projectEquirect(rgb, 5, 9, 3, n)];
      out(r);
    """, {"img": img.ravel().tolist(), "tall": tall.ravel().tolist()})
    worst = 0.0
    for n in range(1, 9):
        for js, ref in zip(res[str(n)], (envmap.project_equirect(img, n), envmap.project_equirect(tall, n))):
            np.testing.assert_allclose(js, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
            worst = max(worst, max_rel(js, ref))
    print(f"projectEquirect (16x32 RGBA, 9x5 RGB) max error / max |c|: {worst:.3g}")


def test_forest_exr_through_exrloader(tmp_path):
    try:
        path = envmap.builtin_environment_path("forest")
    except ImageReadError:
        pytest.skip("bpy's studio lights are not installed (no forest.exr)")
    res = run_js(tmp_path, """
      const bytes = new Uint8Array(fs.readFileSync(IN.path));
      const e = await environmentFromBytes(bytes, 'forest.exr', 5);
      const viaBuffer = await environmentFromBytes(bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.length),
                                                   'forest.exr', 2);
      out({...e, L2: viaBuffer.L});
    """, {"path": str(path)}, timeout=120)
    ref = envmap.project_equirect("forest", 5)
    assert (res["width"], res["height"], res["name"]) == (1024, 512, "forest.exr")
    js = np.array(res["L"])
    # forest.exr is DWAB-compressed half floats: three's decoder and OpenEXR's
    # differ by a few half ulps in ~0.1 % of pixels (1e-6 of the light here).
    np.testing.assert_allclose(js, ref, rtol=0, atol=1e-5 * np.abs(ref).max())
    np.testing.assert_allclose(res["L2"], ref[:4], rtol=0, atol=1e-5 * np.abs(ref).max())
    # Rows in the wrong order (EXRLoader's are bottom first) would negate the
    # terms odd in z, such as this one, which is far from zero for this sky.
    assert np.abs(ref[2]).max() > 0.1 * np.abs(ref).max()
    print(f"forest.exr bands 5 max error / max |c|: {max_rel(js, ref):.3g}")


def rle_scanline(row: np.ndarray) -> bytes:
    """New-style run-length encoding of one (W, 4) uint8 scanline."""
    w = row.shape[0]
    out = bytearray([2, 2, w >> 8, w & 0xFF])
    for c in range(4):
        ch = row[:, c].tolist()
        x = 0
        while x < w:
            run = 1
            while x + run < w and run < 127 and ch[x + run] == ch[x]:
                run += 1
            if run >= 3:
                out += bytes([128 + run, ch[x]])
                x += run
                continue
            start = x
            while x < w and x - start < 128:
                if x + 2 < w and ch[x] == ch[x + 1] == ch[x + 2]:
                    break
                x += 1
            out += bytes([x - start]) + bytes(ch[start:x])
    return bytes(out)


def radiance_bytes(rgbe: np.ndarray, *, rle: bool, bottom_up: bool = False) -> bytes:
    """A Radiance file of (H, W, 4) RGBE bytes given in top-first order."""
    h, w, _ = rgbe.shape
    rows = rgbe[::-1] if bottom_up else rgbe
    head = b"#?RADIANCE\n# written by test_viewer_sh\nFORMAT=32-bit_rle_rgbe\nEXPOSURE=1.0\n\n"
    head += f"{'+' if bottom_up else '-'}Y {h} +X {w}\n".encode()
    body = b"".join(rle_scanline(r) if rle else r.tobytes() for r in rows)
    return head + body


def test_radiance_hdr_matches_python(tmp_path):
    rng = np.random.default_rng(3)
    h, w = 12, 24
    rgbe = rng.integers(0, 256, size=(h, w, 4), dtype=np.uint8)
    rgbe[..., 3] = rng.integers(120, 140, size=(h, w))
    rgbe[2, :10] = [200, 100, 50, 130]                   # runs for the run-length coder
    rgbe[5, :, 3] = 0                                     # e = 0 is black
    rgbe[7, 3:20, 1] = 77
    rgbe[8:] = [90, 60, 30, 129]                          # flat rows: the run-length file is shorter
    rgbe[9, ::5] = [10, 250, 3, 131]
    files = {}
    for name, kw in {"flat.hdr": dict(rle=False), "rle.hdr": dict(rle=True),
                     "bottomup.hdr": dict(rle=True, bottom_up=True)}.items():
        (tmp_path / name).write_bytes(radiance_bytes(rgbe, **kw))
        files[name] = str(tmp_path / name)
    assert len((tmp_path / "rle.hdr").read_bytes()) < len((tmp_path / "flat.hdr").read_bytes())
    res = run_js(tmp_path, """
      const r = {};
      for (const [name, path] of Object.entries(IN.files)) {
        const e = await environmentFromBytes(fs.readFileSync(path), name, 4);
        r[name] = [e.L, e.width, e.height];
      }
      out(r);
    """, {"files": files})
    ref = envmap.project_equirect(read_hdr_image(files["flat.hdr"]), 4)
    for name, path in files.items():
        np.testing.assert_array_equal(read_hdr_image(path), read_hdr_image(files["flat.hdr"]))   # the writer
        js, jw, jh = res[name]
        assert (jw, jh) == (w, h)
        np.testing.assert_allclose(js, ref, rtol=0, atol=1e-12 * np.abs(ref).max(), err_msg=name)
        print(f"{name} bands 4 max error / max |c|: {max_rel(js, ref):.3g}")


# --- bad input ------------------------------------------------------------------------------

def test_bad_input_is_a_clear_error(tmp_path):
    exr_huge = (b"v/1\x01" + (2).to_bytes(4, "little") + b"dataWindow\0box2i\0" + (16).to_bytes(4, "little")
                + np.array([0, 0, 40000, 99], "<i4").tobytes() + b"\0")
    inputs = {
        "garbage": list(np.random.default_rng(0).integers(0, 256, 300, dtype=np.uint8).tobytes()),
        "png": list(b"\x89PNG\r\n\x1a\n" + b"\0" * 32),
        "exrJunk": list(b"v/1\x01" + b"\0" * 20),
        "exrHuge": list(exr_huge),
        "hdrTrunc": list(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 4 +X 8\n\x02\x02\x00\x08\x05"),
        "hdrHuge": list(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 30000 +X 30000\n"),
        "hdrNoEnd": list(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n" + b"x" * 70000),
        "hdrFormat": list(b"#?RADIANCE\nFORMAT=32-bit_rle_xyze\n\n-Y 2 +X 2\n" + b"\x80" * 16),
    }
    try:
        forest = envmap.builtin_environment_path("forest")
        with open(forest, "rb") as f:
            inputs["exrCut"] = list(f.read(3000))        # a real header, its pixels cut off
    except ImageReadError:
        pass
    res = run_js(tmp_path, """
      const r = {};
      for (const key of Object.keys(IN)) r[key] = await errorOf(() => environmentFromBytes(new Uint8Array(IN[key]), key, 3));
      const px = new Float32Array(4 * 8 * 3).fill(1);
      px[5] = NaN; px[30] = Infinity; px[31] = -Infinity;
      r.nan = await errorOf(() => S.projectEquirect(px, 8, 4, 3, 3));
      r.oversized = await errorOf(() => S.projectEquirect(new Float32Array(3), 16384, 8192, 3, 3));
      r.short = await errorOf(() => S.projectEquirect(new Float32Array(5), 8, 4, 3, 3));
      r.bands0 = await errorOf(() => S.projectEquirect(new Float32Array(96), 8, 4, 3, 0));
      r.bands9 = await errorOf(() => S.projectEquirect(new Float32Array(96), 8, 4, 3, 9));
      r.channels = await errorOf(() => S.projectEquirect(new Float32Array(64), 8, 4, 2, 3));
      r.envBands = await errorOf(() => environmentFromBytes(new Uint8Array(4), 'x.hdr', 12));
      out(r);
    """, inputs, timeout=60)
    for key, msg in res.items():
        assert msg is not None and msg.startswith("Error: "), (key, msg)
    expect = {
        "garbage": "garbage: not an OpenEXR or Radiance HDR file",
        "png": "png: a PNG image is not HDR",
        "exrJunk": "exrJunk: unreadable EXR",
        "exrHuge": "exrHuge: 40001x100 pixels; an environment image may have 1..32768",
        "hdrTrunc": "hdrTrunc: corrupt Radiance run-length data",
        "hdrHuge": "hdrHuge: 30000x30000 pixels",
        "hdrNoEnd": "hdrNoEnd: Radiance header longer than 65536 bytes",
        "hdrFormat": "hdrFormat: unsupported Radiance format 32-bit_rle_xyze",
        "exrCut": "exrCut: unreadable EXR",
        "nan": "environment image has 2 NaN/Inf pixels",
        "oversized": "16384x8192 = 134217728 pixels; at most 67108864 (64 Mi)",
        "short": "environment data has 5 values; 8x4x3 = 96 expected",
        "bands0": "bands must be an integer in 1..8, got 0",
        "bands9": "bands must be an integer in 1..8, got 9",
        "channels": "3 or 4 channels, got 2",
        "envBands": "bands must be an integer in 1..8, got 12",
    }
    for key, text in expect.items():
        if key in res:
            assert text in res[key], (key, res[key])
    # The same bytes are refused by the Python reader too (the messages are ports).
    for key in ("png", "exrJunk", "hdrTrunc", "hdrHuge", "hdrFormat"):
        p = tmp_path / f"{key}.bin"
        p.write_bytes(bytes(inputs[key]))
        with pytest.raises(ImageReadError):
            read_hdr_image(p)
    with pytest.raises(ValueError, match="2 NaN/Inf pixels"):
        img = np.ones((4, 8, 3))
        img[0, 1, 2], img[1, 2, 0], img[1, 2, 1] = np.nan, np.inf, -np.inf
        envmap.project_equirect(img, 3)
