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
DEV_ONLY = ("prtt_addon.dev",)


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
    # A module a child process runs (["python", "-m", "prtt_addon.worker", ...]) is not imported.
    launched = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.List, ast.Tuple)):
            for a, b in zip(node.elts, node.elts[1:]):
                if isinstance(a, ast.Constant) and a.value == "-m":
                    launched.add(id(b))
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
        elif (isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in launched
              and re.fullmatch(rf"{PKG}(\.\w+)+", node.value)):
            # A module named by string (importlib, jit.load): the same arrow, seen here too.
            assert node.value in mods, f"{path}:{node.lineno}: names {node.value}, which is not a module"
            targets = [node.value]
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
        for _target, line, inside, src in _package_imports(m, p, k, mods):
            if inside and "#" not in src:
                bare.append(f"{os.path.relpath(p, ROOT)}:{line}: {src.strip()}")
    assert not bare, "\n".join(bare)


def test_architecture_page_names_every_module():
    """docs/architecture.md is the newcomer's map: every runtime module is on it."""
    doc = open(os.path.join(ROOT, "docs", "architecture.md"), encoding="utf-8").read()
    missing = []
    for dotted, (_path, is_pkg) in _modules().items():
        if is_pkg or dotted.startswith(DEV_ONLY):
            continue
        stem = dotted.rsplit(".", 1)[1]
        if f"`{stem}`" not in doc and not re.search(rf"`{stem}[.(` ]", doc) and f", `{stem}`" not in doc:
            missing.append(dotted)
    assert not missing, missing


#: The floors of docs/architecture.md, lowest first. A module may import from
#: its own floor and from any floor below; never from a floor above
#: (function-level imports included). Each entry is a module or a package.
FLOORS = [
    ("ground", ["prtt_addon.version", "prtt_addon.core.base", "prtt_addon.core.settings_schema"]),
    ("SH", ["prtt_addon.core.sh"]),
    ("domain types", ["prtt_addon.core.model"]),
    ("texels", ["prtt_addon.core.texels"]),
    ("shading", ["prtt_addon.core.shading"]),
    ("files", ["prtt_addon.core.io"]),
    ("light", ["prtt_addon.core.light"]),
    ("estimators", ["prtt_addon.core.bake.estimators"]),
    ("executors", ["prtt_addon.core.bake.executors"]),
    ("pipeline", ["prtt_addon.core.bake.pipeline"]),
    ("preview core", ["prtt_addon.core.preview"]),
    ("command-line helpers", ["prtt_addon.cli_options", "prtt_addon.env_report"]),
    ("worker", ["prtt_addon.worker"]),
    ("Blender ground", ["prtt_addon.blender.shared", "prtt_addon.blender.rna_arrays", "prtt_addon.blender.blendfile",
                        "prtt_addon.blender.versions"]),
    ("Blender scene", ["prtt_addon.blender.scene"]),
    ("Blender bake record", ["prtt_addon.blender.record"]),
    ("Blender preview", ["prtt_addon.blender.preview"]),
    ("Blender bake", ["prtt_addon.blender.bake"]),
    ("Blender glTF export", ["prtt_addon.blender.gltf"]),
    ("Blender UI", ["prtt_addon.blender.ui"]),
    ("Blender entry points", ["prtt_addon.blender.commands", "prtt_addon.blender.registration",
                              "prtt_addon.blender"]),
    ("entry points", ["prtt_addon.cli", "prtt_addon.__main__", "prtt_addon"]),
]
#: Packages whose ``__init__`` only names them (a docstring): on no floor.
CONTAINERS = ("prtt_addon.core", "prtt_addon.core.bake")


def _floor(mod):
    """The index of the floor that holds ``mod`` (its longest matching entry), or None."""
    best = None
    for i, (_, entries) in enumerate(FLOORS):
        for e in entries:
            if (mod == e or mod.startswith(e + ".")) and (best is None or len(e) > best[1]):
                best = (i, len(e))
    return None if best is None else best[0]


def test_every_module_has_a_floor():
    mods = [m for m in _modules() if not m.startswith(DEV_ONLY) and m not in CONTAINERS]
    assert not [m for m in mods if _floor(m) is None], [m for m in mods if _floor(m) is None]


def test_imports_only_go_down_the_floors():
    """docs/architecture.md's order, enforced: an import reaches its own floor
    or one below, never one above (function-level imports count: they are
    the same arrow, only later)."""
    mods = _modules()
    up = []
    for m, (p, k) in mods.items():
        if m.startswith(DEV_ONLY) or m in CONTAINERS:
            continue
        here = _floor(m)
        for target, line, _inside, src in _package_imports(m, p, k, mods):
            if target in CONTAINERS or target == m:
                continue
            if target.startswith(DEV_ONLY):      # the shipped add-on imports no development tool
                up.append(f"{os.path.relpath(p, ROOT)}:{line}: dev-only {target}: {src.strip()}")
                continue
            there = _floor(target)
            if there is None or there > here:
                up.append(f"{os.path.relpath(p, ROOT)}:{line}: {FLOORS[here][0]} -> "
                          f"{FLOORS[there][0] if there is not None else target}: {src.strip()}")
    assert not up, "imports against docs/architecture.md's floors:\n" + "\n".join(up)


