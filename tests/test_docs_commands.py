"""The docs are executable (issue 37): every command in README.md and docs/
(shell code blocks and the first column of command tables) is extracted and

- its options and choices are checked against the command's own ``-h`` (a
  synopsis such as ``--bounce-denoise none|edge-aware|oidn`` must name the
  choices the tool has), for every command PRTT itself runs;
- run, at small sizes, where it can run here: the demo, the headless chain,
  ``bake -h``, a bake on a local Dask cluster; a quoted comment beside a
  command (``# "inputs unchanged ...; nothing to do"``) must match its output;
- or listed with the reason it cannot run here (``blender`` itself, a farm
  address, a long benchmark), by ``test_every_command_is_run_or_listed``.

A command that no rule knows fails the test: add it to a rule.
"""
import os
import re
import shlex
import subprocess
import sys

import pytest

from tests.test_headless_chain import ROOT

PAGES = ["README.md"] + sorted(f"docs/{n}" for n in os.listdir(os.path.join(ROOT, "docs")) if n.endswith(".md"))


def _commands_in(page: str) -> list:
    """(page, line, command, comment) of every command on a page: lines of
    ```sh blocks (an indented line continues the one before, as in the
    synopses; a trailing backslash too) and backticked first cells of table
    rows that start with a command."""
    with open(os.path.join(ROOT, page), encoding="utf-8") as f:
        lines = f.read().splitlines()
    out, block, lang = [], False, ""
    for i, ln in enumerate(lines, 1):
        fence = re.match(r"^```(\w*)", ln)
        if fence:
            block, lang = (not block), fence.group(1)
            continue
        if block and lang == "sh":
            text = ln.rstrip()
            if not text.strip() or text.lstrip().startswith("#"):
                continue
            cmd, _, comment = text.partition("  #")
            if out and out[-1][0] == page and (ln.startswith((" ", "\t")) or out[-1][2].endswith("\\")):
                p, n, prev, c = out[-1]
                out[-1] = (p, n, prev.rstrip("\\").rstrip() + " " + cmd.strip(), c or comment.strip())
            else:
                out.append((page, i, cmd.strip(), comment.strip()))
        elif not block:
            m = re.match(r"^\| `((?:python |\./prtt\.sh |blender )[^`]*)` \|", ln)
            if m:
                out.append((page, i, m.group(1).replace("\\|", "|"), ""))
    return out


COMMANDS = [c for page in PAGES for c in _commands_in(page)]


def _ids(cmds):
    return [f"{p}:{n}" for p, n, _, _ in cmds]


#: Commands that cannot run here, by pattern, with the reason.
NOT_HERE = [
    (r"^blender ", "needs Blender's own executable (this machine has Blender as a Python module only); "
                   "its options are checked against the same parser's -h"),
    (r"tcp://(farm|scheduler-host|HOST)", "a farm's scheduler address (the recipe is run by tests/test_farm_recipe.py)"),
    (r"\bdask (scheduler|worker)\b|distributed\.cli", "the farm recipe: run by tests/test_farm_recipe.py"),
    (r"^(python -m )?pip install", "installs packages (the farm recipe's install is run by tests/test_farm_recipe.py)"),
    (r"^\./prtt\.sh (test|slow)$", "the test suite itself"),
    (r"^\./prtt\.sh fuzz", "fuzzing (a minute or more per reader): tests/test_fuzz.py runs every harness "
                            "with a fixed budget and its options"),
    (r"tools/build_extension\.py", "builds the extension zips: run by tests/test_extension.py"),
    (r"--job-only", "writes a farm's job from a .blend: tests/test_newcomer.py bakes such a job with bake-job and "
                    "compares it with the .blend's own bake"),
    (r"^\./prtt\.sh compat", "each Blender's venv and the user's chain (minutes): tests/test_compat.py runs it "
                              "for the default versions"),
    (r"^python -m http\.server", "a static server for viewer/: tests/test_web_viewer.py serves the same folders "
                                  "and drives the page in headless Chromium"),
    (r"prtt_addon\.dev\.bench [\w-]+", "a benchmark (minutes, writes docs/bench/): options checked against -h"),
    (r"[\[\]]|\|| (N|DIR|OUTDIR|JOB\.npz|FILE\.blend|IMG\.png|PATH|M|NAME|F|DEG|TOL)\b",
     "a synopsis (placeholders, [optional] parts, a|b choices): options checked against -h"),
]


def _not_here(cmd: str):
    return next((why for pat, why in NOT_HERE if re.search(pat, cmd)), None)


