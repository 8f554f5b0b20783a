"""Offscreen preview renders from the command lines and the operator."""
import os
import subprocess
import sys

import numpy as np
import pytest

from tests.preview_util import baked_blend, open_blend

pytestmark = pytest.mark.blender
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = dict(os.environ, PYTHONPATH=ROOT)


@pytest.fixture(scope="module")
def blend(tmp_path_factory):
    return baked_blend(str(tmp_path_factory.mktemp("preview_cli")))


def run(args, timeout=300):
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=ENV, timeout=timeout)


def test_python_m_render_matches_in_process(blend, tmp_path):
    from prtt_addon.blender.preview.offscreen import render_scene
    from prtt_addon.core.io.image_write import read_exr_rgba
    out = str(tmp_path / "tpfl.exr")
    r = run(["-m", "prtt_addon", "render", blend, "--out", out, "--mode", "tpfl", "--size", "64x48"])
    assert r.returncode == 0, r.stdout + r.stderr
    assert "rendered tpfl 64x48, 3 object(s)" in r.stdout
    got = read_exr_rgba(out)
    bpy = open_blend(blend)
    want, stats, status, _ = render_scene(bpy.context, mode="tpfl", size=(64, 48))
    assert got.shape == (48, 64, 4)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6 * want.max())


def test_blender_c_prtt_render_writes_png(blend, tmp_path):
    out = str(tmp_path / "vertex.png")
    code = ("import sys, bpy, prtt_addon; prtt_addon.register(); "
            "from prtt_addon.blender.commands import _cli; "
            f"sys.exit(_cli(['render', {blend!r}, '--out', {out!r}, '--mode', 'vertex-tpfl', '--size', '40x30']))")
    r = run(["-c", code])
    assert r.returncode == 0, r.stdout + r.stderr
    import matplotlib.image as mpimg
    img = mpimg.imread(out)
    assert img.shape == (30, 40, 4) and img[..., 3].max() == 1.0 and img[..., 3].min() == 0.0


def test_render_errors_are_clear(blend, tmp_path):
    r = run(["-m", "prtt_addon", "render", blend, "--out", str(tmp_path / "x.jpg")])
    assert r.returncode == 1 and "must end in .png or .exr" in r.stderr
    r = run(["-m", "prtt_addon", "render", blend, "--out", str(tmp_path / "x.png"), "--mode", "phong"])
    assert r.returncode == 2 and "invalid choice" in r.stderr
    r = run(["-m", "prtt_addon", "render", blend, "--out", str(tmp_path / "x.png"), "--camera", "Nope"])
    assert r.returncode == 1 and "no camera 'Nope'" in r.stderr
    bpy = open_blend(blend)
    bpy.context.scene.prtt.last_bake = ""
    fresh = str(tmp_path / "unbaked.blend")
    bpy.ops.wm.save_as_mainfile(filepath=fresh)
    r = run(["-m", "prtt_addon", "render", fresh, "--out", str(tmp_path / "x.png")])
    assert r.returncode == 1 and "nothing baked yet" in r.stderr
    assert not os.path.exists(tmp_path / "x.png")


def test_render_preview_operator(blend):
    bpy = open_blend(blend)
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 80, 60, 50
    scene.prtt.preview_mode = "DIFFUSE"
    assert bpy.ops.prtt.render_preview() == {"FINISHED"}
    img = bpy.data.images["PRTT Preview"]
    assert tuple(img.size) == (40, 30)
    px = np.empty(40 * 30 * 4, np.float32)
    img.pixels.foreach_get(px)
    assert np.isfinite(px).all() and px.reshape(30, 40, 4)[..., 3].max() == 1.0


def test_relightable_chain_bake_render_turn_the_world_render_bake(blend, tmp_path):
    """The chain a user runs headless: bake relightable bounces, render, brighten
    and turn the World, render again (the bounce light follows, no stale
    warning, no rebake), bake again (nothing to do)."""
    import shutil

    from prtt_addon.core.io.image_write import read_exr_rgba
    scene = str(tmp_path / "scene.blend")
    shutil.copy(blend, scene)
    out_dir = str(tmp_path / "out")
    r = run(["-m", "prtt_addon", "bake", scene, "--out", out_dir, "--bounce-mode", "relightable"])
    assert r.returncode == 0, r.stdout + r.stderr
    relit = [f for f in os.listdir(out_dir) if f.endswith(".relight.exr")]
    assert len(relit) == 3 and not any(".bounce" in f for f in os.listdir(out_dir))
    stamp = {f: os.stat(os.path.join(out_dir, f)).st_mtime_ns for f in relit}
    def render(name, *extra):
        path = str(tmp_path / f"{name}.exr")
        r = run(["-m", "prtt_addon", "render", scene, "--out", path, "--size", "64x48", *extra])
        assert r.returncode == 0 and "stale" not in (r.stdout + r.stderr), r.stdout + r.stderr
        return read_exr_rgba(path)[..., :3]

    bounce_a = render("a") - render("a-direct", "--no-bounces")
    assert bounce_a.max() > 0.01 * render("a").max()             # the relit bounce light is drawn
    images = [render("a")]
    for change in ("brighter", "turned"):
        bpy = open_blend(scene)
        world = bpy.context.scene.world.node_tree.nodes
        if change == "brighter":
            world["Background"].inputs["Strength"].default_value *= 2.0
        else:
            next(n for n in world if n.bl_idname == "ShaderNodeMapping").inputs["Rotation"].default_value[2] += 1.2
        bpy.ops.wm.save_as_mainfile(filepath=scene)
        images.append(render(change))
        if change == "brighter":
            # The bounce light doubles with the World, with no rebake.
            bounce_b = images[-1] - render("brighter-direct", "--no-bounces")
            np.testing.assert_allclose(bounce_b, 2.0 * bounce_a, rtol=0, atol=2e-3 * bounce_a.max())
    a, brighter, turned = images
    np.testing.assert_allclose(brighter, 2.0 * a, rtol=0, atol=2e-3 * a.max())
    assert np.abs(turned - brighter).max() > 0.05 * brighter.max()
    r = run(["-m", "prtt_addon", "bake", scene, "--out", out_dir, "--bounce-mode", "relightable"])
    assert r.returncode == 0, r.stdout + r.stderr
    assert {f: os.stat(os.path.join(out_dir, f)).st_mtime_ns for f in relit} == stamp
