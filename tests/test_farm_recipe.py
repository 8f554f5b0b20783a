"""The farm recipe of docs/distributed.md ("On a farm"), run as written.

The section's ``sh`` block is read from the document and its commands run in
separate processes, with only what a test machine needs substituted: the
``pip install "./prtt[farm]"`` line installs a copy of this checkout (named
``prtt``, as in the recipe) into a folder of its own (``--target``, no
dependencies: they are this virtualenv's), then a ``dask scheduler`` and a
``dask worker`` with two worker processes of one thread each run on
127.0.0.1 at a free port, and the ``bake-job --dask`` line bakes a small job
on them. Every process runs outside the repository with ``PYTHONPATH`` = the
installed copy, so it can import only that ``prtt_addon`` (checked in the
workers). The farm's textures must equal, byte for byte, a local
``bake-job`` of the same job by the installed copy and by the checkout.

The recipe's virtualenv (in its prose) is not made: a fresh one would need
the index for numpy and the rest; the block's ``python`` is this interpreter.
"""
import email.parser
import hashlib
import importlib.metadata
import importlib.util
import json
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("distributed")

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "distributed.md"
#: What the package is built from (pyproject.toml); the rest of the checkout
#: (tests, tools, docs, assets) is not copied, so the build cannot depend on it.
SOURCES = ("pyproject.toml", "MANIFEST.in", "blender_manifest.toml", "LICENSE", "README.md", "shaders",
           "prtt_addon")
#: The package's requirements and the lines of requirements.txt they must repeat.
REQUIRES = {None: ("embreex", "openexr", "xatlas", "threadpoolctl", "numpy"),
            "farm": ("dask", "distributed"),
            "numba": ("numba", "llvmlite")}
#: Manifest fields that record how long things took, and how many threads traced.
EXECUTION_KEYS = ("seconds", "created", "rays_per_second", "threads", "memory")


# --- the recipe ------------------------------------------------------------------------

def recipe() -> dict:
    """{kind: command line} of the fenced block in docs/distributed.md's "On a farm"."""
    text = DOC.read_text(encoding="utf-8")
    section = text.split("\n## On a farm\n", 1)[1].split("\n## ", 1)[0]
    block = re.search(r"```sh\n(.*?)```", section, re.S).group(1)
    kinds = {"install": "python -m pip install ",
             "scheduler": "python -m dask scheduler ", "worker": "python -m dask worker ",
             "bake": "python -m prtt_addon bake-job "}
    out = {}
    for line in block.splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        kind = next((k for k, start in kinds.items() if line.startswith(start)), None)
        assert kind is not None, f"docs/distributed.md's farm recipe has a command this test does not run: {line}"
        assert kind not in out, f"two {kind} commands in the farm recipe"
        out[kind] = line
    assert set(out) == set(kinds), f"the farm recipe lacks {set(kinds) - set(out)}"
    return out


def command(line: str, subs=()) -> list:
    """``line`` with each (old, new) of ``subs`` replaced (each must occur; ``new``
    is shell text: quote paths), split as the shell would, with ``python`` =
    this interpreter."""
    for old, new in subs:
        assert old in line, f"the farm recipe's {line!r} no longer contains {old!r}"
        line = line.replace(old, new)
    argv = shlex.split(line)
    assert argv[0] == "python"
    return [sys.executable] + argv[1:]


def q(path) -> str:
    return shlex.quote(str(path))


def can_build_offline() -> bool:
    """Whether this virtualenv builds a wheel with its own setuptools (pip's
    --no-build-isolation): setuptools >= 70.1 has bdist_wheel, older ones
    need the `wheel` package."""
    try:
        version = importlib.metadata.version("setuptools")
    except importlib.metadata.PackageNotFoundError:
        return False
    major_minor = tuple(int(x) for x in re.findall(r"\d+", version)[:2])
    return major_minor >= (70, 1) or importlib.util.find_spec("wheel") is not None


def pins() -> dict:
    """{name (lower case): version} of requirements.txt's ``name==version``
    lines for this Python (a ``python_version`` marker chooses between two
    lines of one name: numba's two lines)."""
    sys.path.insert(0, str(ROOT / "tools"))
    from build_extension import marker_holds
    python = f"{sys.version_info[0]}.{sys.version_info[1]}"
    out = {}
    for line in (ROOT / "requirements.txt").read_text().splitlines():
        m = re.match(r"\s*([A-Za-z0-9_.-]+)==([^\s;]+)\s*(?:;\s*([^#]*?))?\s*(?:#.*)?$", line)
        if m and marker_holds(m.group(3) or "", python):
            out[m.group(1).lower()] = m.group(2)
    return out


def version_of(src: Path) -> str:
    """The version in a checkout's blender_manifest.toml."""
    return re.search(r'^version\s*=\s*"([^"]+)"', (src / "blender_manifest.toml").read_text(), re.M).group(1)