def _runner(cmd: str):
    """The runnable form's kind, or None."""
    if "[" in cmd:
        return None
    if re.match(r"^\./prtt\.sh demo$", cmd):
        return "demo"
    if re.match(r"^python -m prtt_addon (bake|render|export) scene\.blend", cmd) or cmd == "python -m prtt_addon bake -h":
        return "chain"
    if re.match(r"^python -m prtt_addon bake-job JOB\.npz --out DIR --dask local:\d+$", cmd):
        return "dask-local"
    return None


def test_the_docs_have_commands():
    pages = {p for p, _, _, _ in COMMANDS}
    assert {"README.md", "docs/addon.md", "docs/distributed.md", "docs/preview.md"} <= pages, pages
    assert len(COMMANDS) > 40, len(COMMANDS)


def test_every_command_is_run_or_listed(capsys):
    """Each command is run by this file or listed with why not; none unknown."""
    unknown, report = [], []
    for page, line, cmd, _ in COMMANDS:
        kind = _runner(cmd)
        why = None if kind else _not_here(cmd)
        if kind is None and why is None:
            unknown.append(f"{page}:{line}: {cmd}")
        report.append(f"{page}:{line}: {'RUN (' + kind + ')' if kind else 'NOT RUN: ' + str(why)}: {cmd}")
    with capsys.disabled():
        print("\ncommands in the docs:\n  " + "\n  ".join(report))
    assert not unknown, "commands in the docs that no rule runs or lists:\n" + "\n".join(unknown)


# --- options against -h ---------------------------------------------------------------------

def _help_target(cmd: str):
    """The module and subcommand whose -h documents ``cmd`` (None: not PRTT's)."""
    m = re.search(r"(?:-m prtt_addon\.dev\.bench|prtt_addon\.dev\.bench) ([\w-]+)", cmd)
    if m:
        return ["-m", "prtt_addon.dev.bench", m.group(1)]
    if re.search(r"-m prtt_addon\.worker\b", cmd):
        return ["-m", "prtt_addon.worker"]
    if re.search(r"(?:-m prtt_addon\.dev\.demo|\./prtt\.sh demo)\b", cmd):
        return ["-m", "prtt_addon.dev.demo"]
    m = re.search(r"(?:-m prtt_addon|blender -c prtt|\./prtt\.sh) (bake-job|bake|render|export|env)\b", cmd)
    if m:
        return ["-m", "prtt_addon", m.group(1)]
    return None


_HELP: dict = {}


def _help(target) -> str:
    key = tuple(target)
    if key not in _HELP:
        r = subprocess.run([sys.executable, *target, "-h"], capture_output=True, text=True, timeout=120,
                           env=dict(os.environ, PYTHONPATH=ROOT), cwd=ROOT)
        assert r.returncode == 0, r.stderr
        _HELP[key] = r.stdout
    return _HELP[key]


WITH_HELP = [c for c in COMMANDS if _help_target(c[2]) is not None and not c[2].startswith("blender -b")]


@pytest.mark.parametrize("page, line, cmd, comment", WITH_HELP, ids=_ids(WITH_HELP))
def test_options_and_choices_exist(page, line, cmd, comment):
    """Every --option a command names is in its -h, and a|b|c choices given
    after an option are the option's choices (the CLI's are case-insensitive)."""
    text = _help(_help_target(cmd))
    # ``--opt {a,b,c}`` in argparse's help
    choices = {m.group(1): {v.lower() for v in m.group(2).split(",")}
               for m in re.finditer(r"(--[\w-]+) \{([^}]+)\}", text)}
    for m in re.finditer(r"(?<![\w-])(--[a-z][\w-]*)(?:[ =]([\w.:-]+(?:\|[\w.:-]+)+))?", cmd):
        opt, alts = m.group(1), m.group(2)
        assert re.search(rf"(?<![\w-]){re.escape(opt)}(?![\w-])", text), f"{page}:{line}: {opt} is not an option of " \
                                                                         f"{' '.join(_help_target(cmd))}"
        if alts and opt in choices:
            named = {a.lower() for a in alts.split("|")}
            assert named == choices[opt], f"{page}:{line}: {opt} {alts}: the tool's choices are {sorted(choices[opt])}"


# --- runs -----------------------------------------------------------------------------------

RUN = [c for c in COMMANDS if _runner(c[2])]
SMALL = {"bake": ["--resolution", "32", "--rays", "16", "--bounce-rays", "4"], "render": ["--size", "48x32"],
         "demo": ["--resolution", "64", "--rays", "16", "--bounce-rays", "4", "--size", "64x36", "--no-relight"]}


def _quoted(comment: str):
    """A comment's quoted text as a pattern (``...`` matches anything)."""
    m = re.search(r'"([^"]+)"', comment)
    if not m:
        return None
    return re.compile(".*?".join(re.escape(part.strip()) for part in m.group(1).split("...")), re.S)


