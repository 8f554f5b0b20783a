"""Project layout promises: core free of bpy, README commands, CI, manifest."""
import ast
import os
import re
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _imports(path):
    with open(path, encoding="utf-8") as f:
        tree = ast.parse(f.read(), path)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module


def test_core_never_imports_bpy_statically():
    core = os.path.join(ROOT, "prtt_addon", "core")
    seen = 0
    for folder, _, names in os.walk(core):
        for name in names:
            if name.endswith(".py"):
                mods = set(_imports(os.path.join(folder, name)))
                assert not {m for m in mods if m.split(".")[0] in ("bpy", "gpu", "mathutils", "bmesh")}, name
                seen += 1
    assert seen > 30, seen


def test_core_imports_in_plain_python_without_bpy():
    code = ("import sys, importlib, pkgutil, prtt_addon, prtt_addon.core as c\n"
            "for m in pkgutil.walk_packages(c.__path__, 'prtt_addon.core.'): importlib.import_module(m.name)\n"
            "import prtt_addon.cli\n"
            "assert 'bpy' not in sys.modules, 'bpy imported'\n")
    env = dict(os.environ, PYTHONPATH=ROOT)
    subprocess.run([sys.executable, "-c", code], check=True, env=env, cwd=ROOT)


def test_readme_commands_and_ci_agree():
    readme = open(os.path.join(ROOT, "README.md"), encoding="utf-8").read()
    assert "./prtt.sh demo" in readme and "./prtt.sh test" in readme
    ci = open(os.path.join(ROOT, ".ci", "run"), encoding="utf-8").read()
    assert re.search(r"^exec \./prtt\.sh test\s*$", ci, re.M)
    assert os.access(os.path.join(ROOT, ".ci", "run"), os.X_OK)
    assert os.access(os.path.join(ROOT, "prtt.sh"), os.X_OK)


def test_manifest_and_version_single_source():
    import tomllib

    import prtt_addon
    with open(os.path.join(ROOT, "blender_manifest.toml"), "rb") as f:
        man = tomllib.load(f)
    assert man["schema_version"] == "1.0.0" and man["blender_version_min"] == "4.2.0"
    assert man["version"] == prtt_addon.__version__
    assert all(isinstance(v, str) and v for v in man["permissions"].values())


def test_dependencies_pinned_in_one_place():
    req = open(os.path.join(ROOT, "requirements.txt"), encoding="utf-8").read()
    pins = dict(re.findall(r"^([A-Za-z0-9_.-]+)==(\S+)", req, re.M))
    for pkg in ("numpy", "embreex", "OpenEXR", "xatlas", "bpy"):
        assert pkg in pins, pkg
    assert pins["bpy"] == "5.0.1"
    apt = open(os.path.join(ROOT, "tools", "apt-packages.txt"), encoding="utf-8").read()
    for pkg in ("libegl1", "libegl-mesa0", "libgl1-mesa-dri"):
        assert re.search(rf"^{pkg}$", apt, re.M)


def test_cli_demo_runs():
    env = dict(os.environ, PYTHONPATH=ROOT)
    r = subprocess.run([sys.executable, "-m", "prtt_addon", "env", "forest", "--bands", "3"],
                       capture_output=True, text=True, env=env, cwd=ROOT)
    if "not available" in r.stderr:
        import pytest
        pytest.skip("bpy studio lights not installed")
    assert r.returncode == 0, r.stderr
    assert "irradiance error" in r.stdout
    bad = subprocess.run([sys.executable, "-m", "prtt_addon", "env", "nowhere"],
                         capture_output=True, text=True, env=env, cwd=ROOT)
    assert bad.returncode == 2 and "unknown built-in environment 'nowhere'" in bad.stderr