def test_ruff_finds_nothing():
    """The pinned ruff with pyproject.toml's rules (bugs, not style) over the
    package, the tests and the tools."""
    import shutil
    ruff = shutil.which("ruff", path=os.path.dirname(sys.executable)) or shutil.which("ruff")
    assert ruff, "ruff is not installed: ./prtt.sh installs requirements.txt's pin"
    r = subprocess.run([ruff, "check", "prtt_addon", "tests", "tools"], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stdout + r.stderr


def test_module_names_are_unique():
    """One name per concept: no two modules of the package share a name."""
    stems = {}
    for dotted, (_path, is_pkg) in _modules().items():
        if not is_pkg:
            stems.setdefault(dotted.rsplit(".", 1)[1], []).append(dotted)
    assert not {k: v for k, v in stems.items() if len(v) > 1 and k != "__main__"}


def test_no_private_name_is_used_outside_its_module():
    """``from m import _x`` or ``m._x`` across modules (self/cls aside)."""
    bad = []
    for dotted, (path, _is_pkg) in _modules().items():
        tree = ast.parse(open(path, encoding="utf-8").read())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                bad += [f"{dotted}:{node.lineno}: {a.name}" for a in node.names
                        if a.name.startswith("_") and not a.name.startswith("__")]
            elif (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
                  and isinstance(node.value, ast.Name) and node.value.id not in ("self", "cls", "np", "sys", "os")):
                bad.append(f"{dotted}:{node.lineno}: {node.value.id}.{node.attr}")
    assert not bad, bad


def test_docstrings_carry_no_timings_of_a_machine():
    """Timings belong in docs/benchmarks.md (they go stale in a docstring)."""
    pat = re.compile(r"\d+ ?(ns|µs) per|on the 2-core VM|measured on the VM")
    hits = []
    for dotted, (path, _is_pkg) in _modules().items():
        for i, line in enumerate(open(path, encoding="utf-8"), 1):
            if pat.search(line):
                hits.append(f"{dotted}:{i}: {line.strip()}")
    assert not hits, hits


#: First path segments of the project's own folders (a path with another
#: start, such as three/addons/... or image/vnd.radiance, is not ours).
_OUR_ROOTS = ("prtt_addon", "core", "blender", "dev", "bench", "fuzz", "tools", "tests", "shaders", "viewer", "docs",
              "sh", "texels", "io", "light", "model", "shading", "preview", "bake", "export", "gltf", "ui", "base",
              "estimators", "executors", "pipeline")
_SEARCHED = ("", PKG, f"{PKG}/core", f"{PKG}/blender", f"{PKG}/core/bake", f"{PKG}/dev", f"{PKG}/dev/bench")
_EXTENSIONS = ("py", "md", "glsl", "js", "json", "toml", "sh", "txt", "csv", "png", "jpg", "exr", "hdr", "npz",
               "blend", "glb", "gltf", "ktx2", "zip", "whl", "html", "cube")


def _top_names(path):
    tree = ast.parse(open(path, encoding="utf-8").read(), path)
    names = set()
    for n in tree.body:
        if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(n.name)
        elif isinstance(n, (ast.Assign, ast.AnnAssign)):
            for t in (n.targets if isinstance(n, ast.Assign) else [n.target]):
                names |= {x.id for x in ast.walk(t) if isinstance(x, ast.Name)}
    return names          # defined here: a name imported from elsewhere is named by its own module


def test_paths_and_names_in_code_and_docs_exist():
    """Every project path a docstring, comment or page names exists
    (``core/io/exr_io.py``, ``blender/preview/offscreen.ensure_gpu``: the
    module and the name in it), searched from the repository, the package and
    its core/, blender/, bench/ and the file's own folder; every
    ``prtt_addon.a.b.name`` is a module or a name in one."""
    files = [os.path.join(d, f) for top in (PKG, "tools", "docs", "shaders", "viewer")
             for d, _, fs in os.walk(os.path.join(ROOT, top)) for f in fs
             if f.endswith((".py", ".md", ".glsl", ".js")) and "node_modules" not in d]
    files.append(os.path.join(ROOT, "README.md"))
    mods = _modules()
    path_re = re.compile(r"(?<![\w/.:-])((?:[A-Za-z_][\w-]*/)+[A-Za-z_][\w-]*)\.([A-Za-z_]\w*)(\.\w+)?")
    dotted_re = re.compile(rf"(?<![\w.]){PKG}((?:\.\w+)+)")
    stale = []
    for f in files:
        text = open(f, encoding="utf-8").read()

        def where(m, f=f, text=text):
            return f"{os.path.relpath(f, ROOT)}:{text.count(chr(10), 0, m.start()) + 1}"
        for m in path_re.finditer(text):
            path, name, more = m.groups()
            if path.split("/")[0] not in _OUR_ROOTS or more:
                continue
            dirs = [os.path.join(ROOT, b, path) for b in _SEARCHED + (os.path.relpath(os.path.dirname(f), ROOT),)]
            if name in _EXTENSIONS:
                if not any(os.path.exists(f"{d}.{name}") for d in dirs):
                    stale.append(f"{where(m)}: {path}.{name} does not exist")
                continue
            module = next((f"{d}.py" for d in dirs if os.path.isfile(f"{d}.py")), None)
            if module is None and not any(os.path.isdir(d) for d in dirs):
                stale.append(f"{where(m)}: {path}.{name}: no module {path}.py")
            elif module is not None and name not in _top_names(module):
                stale.append(f"{where(m)}: {path}.{name}: {os.path.relpath(module, ROOT)} has no {name}")
        for m in dotted_re.finditer(text):
            parts = (PKG + m.group(1)).split(".")
            k = max(i for i in range(1, len(parts) + 1) if ".".join(parts[:i]) in mods or i == 1)
            mod = ".".join(parts[:k])
            if mod not in mods:
                stale.append(f"{where(m)}: {'.'.join(parts)}: no such module")
            elif k < len(parts) and parts[k] not in _top_names(mods[mod][0]) and parts[k] not in ("py",):
                stale.append(f"{where(m)}: {'.'.join(parts)}: {mod} has no {parts[k]}")
    assert not stale, "\n".join(stale)