def _run(cmd, cwd, extra=()):
    argv = shlex.split(cmd)
    if argv[0] == "python":
        argv[0] = sys.executable
    elif argv[0] == "./prtt.sh":
        argv[0] = os.path.join(ROOT, "prtt.sh")
    r = subprocess.run(argv + list(extra), capture_output=True, text=True, timeout=600, cwd=cwd,
                       env=dict(os.environ, PYTHONPATH=ROOT))
    return r


@pytest.fixture(scope="module")
def chain_blend(tmp_path_factory):
    """scene.blend for the headless chain: a floor and a box without PRTT maps, a camera."""
    from tests import real_scenes as rs
    from tests.blender_util import addon_bpy
    bpy = addon_bpy()
    rs.floor(bpy, 8.0)
    rs.add_object(bpy, "Box", rs.cube_mesh(bpy, "box"), location=(0, 0, 0.5))
    rs.scene_camera(bpy, (0, -9, 5), (1.05, 0, 0))
    bpy.context.scene.prtt.light_source = "BUILTIN"
    path = tmp_path_factory.mktemp("docs_chain") / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    return path


def _chain_blocks() -> dict:
    """{page: its bake/render lines on scene.blend, in order}: a page's headless chain."""
    chains = {}
    for c in RUN:
        if _runner(c[2]) == "chain" and "scene.blend" in c[2]:
            chains.setdefault(c[0], []).append(c)
    return chains


@pytest.mark.blender
@pytest.mark.parametrize("page", sorted(_chain_blocks()))
def test_headless_chain_runs_as_written(page, chain_blend, tmp_path):
    """The page's bake/render lines in order, in a folder holding scene.blend;
    each exits 0 and prints what its comment quotes."""
    (tmp_path / "scene.blend").write_bytes(chain_blend.read_bytes())
    chain = _chain_blocks()[page]
    if not any(" bake scene.blend" in c[2] for c in chain):
        # a page that starts from a baked scene (an export): bake it first, as its text says
        r = _run("python -m prtt_addon bake scene.blend --out textures --unwrap SMART", tmp_path, SMALL["bake"])
        assert r.returncode == 0, r.stderr
    for _, line, cmd, comment in chain:
        kind = next(k for k in ("bake", "render", "export") if f" {k} " in f" {cmd} ")
        r = _run(cmd, tmp_path, SMALL.get(kind, []) if "-h" not in cmd.split() else ())
        assert r.returncode == 0, f"{page}:{line}: {cmd}\n{r.stdout}\n{r.stderr}"
        pattern = _quoted(comment)
        if pattern is not None:
            assert pattern.search(r.stdout + r.stderr), f"{page}:{line}: {comment!r} not in\n{r.stdout}"


def test_bake_help_runs_as_written():
    cmds = [c for c in RUN if c[2] == "python -m prtt_addon bake -h"]
    assert cmds
    r = _run(cmds[0][2], ROOT)
    assert r.returncode == 0 and "--bounce-denoise" in r.stdout, r.stderr


@pytest.mark.blender
@pytest.mark.parametrize("page, line, cmd, comment", [c for c in RUN if _runner(c[2]) == "demo"],
                         ids=_ids([c for c in RUN if _runner(c[2]) == "demo"]))
def test_demo_runs_as_written(page, line, cmd, comment, tmp_path):
    r = _run(cmd, tmp_path, SMALL["demo"] + ["--out", str(tmp_path / "demo")])
    assert r.returncode == 0, f"{page}:{line}\n{r.stdout}\n{r.stderr}"
    assert (tmp_path / "demo" / "demo_side_by_side.png").is_file()
    assert not [n for n in ("EGL Error", "not available", "Traceback") if n in r.stdout + r.stderr], r.stderr


@pytest.mark.parametrize("page, line, cmd, comment", [c for c in RUN if _runner(c[2]) == "dask-local"],
                         ids=_ids([c for c in RUN if _runner(c[2]) == "dask-local"]))
def test_dask_local_bake_runs_as_written(page, line, cmd, comment, tmp_path):
    pytest.importorskip("distributed")
    from prtt_addon.core.io.jobfile import save_scene
    from tests.scenes_util import floor_and_box
    save_scene(floor_and_box(res=16), tmp_path / "JOB.npz", extra={"settings": {"rays": 16, "bounces": 0}})
    r = _run(cmd.replace("local:4", "local:2"), tmp_path)
    assert r.returncode == 0, f"{page}:{line}\n{r.stdout}\n{r.stderr}"
    assert (tmp_path / "DIR" / "manifest.json").is_file()
