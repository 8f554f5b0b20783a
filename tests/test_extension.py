"""Build this platform's extension zip and install it the way a user does,
into a fresh Blender user folder, then bake with the installed copy.
(Blender's validator on every platform's zip: test_validator.py.)"""
import importlib.util
import os
import re
import subprocess
import sys
import textwrap
import tomllib
import zipfile

import pytest

pytestmark = pytest.mark.blender
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TOOL = os.path.join(ROOT, "tools", "build_extension.py")


def _host_platform() -> str:
    """This machine in Blender's platform names, as the build tool writes them."""
    spec = importlib.util.spec_from_file_location("build_extension", TOOL)
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    if tool.host_platform() not in tool.PLATFORMS:
        pytest.skip(f"no extension zip for {tool.host_platform()}")
    return tool.host_platform()


@pytest.fixture(scope="module")
def extension_zip(tmp_path_factory):
    """This platform's zip (the one Blender here installs), built as a user builds it."""
    pytest.importorskip("bpy")
    plat = _host_platform()
    tmp = tmp_path_factory.mktemp("ext")
    r = subprocess.run([sys.executable, TOOL, "--offline", "--platform", plat, "--out", str(tmp / "dist"),
                        "--stage", str(tmp / "stage")], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout + r.stderr
    with open(os.path.join(ROOT, "blender_manifest.toml"), "rb") as f:
        version = tomllib.load(f)["version"]
    (path,) = (tmp / "dist").glob("*.zip")
    assert path.name == f"prtt_addon-{version}-{plat.replace('-', '_')}.zip"
    return str(path)


def test_zip_layout(extension_zip):
    with zipfile.ZipFile(extension_zip) as z:
        names = set(z.namelist())
        man = tomllib.loads(z.read("blender_manifest.toml").decode())
        licence = z.read("LICENSE")
    assert {"blender_manifest.toml", "LICENSE", "__init__.py", "worker.py", "core/sh/__init__.py", "blender/ui/operators.py",
            "core/preview/shader_source.py", "shaders/prtt_common.glsl", "shaders/prtt_surface_frag.glsl"} <= names
    # Runtime files only: the package's modules, shaders, wheels, the licence.
    assert not any(n.startswith(("dev/", "tests/", "docs/", "tools/", "assets/")) or "__pycache__" in n
                   or n.endswith(".pyc") for n in names)
    assert all(n.endswith(".py") or n.startswith(("shaders/", "wheels/")) or n in {"LICENSE", "blender_manifest.toml"}
               for n in names), sorted(names)
    with open(os.path.join(ROOT, "LICENSE"), "rb") as f:
        assert licence == f.read()
    assert man["id"] == "prtt_addon" and man["platforms"] == [_host_platform()]
    wheels = man["wheels"]
    for pkg in ("embreex", "openexr", "xatlas", "numba", "llvmlite"):
        for tag in ("cp311", "cp313"):
            assert any(os.path.basename(w).lower().startswith(pkg) and f"-{tag}-" in w for w in wheels)
    # numba for the bounce's compiled shading, one per numpy line (requirements.txt's markers)
    assert any(os.path.basename(w).startswith("numba-0.61.2-cp311-") for w in wheels)
    assert any(os.path.basename(w).startswith("numba-0.68.1-cp313-") for w in wheels)
    # threadpoolctl is pure Python: one wheel serves both Pythons.
    assert [w for w in wheels if "threadpoolctl" in w] == ["./wheels/threadpoolctl-3.8.0-py3-none-any.whl"]
    assert len(wheels) == 11
    assert {w[2:] for w in wheels} == {n for n in names if n.startswith("wheels/")}


def documented_install_snippet(zip_name: str) -> str:
    """docs/addon.md's headless install snippet, verbatim; the zip it names
    must be the one the build makes (name and version)."""
    with open(os.path.join(ROOT, "docs", "addon.md"), encoding="utf-8") as f:
        doc = f.read()
    m = re.search(r"```python\n(import os, bpy\nbpy\.ops\.extensions\.package_install_files\(.*?)```", doc, re.S)
    assert m, "docs/addon.md has no install snippet"
    named = re.search(r'"dist/(prtt_addon-[^"]+\.zip)"', m.group(1)).group(1)
    if _host_platform() == "linux-x64":
        assert named == zip_name, (named, zip_name)
    return m.group(1).replace(named, zip_name)


def test_install_enable_and_bake(extension_zip, tmp_path):
    # The docs' snippet as written, run where `dist/` holds the zip (the
    # snippet's relative path, made absolute as package_install_files wants).
    install = documented_install_snippet(os.path.basename(extension_zip))
    script = textwrap.dedent(f"""
        import os, sys
        import bpy
        import importlib.util
        assert importlib.util.find_spec("prtt_addon") is None   # only the installed copy
        bpy.ops.wm.read_factory_settings(use_empty=True)
        INSTALL
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
        from bl_ext.user_default.prtt_addon.core.preview.shader_source import shader_dir
        assert shader_dir().startswith(os.path.dirname(pkg.__file__)), shader_dir()
        bpy.ops.object.camera_add(location=(4, -4, 3), rotation=(1.0, 0.0, 0.8))
        bpy.context.scene.camera = bpy.context.active_object
        bpy.context.scene.render.resolution_x, bpy.context.scene.render.resolution_y = 32, 24
        assert bpy.ops.prtt.render_preview() == {{"FINISHED"}}
        img = bpy.data.images["PRTT Preview"]
        print("PREVIEW", tuple(img.size), max(list(img.pixels)[3::4]))
    """).replace("INSTALL", install.rstrip())
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["BLENDER_USER_RESOURCES"] = str(tmp_path / "blender-user")
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env,
                       cwd=os.path.dirname(os.path.dirname(extension_zip)), timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "FILES ['Plane.transfer.exr', 'Suzanne.transfer.exr', 'manifest.json']" in r.stdout
    assert "PREVIEW (32, 24) 1.0" in r.stdout
    # a new session after the documented install has PRTT enabled (the snippet saves the
    # preferences); Blender loads them at start, the bpy module when asked (read_userpref)
    again = ("import bpy; bpy.ops.wm.read_userpref(); "
             "print('ENABLED', 'bl_ext.user_default.prtt_addon' in bpy.context.preferences.addons, "
             "hasattr(bpy.types.Scene, 'prtt'))")
    r = subprocess.run([sys.executable, "-c", again], capture_output=True, text=True, env=env, timeout=300)
    assert "ENABLED True True" in r.stdout, r.stdout[-2000:] + r.stderr[-2000:]
