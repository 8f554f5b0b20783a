"""`render` never lies (issue 13, item 7): every failure exits non-zero, names
what the user gave (the .blend, the texture, the size, the --out path), writes
no image and leaves an existing one alone.

Real Blender and real files: one plane + monkey scene baked once (32 texels,
16 rays, no bounce, *no* per-vertex transfer) shared by the module; the
command runs in a subprocess (``python -m prtt_addon render``) so the exit
codes and stderr are the real ones. Damaged textures are restored after each
test.
"""
import contextlib
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from tests.blender_util import addon_bpy, select_only

pytestmark = pytest.mark.blender
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = dict(os.environ, PYTHONPATH=ROOT)
SIZE = "32x24"


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    """(the .blend path, its bake folder): plane + monkey + camera, baked
    without vertex transfer."""
    d = tmp_path_factory.mktemp("render_errors")
    bpy = addon_bpy()
    bpy.ops.mesh.primitive_plane_add(size=4)
    floor = bpy.context.active_object
    floor.name = "Floor"
    bpy.ops.mesh.primitive_monkey_add(location=(0, 0, 1))
    monkey = bpy.context.active_object
    monkey.name = "Monkey"
    bpy.context.scene.world = bpy.data.worlds.new("W")
    bpy.ops.object.camera_add(location=(0, -6, 3), rotation=(1.2, 0, 0))
    bpy.context.scene.camera = bpy.context.active_object
    st = bpy.context.scene.prtt
    st.resolution, st.rays, st.bounces, st.vertex_transfer = 32, 16, 0, False
    st.output_dir = str(d / "out")
    select_only(bpy, [floor, monkey])
    assert bpy.ops.prtt.unwrap() == {"FINISHED"}
    assert bpy.ops.prtt.bake_transfer() == {"FINISHED"}, st.status
    blend = str(d / "scene.blend")
    bpy.ops.wm.save_as_mainfile(filepath=blend)
    return blend, str(d / "out")


def render(blend, *args, cwd=None, prefix=()):
    """Run ``python -m prtt_addon render BLEND ARGS`` -> CompletedProcess."""
    cmd = [*prefix, sys.executable, "-m", "prtt_addon", "render", blend, *args]
    return subprocess.run(cmd, capture_output=True, text=True, env=ENV, cwd=cwd, timeout=300)


def assert_refused(r, code=1):
    """A clean refusal: the exit code, a one-line-prefixed message, no traceback."""
    assert r.returncode == code, r.stdout + r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    assert "prtt: rendered" not in r.stdout
    if code == 1:
        assert "prtt: error: " in r.stderr, r.stderr


def files_in(folder):
    return sorted(os.listdir(folder))


