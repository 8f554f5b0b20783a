"""The chain a headless user runs (issue 13): bake -> render -> bake again ->
render, each a separate `python -m prtt_addon` process on a .blend with
instances, geometry-nodes faces and meshes that need unwrapping."""
import hashlib
import os
import subprocess
import sys

import pytest

from tests import real_scenes as rs
from tests.blender_util import addon_bpy

pytestmark = pytest.mark.blender
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def run(*args, cwd=None, timeout=300):
    env = dict(os.environ, PYTHONPATH=ROOT)
    return subprocess.run([sys.executable, "-m", "prtt_addon", *args], capture_output=True, text=True,
                          env=env, cwd=cwd, timeout=timeout)


def digest(path):
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


@pytest.fixture(scope="module")
def blend(tmp_path_factory):
    """A saved .blend: floor and cube without PRTT maps, cube instances from an
    excluded collection, a geometry-nodes grid, a camera."""
    tmp = tmp_path_factory.mktemp("chain")
    bpy = addon_bpy()
    rs.chain_scene(bpy)
    path = tmp / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    return path


BAKE = ["--resolution", "32", "--rays", "16", "--bounces", "0"]


@pytest.mark.parametrize("bounces", [(), ("--bounces", "1", "--bounce-rays", "8", "--bounce-mode", "baked"),
                                     ("--bounces", "1", "--bounce-rays", "8", "--dask", "local:2")],
                         ids=["direct", "baked-bounce", "relightable-bounce-on-a-dask-cluster"])
def test_bake_render_bake_render(blend, tmp_path, bounces):
    bake = BAKE + list(bounces)
    work = tmp_path / "work"
    work.mkdir()
    scene = work / "scene.blend"
    scene.write_bytes(blend.read_bytes())
    # relative paths resolve against the caller's folder
    r = run("bake", "scene.blend", "--out", "textures", "--unwrap", "SMART", *bake, cwd=work)
    assert r.returncode == 0, r.stderr + r.stdout
    assert "saved" in r.stdout and (work / "textures" / "manifest.json").is_file()
    assert "nothing to bake (no faces): Edges" in r.stdout + r.stderr
    assert not [n for n in os.listdir(work / "textures") if n.startswith(".prtt-tmp-")]
    r = run("render", "scene.blend", "--out", "first.png", "--size", "64x48", cwd=work)
    assert r.returncode == 0, r.stderr + r.stdout
    assert (work / "first.png").is_file()
    textures = {n: digest(work / "textures" / n) for n in os.listdir(work / "textures")}
    # the second bake finds the saved UV maps and bake record: nothing to do
    if bounces:
        kind = ".bounce1.exr" if "baked" in bounces else ".relight.exr"     # relightable: the default
        assert any(n.endswith(kind) for n in textures), sorted(textures)
    r = run("bake", "scene.blend", "--out", "textures", *bake, cwd=work)
    assert r.returncode == 0, r.stderr + r.stdout
    assert "unchanged" in r.stdout or "up to date" in r.stdout, r.stdout
    assert {n: digest(work / "textures" / n) for n in os.listdir(work / "textures")} == textures
    r = run("render", "scene.blend", "--out", "second.png", "--size", "64x48", cwd=work)
    assert r.returncode == 0, r.stderr + r.stdout
    assert digest(work / "first.png") == digest(work / "second.png")


def test_no_save_save_as_and_range_errors(blend, tmp_path):
    scene = tmp_path / "scene.blend"
    scene.write_bytes(blend.read_bytes())
    before = digest(scene)
    r = run("bake", str(scene), "--bands", "100", *BAKE)
    assert r.returncode == 2 and "--bands 100 is out of range: it must be 1..16" in r.stderr, r.stderr
    r = run("bake", str(scene), "--out", str(tmp_path / "t1"), "--unwrap", "XATLAS", "--no-save", *BAKE)
    assert r.returncode == 0, r.stderr + r.stdout
    assert digest(scene) == before                      # --no-save: the user's file untouched
    other = tmp_path / "baked.blend"
    r = run("bake", str(scene), "--out", str(tmp_path / "t2"), "--unwrap", "XATLAS", "--save-as", str(other), *BAKE)
    assert r.returncode == 0, r.stderr + r.stdout
    assert digest(scene) == before and other.is_file()
    r = run("render", str(other), "--out", str(tmp_path / "o.png"), "--size", "32x24")
    assert r.returncode == 0, r.stderr + r.stdout
    # the original was never baked (its record was not saved)
    r = run("render", str(scene), "--out", str(tmp_path / "n.png"), "--size", "32x24")
    assert r.returncode != 0 and "nothing baked" in (r.stderr + r.stdout)
    assert not (tmp_path / "n.png").exists()


def test_two_bakes_into_one_folder_never_mix(tmp_path):
    """A long bake of scene A holds the folder; a bake of scene B into the same
    --out meanwhile is refused with a message naming A's bake; the folder
    ends with A's textures only."""
    bpy = addon_bpy()
    for name, obj in (("a", "BoxA"), ("b", "BoxB")):
        bpy.ops.wm.read_factory_settings(use_empty=True)
        rs.floor(bpy, 4.0).data.uv_layers.new(name="PRTT")
        rs.add_object(bpy, obj, rs.cube_mesh(bpy, obj), location=(0, 0, 0.5)).data.uv_layers.new(name="PRTT")
        bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / f"{name}.blend"))
    out = tmp_path / "shared"
    env = dict(os.environ, PYTHONPATH=ROOT)
    slow = subprocess.Popen([sys.executable, "-m", "prtt_addon", "bake", str(tmp_path / "a.blend"), "--out",
                             str(out), "--resolution", "256", "--rays", "4096", "--bounces", "0", "--no-save"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        for line in slow.stdout:                 # wait until A's worker is tracing (it holds the lock)
            if line.startswith("prtt: trace"):
                break
        r = run("bake", str(tmp_path / "b.blend"), "--out", str(out), *BAKE, "--no-save")
        assert r.returncode == 1, r.stdout + r.stderr
        assert "in use by another bake" in r.stderr and "a.blend" in r.stderr, r.stderr
    finally:
        slow.terminate()                         # SIGTERM: the command cancels its worker
        code = slow.wait(timeout=30)
    assert code == 3
    names = os.listdir(out)
    assert not any("BoxB" in n or n.startswith(".prtt-tmp-") for n in names), names
