"""The scene's colour management (AgX, Filmic, ... with exposure, gamma and
look) in the preview, `render` and the page, against Blender's own colour
management of the same linear colours (Image.save_render, 16-bit PNG)."""
import os
import subprocess
import sys

import numpy as np
import pytest

from prtt_addon.core.io.image_write import read_exr_rgba, srgb_encode
from prtt_addon.core.shading import display as core_display
from tests.blender_util import addon_bpy
from tests.preview_util import baked_blend, open_blend

pytestmark = pytest.mark.blender

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def blender_view(bpy, colours, *, view, look="None", display="sRGB", exposure=0.0, gamma=1.0):
    """Blender's display code values (n, 3) of scene-linear ``colours`` (n, 3),
    through a scene with these settings (save_render to a 16-bit PNG)."""
    n = colours.shape[0]
    w = 512
    h = -(-n // w)
    px = np.zeros((h * w, 4), np.float32)
    px[:n, :3] = colours
    px[:, 3] = 1.0
    img = bpy.data.images.new("colours", w, h, float_buffer=True, alpha=True)
    img.colorspace_settings.name = "Linear Rec.709"
    img.pixels.foreach_set(px.ravel())
    sc = bpy.data.scenes.new("look")
    sc.display_settings.display_device = display
    sc.view_settings.view_transform = view
    sc.view_settings.look = look
    sc.view_settings.exposure, sc.view_settings.gamma = exposure, gamma
    sc.render.dither_intensity = 0.0
    s = sc.render.image_settings
    s.file_format, s.color_mode, s.color_depth = "PNG", "RGB", "16"
    path = os.path.join(bpy.app.tempdir or "/tmp", f"prtt-view-{os.getpid()}.png")
    img.save_render(path, scene=sc)
    out = bpy.data.images.load(path)
    out.colorspace_settings.name = "Non-Color"
    a = np.empty(len(out.pixels), np.float32)
    out.pixels.foreach_get(a)
    c = out.channels
    for x in (out, img):
        bpy.data.images.remove(x)
    bpy.data.scenes.remove(sc)
    os.remove(path)
    return a.reshape(-1, c)[:n, :3].astype(np.float64)


def sample_colours(seed=7, n=20000):
    """Log-uniform colours over 16 stops, half of them near grey (what lit
    surfaces are), half saturated."""
    rng = np.random.default_rng(seed)
    grey = np.exp2(rng.uniform(-10, 5, (n // 2, 1))) * rng.uniform(0.7, 1.0, (n // 2, 3))
    vivid = np.exp2(rng.uniform(-10, 6, (n - n // 2, 3))) * rng.uniform(0.0, 1.0, (n - n // 2, 1))
    return np.concatenate([grey, vivid])


# (settings, mean and p99 bounds in 8-bit code values): measured mean / p99 at
# N = 65 were AgX 0.11 / 1.3, Filmic 0.07 / 0.8, PBR Neutral 0.19 / 2.0.
CASES = [
    (dict(view="AgX"), 0.25, 2.0),
    (dict(view="AgX", look="AgX - Punchy", exposure=1.3, gamma=1.8), 0.25, 2.0),
    (dict(view="Filmic", look="Medium High Contrast", exposure=-0.7), 0.25, 2.0),
    (dict(view="Khronos PBR Neutral"), 0.6, 5.0),
    (dict(view="Standard", look="Medium Contrast"), 0.4, 3.0),
    (dict(view="AgX", display="Display P3"), 0.25, 2.0),
]


@pytest.mark.parametrize("case, mean_bound, p99_bound", CASES, ids=lambda c: str(c))
def test_the_table_draws_blenders_view_transform(case, mean_bound, p99_bound):
    """The sampled table, with exposure before it and gamma after, against
    Blender's colour management of colours that are not lattice points."""
    from prtt_addon.blender.preview import colour_management as display
    bpy = addon_bpy()
    sc = bpy.context.scene
    sc.display_settings.display_device = case.get("display", "sRGB")
    sc.view_settings.view_transform = case["view"]
    sc.view_settings.look = case.get("look", "None")
    sc.view_settings.exposure = case.get("exposure", 0.0)
    sc.view_settings.gamma = case.get("gamma", 1.0)
    table = display.display_of(sc)
    assert table is not None and case["view"] in table.name
    x = sample_colours()
    ours = table.encode(x * 2.0 ** case.get("exposure", 0.0))
    ref = blender_view(bpy, x, **case)
    err = np.abs(ours - ref) * 255
    print(f"{case}: mean {err.mean():.3f}, p99 {np.percentile(err, 99):.3f}, max {err.max():.2f} (/255)")
    assert err.mean() < mean_bound and np.percentile(err, 99) < p99_bound, (err.mean(), np.percentile(err, 99))
    # and the settings matter: the same colours in Standard are far from it
    if case["view"] != "Standard":
        assert np.abs(srgb_encode(x) - ref).mean() * 255 > 5.0


def test_plain_standard_needs_no_table():
    """Standard, no look, gamma 1 on sRGB: the exact encode, as before tables."""
    from prtt_addon.blender.preview import colour_management as display
    bpy = addon_bpy()
    sc = bpy.context.scene
    sc.view_settings.view_transform = "Standard"
    sc.view_settings.look = "None"
    assert display.display_of(sc) is None
    x = sample_colours(n=2000)
    ref = blender_view(bpy, np.minimum(x, 1.0), view="Standard")
    assert np.abs(srgb_encode(x) - ref).max() * 255 < 0.05
    sc.view_settings.gamma = 1.2
    assert display.display_of(sc) is not None


def test_the_glsl_twin_draws_the_table(tmp_path):
    """The viewport's display variant (prtt_display.glsl, a 3D texture) on
    the GPU gives the table's numpy encode of the same frame drawn linear."""
    from prtt_addon.blender.preview import colour_management as display
    from prtt_addon.blender.preview import drawlist, offscreen
    from prtt_addon.blender.preview import renderer as gpu_preview
    bpy = open_blend(baked_blend(str(tmp_path)))
    sc = bpy.context.scene
    sc.view_settings.view_transform = "AgX"
    sc.view_settings.look = "AgX - Punchy"
    sc.view_settings.exposure = 0.5
    sc.view_settings.gamma = 1.3
    table = display.display_of(sc)
    offscreen.ensure_gpu()
    ps, _ = drawlist.collect(bpy.context)
    vp, cam = offscreen.camera_view(sc.camera, bpy.context.evaluated_depsgraph_get(), 96, 72, sc)
    r = gpu_preview.Renderer()
    e = offscreen.exposure_of(sc)
    linear, _ = gpu_preview.render_offscreen(r, ps, "tpfl", vp, cam, 96, 72, exposure=e)
    shown, _ = gpu_preview.render_offscreen(r, ps, "tpfl", vp, cam, 96, 72, exposure=e, display=table)
    r.free()
    covered = linear[..., 3] > 0.5
    assert covered.mean() > 0.3
    ours = table.encode(linear[covered][:, :3])
    gpu = srgb_encode(shown[covered][:, :3])          # what the sRGB colour buffer stores
    err = np.abs(ours - gpu) * 255
    assert err.max() < 1.0, err.max()
    assert np.abs(srgb_encode(linear[covered][:, :3]) - gpu).mean() * 255 > 3.0   # AgX, not Standard


def read_png(bpy, path) -> np.ndarray:
    """(H, W, C) float code values in [0, 1] of a PNG, top row first, as stored."""
    img = bpy.data.images.load(str(path), check_existing=False)
    img.colorspace_settings.name = "Non-Color"
    w, h = img.size
    px = np.empty(w * h * img.channels, np.float32)
    img.pixels.foreach_get(px)
    bpy.data.images.remove(img)
    return px.reshape(h, w, -1)[::-1]


def run_render(blend, out, *extra):
    proc = subprocess.run([sys.executable, "-m", "prtt_addon", "render", blend, "--out", out, "--size", "160x120",
                           *extra], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return proc


def test_render_png_is_blenders_colour_management_of_its_exr(tmp_path):
    """`render --out x.png` of an AgX scene (exposure, look) against Blender's
    own save_render of `render --out x.exr` (the same linear image)."""
    bpy = open_blend(baked_blend(str(tmp_path)))
    sc = bpy.context.scene
    sc.view_settings.view_transform = "AgX"
    sc.view_settings.look = "AgX - High Contrast"
    sc.view_settings.exposure = 0.4
    blend = str(tmp_path / "agx.blend")
    bpy.ops.wm.save_as_mainfile(filepath=blend)
    png, exr = str(tmp_path / "agx.png"), str(tmp_path / "agx.exr")
    proc = run_render(blend, png)
    assert "AgX, look AgX - High Contrast" in proc.stdout
    run_render(blend, exr)
    linear = read_exr_rgba(exr)                       # exposure already applied, as Blender writes it
    ref = blender_view(bpy, linear[::-1, :, :3].reshape(-1, 3), view="AgX", look="AgX - High Contrast")
    ours = read_png(bpy, png)[..., :3].reshape(-1, 3).astype(np.float64)
    covered = linear[::-1, :, 3].reshape(-1) > 0.5
    err = np.abs(ours[covered] - ref[covered]) * 255
    assert err.mean() < 0.8 and np.percentile(err, 99) < 3.0, (err.mean(), np.percentile(err, 99))
    std = srgb_encode(linear[::-1, :, :3].reshape(-1, 3)[covered])
    assert np.abs(std - ref[covered]).mean() * 255 > 5.0


def test_lut_bytes_round_trip_and_bad_tables_are_refused():
    lut = np.random.default_rng(1).uniform(0, 1, (9, 9, 9, 3)).astype(np.float32)
    t = core_display.DisplayTransform(lut, gamma=2.0, name="x")
    back = core_display.from_lut_bytes(t.lut_bytes(), 9, gamma=2.0)
    assert np.abs(back.lut - lut).max() <= 0.5 / 65535 + 1e-7
    assert np.array_equal(core_display.from_payload(t.payload(), 9).lut, back.lut)
    with pytest.raises(core_display.DisplayError, match="unpacks to 4374 bytes"):
        core_display.from_payload(t.payload(), 8)                  # beyond an 8^3 table: not unpacked
    with pytest.raises(core_display.DisplayError, match="Zstandard"):
        core_display.from_payload(b"not zstd", 9)
    with pytest.raises(core_display.DisplayError, match="bytes"):
        core_display.from_lut_bytes(t.lut_bytes()[:-2], 9)
    with pytest.raises(core_display.DisplayError, match="size"):
        core_display.from_lut_bytes(b"", 1000)
    with pytest.raises(core_display.DisplayError, match="within"):
        core_display.DisplayTransform(lut * 2)
    with pytest.raises(core_display.DisplayError, match="gamma"):
        core_display.DisplayTransform(lut, gamma=0.0)
