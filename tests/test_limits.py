"""A setting at its largest allowed value on a tiny scene, under a memory
limit (issue 50, defect 1): every allocation that grows with a setting is
bounded or checked before it is made.

`bake --resolution 16384 --unwrap smart` once rasterised each unwrap check at
16384² (40 GiB) before any memory check: the out-of-memory killer ended it at
23 GB, or under `ulimit -v` a raw numpy traceback, while the bake itself gave
the objects 1024² and 512² (Tuning Auto makes Resolution a cap)."""
import json
import resource
import subprocess
import sys

import numpy as np
import pytest

from tests import real_scenes as rs
from tests.blender_util import addon_bpy
from tests.test_headless_chain import ROOT

#: Address space a limited child gets: bpy maps ~2 GiB of its own.
LIMIT = 6 << 30


def run_limited(*args, cwd, limit=LIMIT):
    """``python -m prtt_addon ARGS`` in ``cwd`` under an address-space limit of ``limit`` bytes."""
    return subprocess.run([sys.executable, "-m", "prtt_addon", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=900, preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (limit, limit)),
                          env={"PYTHONPATH": ROOT, "PATH": "/usr/bin:/bin"})


def test_overlap_count_is_rasterize_s_count_in_bands():
    from prtt_addon.core.texels import raster
    rng = np.random.default_rng(7)
    for n, w, h in ((300, 257, 300), (50, 1024, 1024), (2000, 64, 64)):
        uv = rng.random((n, 3, 2))
        assert raster.overlap_count(uv, w, h) == raster.rasterize(uv, w, h).overlap_texels
    # bands and triangle groups far smaller than the layout: many cuts, the same count
    uv = rng.random((200, 3, 2))
    want = raster.rasterize(uv, 300, 200).overlap_texels
    old = raster.OVERLAP_BAND_TEXELS, raster.OVERLAP_GROUP_CLAIMS
    try:
        raster.OVERLAP_BAND_TEXELS, raster.OVERLAP_GROUP_CLAIMS = 1000, 500
        assert raster.overlap_count(uv, 300, 200) == want
    finally:
        raster.OVERLAP_BAND_TEXELS, raster.OVERLAP_GROUP_CLAIMS = old


def test_overlap_count_of_stacked_uvs_fits_a_small_limit():
    """Two quads stacked on the whole UV square at 8192²: 134 M texel claims
    (rasterize holds ~7 GB for them); the banded count under a 2 GiB address
    space limit."""
    code = ("import resource, numpy as np; resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30));"
            "from prtt_addon.core.texels.raster import overlap_count;"
            "uv = np.tile(np.array([[[0, 0], [1, 0], [0, 1]], [[1, 1], [0, 1], [1, 0]]], float), (2, 1, 1));"
            "print(overlap_count(uv, 8192, 8192))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=900,
                       env={"PYTHONPATH": ROOT, "PATH": "/usr/bin:/bin", "OPENBLAS_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr[-2000:]
    assert int(r.stdout.split()[-1]) == 8192 * 8192


@pytest.mark.blender
def test_bake_at_the_largest_resolution_with_unwrap_on_a_tiny_scene(tmp_path):
    """The issue's command, under a 6 GiB address-space limit: it bakes, the
    sets get the resolutions Tuning Auto gives them, and the unwrap leaves
    margins for those (no overlapping texels at 1024² / 512²)."""
    bpy = addon_bpy()
    rs.floor_and_box(bpy)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    r = run_limited("bake", "scene.blend", "--resolution", "16384", "--unwrap", "smart", "--rays", "16",
                    "--bounces", "0", "--out", "tex", cwd=tmp_path)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
    # the cap is said, not silent
    assert "baking 2 set(s), 14 triangles: Floor 1024x1024, Box 512x512" in r.stdout, r.stdout
    assert "Tuning Auto sizes each object's own set from its surface area" in r.stdout
    with open(tmp_path / "tex" / "manifest.json", encoding="utf-8") as f:
        sets = {s["name"]: s for s in json.load(f)["sets"]}
    assert sets["Floor"]["resolution"] == [1024, 1024] and sets["Box"]["resolution"] == [512, 512]
    assert all(s["overlap_texels"] == 0 for s in sets.values())
    # the unwrap's islands are sized for those resolutions: the PRTT maps at
    # 512² for the box have no overlapping texels (margins of 1/16384 would)
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "scene.blend"))
    from prtt_addon.blender.scene.uv_maps import overlap_texels
    assert overlap_texels(bpy.data.objects["Box"], 512) == 0
    # render at a size no machine holds, under the same limit: refused in one line, nothing written
    r = run_limited("render", "scene.blend", "--out", "big.png", "--size", "100000x100000", cwd=tmp_path)
    assert r.returncode == 1 and "render smaller (--size WxH)" in r.stderr, r.stdout[-2000:] + r.stderr[-2000:]
    assert "Traceback" not in r.stderr and not (tmp_path / "big.png").exists()


