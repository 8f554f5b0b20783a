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


# --- the import graph ---------------------------------------------------------------------

PKG = "prtt_addon"
#: Development-only code the extension zip leaves out: it imports Blender-side
#: modules lazily so that `bench bake` runs without bpy; held to "no cycles" only.
DEV_ONLY = ("prtt_addon.bench", "prtt_addon.demo")


def _modules():
    mods = {}
    for folder, _, names in os.walk(os.path.join(ROOT, PKG)):
        for name in names:
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                dotted = os.path.relpath(path, ROOT)[:-3].replace(os.sep, ".")
                is_pkg = dotted.endswith(".__init__")
                mods[dotted[:-9] if is_pkg else dotted] = (path, is_pkg)
    return mods


def _package_imports(mod, path, is_pkg, mods):
    """(imported module, line, inside a function, the source line) for every
    import of a package module outside ``if TYPE_CHECKING:`` blocks."""
    with open(path, encoding="utf-8") as f:
        text = f.read()
    tree = ast.parse(text, path)
    lines = text.splitlines()
    type_only = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            type_only |= {id(n) for n in ast.walk(node)}
    inner = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            inner |= {id(n) for n in ast.walk(node)}
    out = []
    for node in ast.walk(tree):
        if id(node) in type_only:
            continue
        targets = []
        if isinstance(node, ast.ImportFrom):
            if node.level:
                parts = mod.split(".") if is_pkg else mod.split(".")[:-1]
                parts = parts[:len(parts) - (node.level - 1)]
                base = ".".join(parts) + ("." + node.module if node.module else "")
            else:
                base = node.module or ""
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
        elif isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        for t in targets:
            if t == PKG or t.startswith(PKG + "."):
                while t not in mods and "." in t:
                    t = t.rsplit(".", 1)[0]
                out.append((t, node.lineno, id(node) in inner, lines[node.lineno - 1]))
    return out


def test_no_import_cycles():
    """Strongly connected components of the package's import graph, counting
    imports inside functions too (they only hide a cycle) and leaving out
    type-only ones. Importing a.b.c imports the package a.b first; that edge
    is Python's, not a design choice, so it is not counted."""
    mods = _modules()
    graph = {m: {t for t, *_ in _package_imports(m, p, k, mods) if t != m} for m, (p, k) in mods.items()}
    index, low, stack, on, cycles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    assert not cycles, cycles


def test_function_level_imports_say_why():
    """A package module imported inside a function (outside the dev-only
    bench and demo) carries a comment on that line saying why: start-up time,
    Blender not being ready, an optional dependency..."""
    mods = _modules()
    bare = []
    for m, (p, k) in mods.items():
        if m.startswith(DEV_ONLY):
            continue
        for target, line, inside, src in _package_imports(m, p, k, mods):
            if inside and "#" not in src:
                bare.append(f"{os.path.relpath(p, ROOT)}:{line}: {src.strip()}")
    assert not bare, "\n".join(bare)


def test_architecture_page_names_every_module():
    """docs/architecture.md is the newcomer's map: every runtime module is on it."""
    doc = open(os.path.join(ROOT, "docs", "architecture.md"), encoding="utf-8").read()
    missing = []
    for dotted, (path, is_pkg) in _modules().items():
        if is_pkg or dotted.startswith(DEV_ONLY):
            continue
        stem = dotted.rsplit(".", 1)[1]
        if f"`{stem}`" not in doc and not re.search(rf"`{stem}[.(` ]", doc) and f", `{stem}`" not in doc:
            missing.append(dotted)
    assert not missing, missing