def files(folder: Path) -> dict:
    """{name: sha256} of a bake's outputs (textures, vertex transfer; the manifest aside)."""
    return {n: hashlib.sha256((folder / n).read_bytes()).hexdigest() for n in sorted(os.listdir(folder))
            if n.endswith((".exr", ".npz"))}


def without(x, keys=EXECUTION_KEYS):
    if isinstance(x, dict):
        return {k: without(v, keys) for k, v in x.items() if not any(t in k for t in keys)}
    if isinstance(x, list):
        return [without(v, keys) for v in x]
    return x


def manifest(folder: Path) -> dict:
    return without(json.loads((folder / "manifest.json").read_text()))


def run(argv, **kw):
    r = subprocess.run(argv, capture_output=True, text=True, timeout=300, **kw)
    assert r.returncode == 0, f"{shlex.join(argv)} exited {r.returncode}:\n{r.stdout}\n{r.stderr}"
    return r


# --- fixtures --------------------------------------------------------------------------

@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(farm folder, installed site folder, environment): the recipe's install
    line run in a folder outside the repository that holds a copy of the
    checkout named ``prtt`` (pip builds in the source tree; a copy keeps
    build/ and prtt.egg-info/ out of the repository and apart from parallel
    runs)."""
    base = tmp_path_factory.mktemp("farm")
    assert ROOT not in base.resolve().parents
    src = base / "prtt"
    src.mkdir()
    skip = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in SOURCES:
        p = ROOT / name
        if p.is_dir():
            shutil.copytree(p, src / name, ignore=skip)
        elif p.exists():
            shutil.copy2(p, src / name)
    site = base / "site"
    offline = can_build_offline()
    argv = command(recipe()["install"]) + ["--no-deps", "--target", str(site)]
    if offline:
        argv.append("--no-build-isolation")      # this venv's setuptools: no index needed
    t = time.monotonic()
    r = subprocess.run(argv, cwd=base, capture_output=True, text=True, timeout=300)
    if r.returncode and not offline and re.search(r"install(ing)? build dependencies", r.stdout + r.stderr, re.I):
        pytest.skip(f"this virtualenv cannot build the wheel itself (setuptools "
                    f"{importlib.metadata.version('setuptools')} without the `wheel` package) and pip could "
                    f"not fetch setuptools for an isolated build: "
                    f"{next((l.strip() for l in r.stdout.splitlines() + r.stderr.splitlines() if 'ERROR' in l), '')}")
    assert r.returncode == 0, f"{shlex.join(argv)}:\n{r.stdout}\n{r.stderr}"
    print(f"installed in {time.monotonic() - t:.1f} s ({'offline' if offline else 'isolated build'})")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "DASK_SCHEDULER_ADDRESS")}
    env.update(PYTHONPATH=str(site), PYTHONUNBUFFERED="1")
    return base, site, env


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stop(p: subprocess.Popen) -> None:
    """Kill ``p`` and its process group (a `dask worker`'s nanny processes)."""
    try:
        os.killpg(p.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    p.wait(30)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            os.killpg(p.pid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.1)
    raise AssertionError(f"processes of group {p.pid} outlived SIGKILL")


@pytest.fixture
def farm(installed, request):
    """The recipe's scheduler and worker lines on 127.0.0.1 at a free port, in
    the farm folder with the installed copy, both workers connected; the
    scheduler's address. Both process groups are killed at the end, whatever
    happened (a finalizer)."""
    base, site, env = installed
    steps = recipe()
    port = str(free_port())
    addr = f"tcp://127.0.0.1:{port}"
    procs = []

    def start(argv, name):
        log = open(base / f"{name}.log", "w")
        p = subprocess.Popen(argv, cwd=base, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        log.close()
        procs.append(p)
        return p

    def finish():
        for p in reversed(procs):
            stop(p)

    request.addfinalizer(finish)
    # Local only: listen on the loopback interface; no dashboard (it would
    # want port 8787, and bokeh).
    sched = start(command(steps["scheduler"], [("8786", port)]) + ["--host", "127.0.0.1", "--no-dashboard"],
                  "scheduler")
    deadline = time.monotonic() + 60
    while True:
        assert sched.poll() is None, (base / "scheduler.log").read_text()
        try:
            socket.create_connection(("127.0.0.1", int(port)), timeout=1).close()
            break
        except OSError:
            assert time.monotonic() < deadline, (base / "scheduler.log").read_text()
            time.sleep(0.1)
    worker = start(command(steps["worker"], [("scheduler-host:8786", f"127.0.0.1:{port}"),
                                             ("--nworkers 16", "--nworkers 2")]) + ["--no-dashboard"], "worker")
    from distributed import Client
    with Client(addr, timeout=60) as client:
        deadline = time.monotonic() + 90
        while len(client.nthreads()) < 2:
            assert worker.poll() is None and time.monotonic() < deadline, (base / "worker.log").read_text()
            time.sleep(0.2)
    return addr


# --- tests -----------------------------------------------------------------------------

def test_installed_package(installed):
    """``pip install "./prtt[farm]"`` installs prtt_addon with every module, its
    shaders and its manifest, the manifest's version, and requirements.txt's pins."""
    base, site, env = installed
    src = base / "prtt"
    assert sorted(p.name for p in site.iterdir()) == ["prtt-" + version_of(src) + ".dist-info", "prtt_addon"]
    pkg = site / "prtt_addon"
    src_py = {p.relative_to(src / "prtt_addon") for p in (src / "prtt_addon").rglob("*.py")}
    got_py = {p.relative_to(pkg) for p in pkg.rglob("*.py")}
    assert src_py == got_py, f"missing {sorted(map(str, src_py - got_py))} (pyproject.toml's packages)"
    assert all((pkg / p).read_bytes() == (src / "prtt_addon" / p).read_bytes() for p in src_py)
    glsl = sorted(p.name for p in (src / "shaders").glob("*.glsl"))
    assert glsl and sorted(p.name for p in (pkg / "shaders").iterdir() if p.name != "__pycache__") == glsl
    assert (pkg / "blender_manifest.toml").read_bytes() == (src / "blender_manifest.toml").read_bytes()
    # Imported from the installed copy, outside the checkout: its version and shaders.
    probe = ("import json, prtt_addon, prtt_addon.version as v; "
             "from prtt_addon.core.preview import shader_source as s; "
             "print(json.dumps([prtt_addon.__file__, v.__version__, s.shader_dir(), len(s.read_source('prtt_common.glsl'))]))")
    where, version, shaders, n = json.loads(run([sys.executable, "-c", probe], cwd=base, env=env).stdout)
    assert Path(where).parent == pkg and Path(shaders) == pkg / "shaders" and n > 0
    assert version == version_of(src)
    # The metadata: name, version, and the pins of requirements.txt.
    dist = next(site.glob("prtt-*.dist-info"))
    meta = email.parser.Parser().parsestr((dist / "METADATA").read_text())
    assert meta["Name"] == "prtt" and meta["Version"] == version
    got = {}
    for req in meta.get_all("Requires-Dist"):
        m = re.fullmatch(r"([A-Za-z0-9_.-]+)\s*==\s*(\S+?)\s*(?:;\s*extra\s*==\s*['\"](\w+)['\"])?", req)
        assert m, req
        got[(m.group(3), m.group(1).lower())] = m.group(2)
    want = {(extra, name): pins()[name] for extra, names in REQUIRES.items() for name in names}
    assert got == want
    assert sorted(meta.get_all("Provides-Extra")) == ["farm", "numba"]


def test_farm_recipe_bakes_the_local_bits(installed, farm, tmp_path):
    """The recipe's scheduler, two one-thread workers and ``bake-job --dask``:
    the textures of a local ``bake-job`` (installed copy and checkout), byte
    for byte, and the workers ran the installed prtt_addon."""
    from distributed import Client

    from prtt_addon.core.io.jobfile import save_scene
    from tests.scenes_util import floor_and_box

    base, site, env = installed
    job = base / "level.npz"          # the recipe's name, in the recipe's folder
    save_scene(floor_and_box(res=32), job, extra={"settings": {"rays": 64, "bounces": 1, "bounce_rays": 32}})
    bake = recipe()["bake"]
    addr = farm
    # Local bakes first (no --dask): the installed copy's (which also fills its
    # numba cache, as a farm node's first bake would) and the checkout's.
    here = bake.split(" --dask ")[0]
    run(command(here, [("/shared/level_prtt", q(tmp_path / "local"))]), cwd=base, env=env)
    run(command(here, [("level.npz", q(job)), ("/shared/level_prtt", q(tmp_path / "checkout"))]),
        cwd=ROOT, env=dict(env, PYTHONPATH=str(ROOT)))
    with Client(addr, timeout=60) as client:
        t = time.monotonic()
        r = run(command(bake, [("scheduler-host:8786", addr.removeprefix("tcp://")),
                               ("/shared/level_prtt", q(tmp_path / "farm"))]), cwd=base, env=env)
        seconds = time.monotonic() - t
        where = client.run(lambda: sys.modules["prtt_addon"].__file__)
        threads = client.nthreads()
    assert len(where) == 2 and all(Path(w).parent == site / "prtt_addon" for w in where.values()), where
    assert sorted(threads.values()) == [1, 1]
    assert "Dask: 2 workers" in r.stdout + r.stderr, r.stdout + r.stderr
    a = files(tmp_path / "local")
    assert len(a) == 4 and a == files(tmp_path / "farm") == files(tmp_path / "checkout")
    assert manifest(tmp_path / "local") == manifest(tmp_path / "farm") == manifest(tmp_path / "checkout")
    assert json.loads((tmp_path / "farm" / "manifest.json").read_text())["prtt_version"] == version_of(base / "prtt")
    print(f"farm bake-job: {seconds:.1f} s")
