"""`python -m prtt_addon.dev.bench web` end to end at a toy size: the demo room
baked at 64² with 16 rays, exported, loaded in headless Chromium and drawn at
160 × 90 (one timed frame), and the room with 4 bunnies for the triangle
table; the record holds every figure docs/benchmarks.md's block reads."""
import json
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# a few minutes on 2 cores (two bakes, three exports, eight page loads)
pytestmark = [pytest.mark.slow, pytest.mark.blender]


def positive(value, what):
    assert isinstance(value, (int, float)) and value > 0, (what, value)


def test_web_bench_at_a_toy_size(tmp_path):
    pytest.importorskip("bpy")
    pytest.importorskip("playwright")
    from prtt_addon.dev.bench import figures, web_bench
    if not os.path.exists(web_bench.BROWSER):
        pytest.skip("Debian's chromium-headless-shell is needed: ./prtt.sh installs it")
    out = tmp_path / "web.json"
    r = subprocess.run([sys.executable, "-m", "prtt_addon.dev.bench", "web", "--resolution", "64", "--rays", "16",
                        "--bounce-rays", "16", "--size", "160x90", "--small-size", "80x45", "--frames", "1",
                        "--loads", "1", "--scenes", "21K,300K", "--scaling-resolution", "64",
                        "--json", str(out)],
                       capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=ROOT), cwd=ROOT, timeout=1800)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]
    rec = json.loads(out.read_text())
    assert rec["command"].startswith("python -m prtt_addon.dev.bench web ") and rec["date"] and rec["machine"]["cores"]
    assert rec["settings"]["resolution"] == 64 and rec["settings"]["size"] == [160, 90]
    assert rec["errors"] == []
    assert "SwiftShader" in rec["browser"]["webgl_renderer"], rec["browser"]
    assert len(rec["loadavg"]["start"]) == 3 and len(rec["loadavg"]["end"]) == 3
    assert {"bake", "export half", "page loads u8", "tp frames", "300K 80x45"} <= set(rec["loadavg"]["after"])
    assert rec["code"] is None or rec["code"]["commit"]
    positive(rec["scene"]["triangles"], "triangles")
    for k in ("seconds", "wall_s"):
        positive(rec["bake"][k], f"bake {k}")
    for k in ("cli_wall_s", "export_glb_s", "export_glb_again_s", "ratio", "ratio_cli"):
        positive(rec["export"][k], f"export {k}")
    by = rec["bytes"]
    for k in ("glb", "ratio_glb_to_exr", "ratio_textures_to_exr"):
        positive(by[k], k)
    for k in ("textures", "environment", "total", "uncompressed_textures"):
        positive(by["payload"][k], f"payload {k}")
    positive(by["payload"]["kinds"]["transfer"], "transfer payload")
    positive(by["payload"]["kinds"]["relightDC"], "relightable bounce payload")
    assert by["payload"]["total"] < by["glb"]
    assert by["exr"]["all_half_lossless"], by["exr"]            # PRTT writes half, ZIP / PIZ
    assert set(by["exr"]["files"]) == {"atlas.transfer.exr", "atlas.relight.exr"}
    positive(by["exr"]["total"], "EXR bytes")
    assert [e["encoding"] for e in rec["encodings"]] == ["half", "u8"] and rec["export"]["encoding"] == "half"
    for e in rec["encodings"]:
        for k in ("cli_wall_s", "export_glb_s", "glb", "ratio", "ratio_glb_to_exr"):
            positive(e[k], f"{e['encoding']} {k}")
        positive(e["page_load"]["median_s"], f"{e['encoding']} page load")
    assert rec["encodings"][1]["payload"]["textures"] < rec["encodings"][0]["payload"]["textures"]
    assert len(rec["page_load"]["seconds"]) == 1
    positive(rec["page_load"]["median_s"], "page load")
    assert [f["mode"] for f in rec["frames"]] == ["tpfl", "tp", "diffuse"]
    for f in rec["frames"]:
        assert len(f["ms"]) == 1
        for k in ("median_ms", "min_ms", "max_ms", "load_s"):
            positive(f[k], f"{f['mode']} {k}")
    assert [s["scene"] for s in rec["scaling"]] == ["21K", "300K"]
    assert rec["scaling"][1]["triangles"] > 10 * rec["scaling"][0]["triangles"] > 200_000
    for s in rec["scaling"]:
        for k in ("triangles", "bake_s", "export_wall_s", "glb_bytes"):
            positive(s[k], f"{s['scene']} {k}")
        assert [(z["width"], z["height"]) for z in s["sizes"]] == [(160, 90), (80, 45)]
        for z in s["sizes"]:
            positive(z["median_ms"], f"{s['scene']} frame")
            positive(z["ns_per_pixel"], f"{s['scene']} ns/pixel")
    # the docs' block is made from such a record, and the output quotes it
    block = figures.web_block(rec)
    assert "| export / bake |" in block and "| 300K | " in block
    assert block in r.stdout