def test_every_bake_setting_at_its_largest_is_refused_before_it_is_baked(tmp_path):
    """Tuning fixed, 16384², 16 bands, the most rays, bounces, patterns and
    the largest chunks on a tiny scene, under a 6 GiB address-space limit:
    refused by the memory plan in one line before anything is traced. And two
    relightable bounces at 16 bands (512²), which the plan once undercounted
    (the next level's rows, 12 K bytes a texel and more) and which then ran out
    of memory half-way through the second level: refused up front too."""
    bpy = addon_bpy()
    rs.floor_and_box(bpy)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    most = ("--tuning", "fixed", "--bands", "16", "--rays", "65536", "--bounce-rays", "16384", "--vertex", "--mips",
            "--dilate", "64", "--patterns", "1024", "--chunk-rays", "4194304")
    for resolution, bounces in (("16384", "8"), ("512", "2")):
        r = run_limited("bake", "scene.blend", "--unwrap", "smart", "--resolution", resolution, "--bounces", bounces,
                        *most, "--out", "tex", cwd=tmp_path)
        out = r.stdout + r.stderr
        assert r.returncode == 1 and "needs about" in out and "but only" in out, out[-3000:]
        assert "Traceback" not in out and "during the bake" not in out and "trace [" not in out, out[-3000:]
        assert not (tmp_path / "tex" / "manifest.json").exists()


@pytest.mark.blender
def test_export_under_a_memory_limit_is_made_or_refused_up_front(tmp_path):
    """The glTF export of relightable sets (tuning fixed: the relightable
    textures at the set's resolution) under a 3 GiB address-space limit: at
    512² it is written; at 1024² (a set's payloads need about 2.2 GiB while
    they are made) it is refused in one line before a texture is read, and
    nothing is written. Before the payloads were made a band of rows at a
    time, the 2048² export peaked at 21.6 GB."""
    bpy = addon_bpy()
    rs.floor_and_box(bpy)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    for res in ("512", "1024"):
        r = run_limited("bake", "scene.blend", "--unwrap", "smart", "--tuning", "fixed", "--resolution", res,
                        "--rays", "8", "--bounce-rays", "4", "--out", f"tex{res}", "--save-as", f"s{res}.blend",
                        cwd=tmp_path)
        assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
    limit = 3 << 30
    small = run_limited("export", "s512.blend", "--out", "s512.glb", cwd=tmp_path, limit=limit)
    assert small.returncode == 0 and (tmp_path / "s512.glb").stat().st_size > 0, small.stderr[-3000:]
    big = run_limited("export", "s1024.blend", "--out", "s1024.glb", cwd=tmp_path, limit=limit)
    assert big.returncode == 1, big.stdout[-2000:] + big.stderr[-3000:]
    assert "exporting texture set" in big.stderr and "needs about" in big.stderr and "--encoding u8" in big.stderr
    assert "Traceback" not in big.stderr and not (tmp_path / "s1024.glb").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".s1024")]      # no temporary left
