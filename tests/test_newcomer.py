"""What a newcomer runs from the docs (issue 37): a baked project folder that
moves, a no-op bake that leaves the .blend alone, the demo's options refused
before any work, and no harmless native noise taken for errors."""
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from tests import real_scenes as rs
from tests.blender_util import addon_bpy
from tests.test_headless_chain import ROOT, digest, run

pytestmark = pytest.mark.blender

BAKE = ["--resolution", "32", "--rays", "16", "--bounces", "1", "--bounce-rays", "4"]
#: Lines users took for errors (issue 37, item 6).
NOISE = ("EGL Error", "not available. Keeping packed image", "does not support blend relative")


@pytest.fixture(scope="module")
def blend(tmp_path_factory):
    """Floor and a cube whose material samples a packed float image (as the
    demo's do), a camera, the built-in light; saved without a PRTT map."""
    from prtt_addon.dev.bench.scene_build import float_image, principled
    tmp = tmp_path_factory.mktemp("newcomer")
    bpy = addon_bpy()
    rs.floor(bpy, 6.0)
    box = rs.add_object(bpy, "Box", rs.cube_mesh(bpy, "box"), location=(0, 0, 0.5))
    box.data.uv_layers.new(name="UVMap")
    checker = np.indices((8, 8)).sum(0) % 2 * 0.6 + 0.2
    img = float_image("checker", np.repeat(checker[..., None], 3, -1).astype(np.float32), non_color=False)
    box.data.materials.append(principled("Checker", base_image=img))
    rs.scene_camera(bpy, (0, -7, 4), (1.05, 0, 0))
    bpy.context.scene.prtt.light_source = "BUILTIN"
    path = tmp / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    return path


