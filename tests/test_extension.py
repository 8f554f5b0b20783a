"""Build the extension zip and install it the way a user does, into a fresh
Blender user folder, then bake with the installed copy."""
import os
import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.blender
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def extension_zip(tmp_path_factory):
    pytest.importorskip("bpy")
    out = tmp_path_factory.mktemp("dist")
    r = subprocess.run([sys.executable, os.path.join(ROOT, "tools", "build_extension.py"), "--out", str(out)],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr
    (path,) = [os.path.join(out, f) for f in os.listdir(out) if f.endswith(".zip")]
    return path


def test_zip_layout(extension_zip):
    import tomllib
    import zipfile
    with zipfile.ZipFile(extension_zip) as z:
        names = set(z.namelist())
        man = tomllib.loads(z.read("blender_manifest.toml").decode())
    assert {"blender_manifest.toml", "__init__.py", "worker.py", "core/sh.py", "blender/operators.py",
            "shader_source.py", "shaders/prtt_common.glsl", "shaders/prtt_surface_frag.glsl"} <= names
    assert not any(n.startswith("bench/") or "__pycache__" in n for n in names)
    assert man["id"] == "prtt_addon" and man["platforms"] == ["linux-x64"]
    wheels = man["wheels"]
    for pkg in ("embreex", "openexr", "xatlas"):
        for tag in ("cp311", "cp313"):
            assert any(os.path.basename(w).lower().startswith(pkg) and f"-{tag}-" in w for w in wheels)
    assert all(w[2:] in names for w in wheels)


def test_install_enable_and_bake(extension_zip, tmp_path):
    script = textwrap.dedent(f"""
        import os, sys
        import bpy
        import importlib.util
        assert importlib.util.find_spec("prtt_addon") is None   # only the installed copy
        bpy.ops.wm.read_factory_settings(use_empty=True)
        r = bpy.ops.extensions.package_install_files(filepath={extension_zip!r}, repo="user_default",
                                                     enable_on_install=True)
        assert r == {{"FINISHED"}}, r
        assert "bl_ext.user_default.prtt_addon" in bpy.context.preferences.addons
        for op in ("unwrap", "bake_transfer", "cancel_bake"):
            assert hasattr(bpy.ops.prtt, op), op
        assert hasattr(bpy.types, "PRTT_PT_main") and hasattr(bpy.types.Scene, "prtt")
        import bl_ext.user_default.prtt_addon as pkg
        assert "user_default" in pkg.__file__
        bpy.ops.mesh.primitive_plane_add(size=4)
        plane = bpy.context.active_object
        bpy.ops.mesh.primitive_monkey_add(location=(0, 0, 1))
        for o in bpy.context.scene.objects:
            o.select_set(True)
        st = bpy.context.scene.prtt
        st.resolution, st.rays, st.bounces, st.output_dir = 32, 32, 0, {str(tmp_path / "out")!r}
        st.light_source = "BUILTIN"              # no World in an empty scene
        assert bpy.ops.prtt.unwrap() == {{"FINISHED"}}
        assert bpy.ops.prtt.bake_transfer() == {{"FINISHED"}}
        print("FILES", sorted(os.listdir({str(tmp_path / "out")!r})))
        # The installed copy finds its shaders inside the extension folder.
        from bl_ext.user_default.prtt_addon.shader_source import shader_dir
        assert shader_dir().startswith(os.path.dirname(pkg.__file__)), shader_dir()
        bpy.ops.object.camera_add(location=(4, -4, 3), rotation=(1.0, 0.0, 0.8))
        bpy.context.scene.camera = bpy.context.active_object
        bpy.context.scene.render.resolution_x, bpy.context.scene.render.resolution_y = 32, 24
        assert bpy.ops.prtt.render_preview() == {{"FINISHED"}}
        img = bpy.data.images["PRTT Preview"]
        print("PREVIEW", tuple(img.size), max(list(img.pixels)[3::4]))
    """)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["BLENDER_USER_RESOURCES"] = str(tmp_path / "blender-user")
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env,
                       cwd=str(tmp_path), timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "FILES ['Plane.transfer.exr', 'Suzanne.transfer.exr', 'manifest.json']" in r.stdout
    assert "PREVIEW (32, 24) 1.0" in r.stdout