def test_the_scene_renders(baked, tmp_path):
    blend, _ = baked
    r = render(blend, "--out", "ok.png", "--size", SIZE, cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "rendered tpfl 32x24, 2 object(s)" in r.stdout
    assert files_in(tmp_path) == ["ok.png"]


@pytest.mark.parametrize("mode", ["vertex-tpfl", "vertex-tp"])
def test_vertex_mode_without_vertex_transfer(baked, tmp_path, mode):
    blend, _ = baked
    r = render(blend, "--out", "v.png", "--mode", mode, "--size", SIZE, cwd=tmp_path)
    assert_refused(r)
    assert f"cannot render {mode}: 2 baked object(s) cannot be drawn" in r.stderr
    assert "Floor, Monkey: the bake has no per-vertex transfer" in r.stderr
    assert "Vertex Transfer on" in r.stderr
    assert files_in(tmp_path) == []


def test_vertex_mode_on_a_mesh_edited_since_the_bake(baked, tmp_path):
    from tests.preview_util import open_blend
    bpy = open_blend(baked[0])
    st = bpy.context.scene.prtt
    st.vertex_transfer, st.output_dir = True, str(tmp_path / "out")
    assert bpy.ops.prtt.bake_transfer() == {"FINISHED"}, st.status
    bpy.data.objects["Monkey"].modifiers.new("more", "SUBSURF")
    edited = str(tmp_path / "edited.blend")
    bpy.ops.wm.save_as_mainfile(filepath=edited)
    r = render(edited, "--out", "v.png", "--mode", "vertex-tpfl", "--size", SIZE, cwd=tmp_path)
    assert_refused(r)
    assert "1 baked object(s) cannot be drawn:\n  Monkey: its per-vertex transfer does not match its mesh" in r.stderr
    assert "v.png" not in files_in(tmp_path)


@contextlib.contextmanager
def damaged(path, how):
    """``path`` truncated, replaced by a 3-band texture, or removed; restored after."""
    keep = path + ".keep"
    shutil.copy2(path, keep)
    try:
        if how == "truncated":
            with open(keep, "rb") as f:
                data = f.read()
            with open(path, "wb") as f:
                f.write(data[: len(data) // 2])
        elif how == "bands":
            from prtt_addon.core.io.exr_io import write_sh_exr
            write_sh_exr(path, np.zeros((32, 32, 9), np.float32), kind="transfer", attrs={"bands": 3})
        else:
            os.remove(path)
        yield
    finally:
        os.replace(keep, path)


@pytest.mark.parametrize("how,says", [
    ("truncated", "unreadable EXR"),
    ("bands", "holds 9 SH coefficients"),
    ("missing", "is missing; bake again"),
])
def test_damaged_texture(baked, tmp_path, how, says):
    blend, out_dir = baked
    exr = os.path.join(out_dir, "Monkey.transfer.exr")
    with damaged(exr, how):
        r = render(blend, "--out", "t.exr", "--size", SIZE, cwd=tmp_path)
    assert_refused(r)
    assert exr in r.stderr and says in r.stderr, r.stderr
    assert "bake again" in r.stderr
    assert files_in(tmp_path) == []


@pytest.mark.parametrize("size,says", [
    ("100000x10", "larger than this GPU's largest image"),
    # Within the GL limit (16384 on llvmpipe): refused by the memory estimate
    # or, with more memory, by the driver's allocation of the frame.
    ("16384x16384", ""),
])
def test_size_beyond_the_limits(baked, tmp_path, size, says):
    blend, _ = baked
    r = render(blend, "--out", "big.png", "--size", size, cwd=tmp_path)
    assert_refused(r)
    assert f"prtt: error: --size {size}: " in r.stderr and says in r.stderr, r.stderr
    assert "render smaller" in r.stderr
    assert files_in(tmp_path) == []


@pytest.mark.parametrize("size", ["0x10", "640"])
def test_bad_size_is_a_usage_error(baked, tmp_path, size):
    r = render(baked[0], "--out", "x.png", "--size", size, cwd=tmp_path)
    assert_refused(r, code=2)
    assert r.stderr.startswith("usage:") and "argument --size" in r.stderr


def _unprivileged():
    """A command prefix under which permission bits apply (root ignores them):
    setpriv without the capabilities that override them; skips if unavailable."""
    if os.geteuid() != 0:
        return ()
    setpriv = shutil.which("setpriv")
    prefix = (setpriv, "--bounding-set=-dac_override,-dac_read_search", "--") if setpriv else None
    if prefix is None or subprocess.run([*prefix, "true"]).returncode != 0:
        pytest.skip("running as root without setpriv: a read-only folder is writable")
    return prefix


@pytest.mark.parametrize("case", ["missing folder", "file as folder", "folder named x.png", "read-only folder"])
def test_out_that_cannot_be_written(baked, tmp_path, case):
    blend, _ = baked
    prefix = ()
    if case == "missing folder":
        out, says = os.path.join("missing", "x.png"), "the folder missing does not exist"
    elif case == "file as folder":
        (tmp_path / "plain").write_text("")
        out, says = os.path.join("plain", "x.png"), "the folder plain is a file, not a folder"
    elif case == "folder named x.png":
        (tmp_path / "x.png").mkdir()
        out, says = "x.png", "is a folder"
    else:
        (tmp_path / "ro").mkdir()
        prefix = _unprivileged()
        out, says = os.path.join("ro", "x.png"), "cannot write in the folder ro: Permission denied"
    before = files_in(tmp_path)
    try:
        if case == "read-only folder":
            os.chmod(tmp_path / "ro", 0o555)
        r = render(blend, "--out", out, "--size", SIZE, cwd=tmp_path, prefix=prefix)
    finally:
        if case == "read-only folder":
            os.chmod(tmp_path / "ro", 0o755)
    assert_refused(r)
    assert f"prtt: error: --out {out}: {says}" in r.stderr, r.stderr
    assert ".prtt-tmp" not in r.stderr
    assert files_in(tmp_path) == before
    for sub in ("ro", "x.png"):
        if (tmp_path / sub).is_dir():
            assert files_in(tmp_path / sub) == []


@pytest.mark.parametrize("why", ["vertex mode", "size"])
def test_existing_image_is_left_alone(baked, tmp_path, why):
    blend, _ = baked
    r = render(blend, "--out", "keep.png", "--size", SIZE, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    old = (tmp_path / "keep.png").read_bytes()
    args = ["--mode", "vertex-tpfl", "--size", SIZE] if why == "vertex mode" else ["--size", "100000x10"]
    r = render(blend, "--out", "keep.png", *args, cwd=tmp_path)
    assert_refused(r)
    assert (tmp_path / "keep.png").read_bytes() == old
    assert files_in(tmp_path) == ["keep.png"]


def test_unreadable_blend_is_named(tmp_path):
    (tmp_path / "junk.blend").write_bytes(b"not a blend file")
    r = render("junk.blend", "--out", "x.png", cwd=tmp_path)
    assert_refused(r)
    assert "junk.blend" in r.stderr
    assert files_in(tmp_path) == ["junk.blend"]


def test_write_error_names_the_given_path(tmp_path):
    from prtt_addon.core.io.image_write import ImageWriteError, write_image
    path = str(tmp_path / "gone" / "x.exr")
    with pytest.raises(ImageWriteError) as e:
        write_image(path, np.zeros((2, 3, 4), np.float32))
    assert str(e.value).startswith(f"cannot write {path}: ") and ".prtt-tmp" not in str(e.value)


def test_help(baked, tmp_path, capsys):
    from prtt_addon.blender.preview.offscreen import render_file
    with pytest.raises(SystemExit) as e:          # blender -c prtt render -h lands here
        render_file(["-h"], prog="blender -c prtt render")
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: blender -c prtt render") and "--mode" in out and "Exit status" in out
    r = render(baked[0], "-h", cwd=tmp_path)
    assert r.returncode == 0 and "Exit status" in r.stdout, r.stderr


def test_python_m_render_dash_h(tmp_path):
    r = subprocess.run([sys.executable, "-m", "prtt_addon", "render", "-h"], capture_output=True, text=True,
                       env=ENV, cwd=tmp_path, timeout=300)
    assert r.returncode == 0 and "--mode" in r.stdout, r.stderr
    r = subprocess.run([sys.executable, "-m", "prtt_addon", "bake", "-h"], capture_output=True, text=True,
                       env=ENV, cwd=tmp_path, timeout=300)
    assert r.returncode == 0 and "--no-save" in r.stdout, r.stderr