def stored_output_dir(path) -> str:
    code = ("import bpy, prtt_addon; prtt_addon.register(); "
            f"bpy.ops.wm.open_mainfile(filepath={str(path)!r}); print('OUT=' + bpy.context.scene.prtt.output_dir)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, PYTHONPATH=ROOT))
    return next(ln[4:] for ln in r.stdout.splitlines() if ln.startswith("OUT="))


def no_noise(r):
    text = r.stdout + r.stderr
    assert not [n for n in NOISE if n in text], text


def test_a_baked_project_folder_moves(blend, tmp_path):
    old = tmp_path / "old" / "project"
    old.mkdir(parents=True)
    shutil.copy(blend, old / "scene.blend")
    r = run("bake", "scene.blend", "--out", "textures", "--unwrap", "SMART", *BAKE, cwd=old)
    assert r.returncode == 0, r.stderr + r.stdout
    no_noise(r)
    assert stored_output_dir(old / "scene.blend") == "//textures/"
    new = tmp_path / "new" / "place"
    new.parent.mkdir()
    shutil.move(old, new)
    assert not (tmp_path / "old" / "project").exists()
    r = run("render", "scene.blend", "--out", "moved.png", "--size", "48x32", cwd=new)
    assert r.returncode == 0, r.stderr + r.stdout
    no_noise(r)
    # a plain bake finds the moved textures, writes nothing and does not save
    textures = {n: digest(new / "textures" / n) for n in os.listdir(new / "textures")}
    blend_bytes, backup = digest(new / "scene.blend"), digest(new / "scene.blend1")
    r = run("bake", "scene.blend", *BAKE, cwd=new)
    assert r.returncode == 0, r.stderr + r.stdout
    assert "nothing to do" in r.stdout and "not saved" in r.stdout, r.stdout
    no_noise(r)
    assert not (tmp_path / "old" / "project").exists()          # the old folder is not made again
    assert {n: digest(new / "textures" / n) for n in os.listdir(new / "textures")} == textures
    assert digest(new / "scene.blend") == blend_bytes and digest(new / "scene.blend1") == backup
    # --save-as elsewhere: the copy points at the same textures, relative to itself
    other = tmp_path / "elsewhere"
    other.mkdir()
    r = run("bake", "scene.blend", *BAKE, "--save-as", str(other / "copy.blend"), cwd=new)
    assert r.returncode == 0, r.stderr + r.stdout
    assert stored_output_dir(other / "copy.blend") == "//../new/place/textures/"
    r = run("render", str(other / "copy.blend"), "--out", str(other / "copy.png"), "--size", "48x32")
    assert r.returncode == 0, r.stderr + r.stdout
    assert digest(other / "copy.png") == digest(new / "moved.png")
    # the old meaning, one flag away
    r = run("bake", "scene.blend", "--out", "textures", "--absolute-out", *BAKE, cwd=new)
    assert r.returncode == 0, r.stderr + r.stdout
    assert stored_output_dir(new / "scene.blend") == str(new / "textures")


@pytest.mark.parametrize("args, message", [
    (["--resolution", "0"], "--resolution 0 is out of range: it must be 16..16384"),
    (["--rays", "0"], "--rays 0 is out of range: it must be 1..65536"),
    (["--bounce-rays", "many"], "--bounce-rays many is not an integer"),
    (["--size", "320"], "size must look like 1920x1080, got '320'"),
    (["--size", "0x10"], "width and height must be at least 1, got '0x10'"),
])
def test_demo_refuses_bad_options_before_any_work(tmp_path, args, message):
    out = tmp_path / "demo"
    r = subprocess.run([sys.executable, "-m", "prtt_addon.dev.demo", "--out", str(out), *args],
                       capture_output=True, text=True, timeout=120, env=dict(os.environ, PYTHONPATH=ROOT))
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert not out.exists()


def test_every_way_of_saving_elsewhere_keeps_the_bake(blend, tmp_path):
    """Found by review: after Blender's own Save As to another folder, after
    `--absolute-out --save-as` without --out, and with an empty Output Folder
    and --save-as, the copy still renders its bake."""
    proj = tmp_path / "proj"
    proj.mkdir()
    shutil.copy(blend, proj / "scene.blend")
    r = run("bake", "scene.blend", "--out", "textures", "--unwrap", "SMART", *BAKE, cwd=proj)
    assert r.returncode == 0, r.stderr + r.stdout
    other = tmp_path / "other"
    other.mkdir()
    # Blender's own Save As (not PRTT's --save-as): the record's absolute folder finds the textures
    code = ("import bpy, prtt_addon; prtt_addon.register(); "
            f"bpy.ops.wm.open_mainfile(filepath={str(proj / 'scene.blend')!r}); "
            f"bpy.ops.wm.save_as_mainfile(filepath={str(other / 'blender_save_as.blend')!r})")
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, timeout=120,
                   env=dict(os.environ, PYTHONPATH=ROOT))
    # --absolute-out without --out, then --save-as
    r = run("bake", "scene.blend", "--absolute-out", "--save-as", str(other / "absolute.blend"), *BAKE, cwd=proj)
    assert r.returncode == 0, r.stderr + r.stdout
    assert stored_output_dir(other / "absolute.blend") == str(proj / "textures")
    # an empty Output Folder (//prtt/ by default), then --save-as
    code = ("import bpy, prtt_addon; prtt_addon.register(); "
            f"bpy.ops.wm.open_mainfile(filepath={str(proj / 'scene.blend')!r}); "
            "bpy.context.scene.prtt.output_dir = ''; "
            f"bpy.ops.wm.save_as_mainfile(filepath={str(proj / 'empty.blend')!r})")
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, timeout=120,
                   env=dict(os.environ, PYTHONPATH=ROOT))
    r = run("bake", "empty.blend", "--save-as", str(other / "empty_copy.blend"), *BAKE, cwd=proj)
    assert r.returncode == 0, r.stderr + r.stdout
    assert stored_output_dir(other / "empty_copy.blend") == "//../proj/prtt/"
    for name in ("blender_save_as", "absolute", "empty_copy"):
        r = run("render", f"{name}.blend", "--out", f"{name}.png", "--size", "48x32", cwd=other)
        assert r.returncode == 0, (name, r.stderr + r.stdout)


def test_a_job_file_from_a_blend_bakes_on_a_farm_as_the_blend_does(blend, tmp_path):
    """`bake --job-only` writes the job a farm bakes (issue 50: no command
    wrote one from a .blend); `bake-job` on it writes the textures `bake` of
    the .blend writes, byte for byte."""
    work = tmp_path / "p"
    shutil.copytree(blend.parent, work)
    r = run("bake", "scene.blend", "--unwrap", "SMART", "--job-only", "level.npz", *BAKE, cwd=work)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "wrote" in r.stdout and "bake-job level.npz --out DIR" in r.stdout and (work / "level.npz").is_file()
    r = run("bake-job", "level.npz", "--out", "farm", cwd=work)
    assert r.returncode == 0, r.stdout + r.stderr
    r = run("bake", "scene.blend", "--out", "local", *BAKE, cwd=work)       # its saved UVs: the job's
    assert r.returncode == 0, r.stdout + r.stderr
    exrs = sorted(n for n in os.listdir(work / "local") if n.endswith(".exr"))
    assert exrs and exrs == sorted(n for n in os.listdir(work / "farm") if n.endswith(".exr"))
    for n in exrs:
        assert digest(work / "local" / n) == digest(work / "farm" / n), n
    r = run("bake", "scene.blend", "--job-only", "missing/level.npz", cwd=work)
    assert r.returncode == 1 and "the folder missing does not exist" in r.stderr, r.stderr
