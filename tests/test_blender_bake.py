"""Bake control in real Blender: cancel, kill, bad input, headless entry points."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from tests.blender_util import addon_bpy, select_only, uv_snapshot
from tests.test_blender_addon import plane_and_monkey

pytestmark = pytest.mark.blender
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def ready_scene(bpy, tmp_path, res=32, rays=32):
    plane, monkey = plane_and_monkey(bpy, tmp_path, res, rays)
    select_only(bpy, [plane, monkey])
    bpy.ops.prtt.unwrap()
    return plane, monkey


def snapshot_files(folder):
    return {n: open(os.path.join(folder, n), "rb").read() for n in sorted(os.listdir(folder))
            if not n.startswith((".prtt-tmp-", ".prtt-lock"))}


@pytest.mark.parametrize("how", ["cancel", "kill"])
def test_cancel_or_kill_mid_bake_keeps_everything(tmp_path, how):
    bpy = addon_bpy()
    ready_scene(bpy, tmp_path)
    assert bpy.ops.prtt.bake_transfer() == {"FINISHED"}
    out = str(tmp_path / "out")
    before_files = snapshot_files(out)
    before_uv = uv_snapshot(bpy)
    st = bpy.context.scene.prtt
    before_meta = st.last_bake
    st.resolution, st.rays = 256, 4096                    # long enough to interrupt
    from prtt_addon.blender.bake import run as bake_run
    from prtt_addon.blender.bake.worker_job import WorkerJob
    prepared = bake_run.prepare(bpy.context)
    job = WorkerJob(prepared.job, prepared.out_dir).start()
    while True:
        evs = job.events(timeout=30)
        assert evs, "the worker said nothing for 30 s"
        if any(e and e.get("stage") == "trace" for e in evs) or None in evs:
            break
    job.cancel() if how == "cancel" else job.kill()
    code = job.wait(timeout=60)
    outcome = bake_run.interpret(job, code)
    bake_run.finish(bpy.context, prepared, outcome)
    if how == "cancel":
        assert code == 3 and outcome.status == "cancelled"
        assert "previous textures are unchanged" in outcome.message
    else:
        assert outcome.status == "failed" and "was killed (signal 9)" in outcome.message
    assert snapshot_files(out) == before_files
    assert st.last_bake == before_meta and not st.baking
    after_uv = uv_snapshot(bpy)
    for name, (maps, _sel) in before_uv.items():
        for m, (data, *_flags) in maps.items():
            np.testing.assert_array_equal(after_uv[name][0][m][0], data)


def test_bad_input_gets_clear_reports(tmp_path):
    bpy = addon_bpy()
    st = bpy.context.scene.prtt
    st.output_dir, st.resolution, st.rays, st.bounces = str(tmp_path / "out"), 16, 16, 0
    from prtt_addon.blender.bake.run import bake_blocking
    # nothing to bake at all
    out = bake_blocking(bpy.context)
    assert out.status == "failed" and "no object to bake" in out.message
    # a mesh without faces, a camera, a light, an empty, a curve: no crash, clear words
    me = bpy.data.meshes.new("points")
    me.from_pydata([(0, 0, 0), (1, 0, 0)], [], [])
    pts = bpy.data.objects.new("Points", me)
    bpy.context.scene.collection.objects.link(pts)
    bpy.ops.object.camera_add()
    bpy.ops.object.light_add(type="SUN")
    bpy.ops.object.empty_add()
    bpy.ops.curve.primitive_bezier_circle_add()
    out = bake_blocking(bpy.context)
    assert out.status == "failed" and "no object to bake" in out.message
    # a mesh without the PRTT map
    bpy.ops.mesh.primitive_cube_add()
    cube = bpy.context.active_object
    out = bake_blocking(bpy.context)
    assert out.status == "failed" and "have no 'PRTT' UV map: Cube" in out.message
    # Unwrap "Existing" on a mesh without UVs
    cube.data.uv_layers.remove(cube.data.uv_layers[0])
    select_only(bpy, [cube])
    st.unwrap_method = "EXISTING"
    with pytest.raises(RuntimeError, match="has no UV map .* to copy"):
        bpy.ops.prtt.unwrap()
    assert "PRTT" not in cube.data.uv_layers
    st.unwrap_method = "SMART"
    bpy.ops.prtt.unwrap()
    # unsaved .blend with a relative output folder
    st.output_dir = "//prtt/"
    out = bake_blocking(bpy.context)
    assert out.status == "failed" and "not saved" in out.message
    # an output folder that cannot exist (below a file)
    (tmp_path / "file").write_text("x")
    st.output_dir = str(tmp_path / "file" / "sub")
    out = bake_blocking(bpy.context)
    assert out.status == "failed" and "output folder" in out.message
    # and with everything right it bakes, mentioning the face-less object
    st.output_dir = str(tmp_path / "out")
    out = bake_blocking(bpy.context)
    assert out.status == "done", out.message
    info = json.loads(st.last_bake)
    skipped = [w for w in info["warnings"] if "nothing to bake" in w]
    assert len(skipped) == 1 and all(n in skipped[0] for n in ("Points", "Empty", "BézierCircle")), skipped


def test_three_headless_entry_points_agree(tmp_path):
    """The operator in background mode (blender -b --python-expr), the CLI
    command's handler (blender -c prtt bake) and python -m prtt_addon bake
    give the same textures."""
    bpy = addon_bpy()
    ready_scene(bpy, tmp_path)
    st = bpy.context.scene.prtt
    st.output_dir = "//prtt_out/"
    blend = str(tmp_path / "scene.blend")
    bpy.ops.wm.save_as_mainfile(filepath=blend)
    env = dict(os.environ, PYTHONPATH=ROOT)
    expr = ("import bpy, prtt_addon; prtt_addon.register(); "
            f"bpy.ops.wm.open_mainfile(filepath={blend!r}); "
            "r = bpy.ops.prtt.bake_transfer(); print('RESULT', r)")
    r1 = subprocess.run([sys.executable, "-c", expr], capture_output=True, text=True, env=env, timeout=300)
    assert "RESULT {'FINISHED'}" in r1.stdout, r1.stdout + r1.stderr
    a = snapshot_files(tmp_path / "prtt_out")
    r2 = subprocess.run([sys.executable, "-c",
                         "import sys, bpy, prtt_addon; prtt_addon.register(); "
                         "from prtt_addon.blender.commands import _cli; "
                         f"sys.exit(_cli(['bake', {blend!r}, '--out', {str(tmp_path / 'cli')!r}]))"],
                        capture_output=True, text=True, env=env, timeout=300)
    assert r2.returncode == 0, r2.stdout + r2.stderr
    r3 = subprocess.run([sys.executable, "-m", "prtt_addon", "bake", blend, "--out", str(tmp_path / "pym")],
                        capture_output=True, text=True, env=env, timeout=300)
    assert r3.returncode == 0, r3.stdout + r3.stderr
    for other in ("cli", "pym"):
        b = snapshot_files(tmp_path / other)
        for f in ("Plane.transfer.exr", "Suzanne.transfer.exr"):
            from prtt_addon.core.io.exr_io import read_sh_exr
            np.testing.assert_array_equal(read_sh_exr(tmp_path / "prtt_out" / f)[0],
                                          read_sh_exr(tmp_path / other / f)[0])
        assert set(b) == set(a)
    bad = subprocess.run([sys.executable, "-m", "prtt_addon", "bake", str(tmp_path / "missing.blend")],
                         capture_output=True, text=True, env=env, timeout=120)
    assert bad.returncode == 1 and "cannot open" in bad.stderr


def test_dask_scheduler_from_the_panel_and_the_cli(tmp_path):
    """The panel's Dask Scheduler (saved with the scene) and ``bake --dask``
    (this bake only) run the worker on a local cluster: the textures are the
    local bake's, byte for byte; a bad value fails the bake with its reason."""
    pytest.importorskip("distributed")
    bpy = addon_bpy()
    ready_scene(bpy, tmp_path)
    st = bpy.context.scene.prtt
    st.output_dir = str(tmp_path / "local")
    assert bpy.ops.prtt.bake_transfer() == {"FINISHED"}
    local = snapshot_files(tmp_path / "local")
    st.output_dir, st.dask_scheduler = str(tmp_path / "panel"), "local:2"
    assert bpy.ops.prtt.bake_transfer() == {"FINISHED"}
    panel = snapshot_files(tmp_path / "panel")
    exrs = [n for n in local if n.endswith(".exr")]
    assert len(exrs) >= 2 and all(panel[n] == local[n] for n in exrs)
    st.dask_scheduler = ""
    blend = str(tmp_path / "scene.blend")
    bpy.ops.wm.save_as_mainfile(filepath=blend)
    env = dict(os.environ, PYTHONPATH=ROOT)
    r = subprocess.run([sys.executable, "-m", "prtt_addon", "bake", blend, "--out", str(tmp_path / "cli"),
                        "--dask", "local:2", "--no-save", "-q"], capture_output=True, text=True, env=env,
                       timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    cli = snapshot_files(tmp_path / "cli")
    assert all(cli[n] == local[n] for n in exrs)
    st.output_dir, st.dask_scheduler = str(tmp_path / "bad"), "farm:8786"
    with pytest.raises(RuntimeError, match="tcp://HOST:PORT, got 'farm:8786'"):
        bpy.ops.prtt.bake_transfer()          # the operator's error report (background mode raises it)
    assert not (tmp_path / "bad" / "manifest.json").exists()
