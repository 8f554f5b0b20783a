"""Conventions every command line of PRTT follows (issue 14, item 3):

* ``-h`` on every subcommand, exit 0;
* choices in any case (``--unwrap smart`` == ``SMART``, ``--mode TPFL`` == ``tpfl``);
* a value out of range is a usage error (exit 2) naming the option, the value
  and the range: ``--rays 0 is out of range: it must be 1..65536``;
* paths relative to the caller's folder, ./prtt.sh included;
* bake progress: one updating line on a terminal, plain lines elsewhere,
  ``--quiet`` for warnings, errors and the final line only.
"""
import io
import os
import subprocess
import sys

import pytest

from prtt_addon.cli import build_parser
from prtt_addon.cli_options import ConsoleProgress

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = dict(os.environ, PYTHONPATH=ROOT, PYTHONUNBUFFERED="1")


def py(*args, cwd=None, timeout=300):
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=ENV, cwd=cwd or ROOT,
                          timeout=timeout)


def parse_error(parser, argv, capsys) -> str:
    with pytest.raises(SystemExit) as e:
        parser.parse_args(argv)
    assert e.value.code == 2
    return capsys.readouterr().err.strip().splitlines()[-1]


def subparser(name):
    import argparse
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


# --- -h everywhere -------------------------------------------------------------------------

@pytest.mark.parametrize("args, says", [
    (["-m", "prtt_addon", "-h"], "bake-job"),
    (["-m", "prtt_addon", "env", "-h"], "--bands"),
    (["-m", "prtt_addon", "bake-job", "-h"], "--rays"),
    (["-m", "prtt_addon.dev.demo", "-h"], "--out"),
    (["-m", "prtt_addon", "bake", "-h"], "--unwrap"),
    (["-m", "prtt_addon", "render", "-h"], "--mode"),
    (["-m", "prtt_addon.worker", "-h"], "out_dir"),
    (["-m", "prtt_addon.core.settings_schema", "-h"], "--write"),
])
def test_dash_h_on_every_subcommand(args, says, tmp_path):
    if args[2:3] in (["bake"], ["render"]) or args[1] == "prtt_addon.dev.demo":
        pytest.importorskip("bpy")
    r = py(*args, cwd=tmp_path)
    assert r.returncode == 0 and r.stdout.startswith("usage:") and says in r.stdout, r.stdout + r.stderr
    assert r.stderr == ""


@pytest.mark.blender
def test_dash_h_through_blender_c_prtt(capsys):
    """``blender -c prtt ...`` lands in blender/commands._cli, which returns the status
    (argparse's SystemExit never reaches Blender)."""
    from tests.blender_util import addon_bpy
    addon_bpy()
    from prtt_addon.blender.commands import _cli
    for argv, usage in ((["-h"], "usage: blender -c prtt bake"), (["bake", "-h"], "usage: blender -c prtt bake"),
                        (["bake", "--help"], "usage: blender -c prtt bake"),
                        (["render", "-h"], "usage: blender -c prtt render"),
                        (["export", "-h"], "usage: blender -c prtt export")):
        assert _cli(argv) == 0, argv
        assert capsys.readouterr().out.startswith(usage), argv
    assert _cli(["bake", "x.blend", "--rays", "0"]) == 2
    assert capsys.readouterr().err.strip().endswith("--rays 0 is out of range: it must be 1..65536")
    assert _cli(["frobnicate"]) == 2


# --- choices in any case ---------------------------------------------------------------------

def test_choices_are_case_insensitive():
    p = subparser("bake-job")
    base = ["job.npz", "--out", "o"]
    for option, given, value in (("--sampler", "SOBOL", "sobol"), ("--sampler", "Stratified", "stratified"),
                                 ("--estimator", "CONTROL-VARIATE", "control-variate"),
                                 ("--estimator", "control_variate", "control-variate"),
                                 ("--distribution", "Uniform", "uniform"), ("--overlap", "ERROR", "error")):
        assert getattr(p.parse_args(base + [option, given]), option[2:]) == value, (option, given)
    assert subparser("env").parse_args(["forest", "--method", "SAMPLES"]).method == "samples"


@pytest.mark.blender
def test_blender_choices_are_case_insensitive():
    pytest.importorskip("bpy")
    from prtt_addon.blender.commands import bake_parser
    from prtt_addon.blender.preview.offscreen import render_parser
    b = bake_parser("prtt bake")
    for given, value in (("smart", "SMART"), ("Xatlas", "XATLAS"), ("EXISTING", "EXISTING")):
        assert b.parse_args(["s.blend", "--unwrap", given]).unwrap == value
    assert b.parse_args(["s.blend", "--estimator", "PLAIN"]).estimator == "plain"
    r = render_parser("prtt render")
    for given, value in (("TPFL", "tpfl"), ("tpfl", "tpfl"), ("VERTEX_TPFL", "vertex-tpfl"),
                         ("Vertex-TP", "vertex-tp"), ("DIFFUSE", "diffuse")):
        assert r.parse_args(["s.blend", "--out", "x.png", "--mode", given]).mode == value


# --- values out of range ------------------------------------------------------------------------

def test_out_of_range_names_option_value_and_range(capsys):
    p = subparser("bake-job")
    base = ["job.npz", "--out", "o"]
    for argv, message in (
            (["--rays", "0"], "--rays 0 is out of range: it must be 1..65536"),
            (["--rays", "65537"], "--rays 65537 is out of range: it must be 1..65536"),
            (["--rays", "many"], "--rays many is not an integer: it must be 1..65536"),
            (["--bands", "17"], "--bands 17 is out of range: it must be 1..16"),
            (["--resolution", "0"], "--resolution 0 is out of range: it must be 1..16384"),
            (["--seed", "-1"], "--seed -1 is out of range: it must be 0..4294967295"),
            (["--adaptive", "101"], "--adaptive 101 is out of range: it must be 0..100"),
            (["--adaptive", "nan"], "--adaptive nan is not a finite number: it must be 0..100"),
            (["--chunk-rays", "1000"], "--chunk-rays 1000 is out of range: it must be 1024..4194304"),
            (["--env-strength", "0"], "--env-strength 0 is out of range: it must be > 0 and <= 1000000"),
            (["--sampler", "halton"],
             "--sampler halton is an invalid choice: it must be one of sobol, stratified, random")):
        err = parse_error(p, base + argv, capsys)
        assert err == f"python -m prtt_addon bake-job: error: {message}", err
    assert parse_error(subparser("env"), ["forest", "--bands", "65"], capsys).endswith(
        "error: --bands 65 is out of range: it must be 1..64")


def test_out_of_range_exit_status_end_to_end(tmp_path):
    r = py("-m", "prtt_addon", "bake-job", "missing.npz", "--out", "o", "--bounces", "9", cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.startswith("usage:"), r.stderr
    assert r.stderr.strip().endswith("error: --bounces 9 is out of range: it must be 0..8")
    assert os.listdir(tmp_path) == []


@pytest.mark.blender
def test_blender_bake_range_errors_come_before_the_file(tmp_path):
    """The options are checked before the .blend is opened (it need not exist)."""
    pytest.importorskip("bpy")
    for argv, message in ((["--bands", "17"], "--bands 17 is out of range: it must be 1..16"),
                          (["--resolution", "16385"], "--resolution 16385 is out of range: it must be 1..16384"),
                          (["--margin", "65"], "--margin 65 is out of range: it must be 0..64"),
                          (["--unwrap", "cube"], "--unwrap cube is an invalid choice: it must be one of "
                                                 "EXISTING, SMART, LIGHTMAP, XATLAS")):
        r = py("-m", "prtt_addon", "bake", "missing.blend", *argv, cwd=tmp_path)
        assert r.returncode == 2 and r.stderr.strip().endswith(f"error: {message}"), r.stderr


# --- paths relative to the caller ---------------------------------------------------------------

def test_prtt_sh_keeps_the_callers_folder(tmp_path):
    """./prtt.sh runs the project's Python in the caller's folder: a relative job
    file and --out are the caller's (they used to resolve against the repository)."""
    from prtt_addon.core.io.jobfile import save_scene
    from tests.scenes_util import floor_and_box
    work = tmp_path / "work"
    work.mkdir()
    save_scene(floor_and_box(res=8), work / "job.npz")
    sh = os.path.join(ROOT, "prtt.sh")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    r = subprocess.run([sh, "py", "-c", "import os; print(os.getcwd())"], capture_output=True, text=True,
                       cwd=work, env=env, timeout=300)
    assert r.returncode == 0 and r.stdout.strip() == str(work), r.stdout + r.stderr
    r = subprocess.run([sh, "py", "-m", "prtt_addon", "bake-job", "job.npz", "--out", "textures", "--rays", "4",
                        "--bounces", "0", "--quiet"], capture_output=True, text=True, cwd=work, env=env, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert (work / "textures" / "manifest.json").is_file()
    assert not os.path.exists(os.path.join(ROOT, "textures"))
    # --quiet: the final line only
    assert r.stdout == f"prtt: done: {work / 'textures' / 'manifest.json'}\n", r.stdout
    r = subprocess.run([sh, "py", "-m", "prtt_addon", "env", "forest", "--bands", "2"], capture_output=True,
                       text=True, cwd=work, env=env, timeout=300)
    assert r.returncode == 0 and "projected to 2 bands" in r.stdout, r.stdout + r.stderr


# --- progress ----------------------------------------------------------------------------------------

class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


class FakeTTY(io.StringIO):
    def isatty(self):
        return True


EVENTS = [
    (0.0, {"type": "progress", "stage": "load", "fraction": 0.0}),
    (0.1, {"type": "start", "pid": 1, "sets": ["floor", "box"], "triangles": 14, "settings": {}, "light": None}),
    (0.2, {"type": "progress", "stage": "bvh", "fraction": 0.0}),
    (0.5, {"type": "progress", "stage": "trace", "set": "floor", "fraction": 0.0, "rays": 0, "rays_per_s": 0.0,
           "set_index": 0, "sets": 2}),
    (2.5, {"type": "progress", "stage": "trace", "set": "floor", "fraction": 0.25, "rays": 50_000_000,
           "rays_per_s": 25_000_000.0, "set_index": 0, "sets": 2}),
    (3.0, {"type": "warning", "message": "set 'floor': 3 texels are covered by overlapping UV islands"}),
    (4.5, {"type": "progress", "stage": "trace", "set": "floor", "fraction": 0.5, "rays": 100_000_000,
           "rays_per_s": 25_000_000.0, "set_index": 0, "sets": 2}),
    (10.6, {"type": "progress", "stage": "trace", "set": "floor", "fraction": 0.75, "rays": 150_000_000,
            "rays_per_s": 24_000_000.0, "set_index": 0, "sets": 2}),
    (11.0, {"type": "progress", "stage": "bounce", "set": "floor", "level": 1, "fraction": 0.0, "rays": 0}),
    (13.0, {"type": "progress", "stage": "bounce", "set": "floor", "level": 1, "fraction": 0.4, "rays": 4_000_000}),
    (14.0, {"type": "progress", "stage": "write", "file": "floor.transfer.exr", "fraction": 0.0}),
    (15.0, {"type": "done", "manifest": "out/manifest.json", "skipped": False}),
]


def feed(printer, clock, events=EVENTS):
    for t, e in events:
        clock.t = t
        printer(e)


def test_progress_on_a_terminal_is_one_updating_line():
    clock, out = Clock(), FakeTTY()
    feed(ConsoleProgress(out, clock=clock, width=200), clock)
    text = out.getvalue()
    # newlines only after the start line, the warning and the final line: progress rewrites one line with \r
    assert text.count("\n") == 3
    start, warning, rest, end = text.split("\n")
    assert start.split("\r")[1] == "prtt: load   0.0%"
    assert start.endswith("\rprtt: baking 2 set(s), 14 triangles")
    assert warning.endswith("\rprtt: warning: set 'floor': 3 texels are covered by overlapping UV islands")
    assert rest.endswith("\rprtt: done: out/manifest.json") and end == ""
    states = [seg.rstrip() for seg in text.replace("\n", "\r").split("\r") if seg.strip()]
    assert states == [
        "prtt: load   0.0%",
        "prtt: baking 2 set(s), 14 triangles",
        "prtt: load   0.0%",                                          # the progress line stays last
        "prtt: bvh   0.0%",
        "prtt: trace [floor 1/2]   0.0%",
        "prtt: trace [floor 1/2]  25.0%  25.0 Mrays/s  0:06 left",
        "prtt: warning: set 'floor': 3 texels are covered by overlapping UV islands",
        "prtt: trace [floor 1/2]  25.0%  25.0 Mrays/s  0:06 left",     # drawn again under the warning
        "prtt: trace [floor 1/2]  50.0%  25.0 Mrays/s  0:04 left",
        "prtt: trace [floor 1/2]  75.0%  24.0 Mrays/s  0:03 left",
        # bounce events carry rays but no rate: it comes from the stage's elapsed time
        "prtt: bounce [floor] level 1   0.0%",
        "prtt: bounce [floor] level 1  40.0%  2.0 Mrays/s  0:03 left",
        "prtt: write floor.transfer.exr   0.0%",
        "prtt: done: out/manifest.json"]
    # the line is cleared (blanks) before a line of its own, and a shorter state is padded over a longer one
    assert "\r" + " " * len(states[5]) + "\rprtt: warning:" in text
    segs = [seg for seg in rest.split("\r") if seg.strip()]
    for prev, new in zip(segs, segs[1:-1]):
        assert len(new) >= len(prev.rstrip()), (prev, new)


def test_progress_elsewhere_is_plain_lines():
    clock, out = Clock(), io.StringIO()
    feed(ConsoleProgress(out, clock=clock, interval=5.0), clock)
    assert "\r" not in out.getvalue()
    assert out.getvalue().splitlines() == [
        "prtt: load   0.0%",
        "prtt: baking 2 set(s), 14 triangles",
        "prtt: bvh   0.0%",
        "prtt: trace [floor 1/2]   0.0%",
        "prtt: warning: set 'floor': 3 texels are covered by overlapping UV islands",
        "prtt: trace [floor 1/2]  75.0%  24.0 Mrays/s  0:03 left",      # 5 s after the last line
        "prtt: bounce [floor] level 1   0.0%",
        "prtt: write floor.transfer.exr   0.0%",
        "prtt: done: out/manifest.json"]


@pytest.mark.parametrize("tty", [False, True])
def test_quiet_prints_warnings_errors_and_the_final_line(tty, capsys):
    clock = Clock()
    out = FakeTTY() if tty else io.StringIO()
    feed(ConsoleProgress(out, clock=clock, quiet=True), clock)
    assert out.getvalue() == ("prtt: warning: set 'floor': 3 texels are covered by overlapping UV islands\n"
                              "prtt: done: out/manifest.json\n")
    err = io.StringIO()
    p = ConsoleProgress(io.StringIO(), clock=clock, quiet=True, err=err)
    p({"type": "error", "error": "BakeError", "message": "no light"})
    assert err.getvalue() == "prtt: error: no light\n"


def test_final_lines_can_be_left_to_the_caller():
    """Blender's bake prints its own final line (the outcome, where it saved)."""
    clock, out = Clock(), FakeTTY()
    feed(ConsoleProgress(out, clock=clock, final=False), clock)
    assert "done" not in out.getvalue()
    assert out.getvalue().endswith("\r")          # the progress line is cleared, the caller's line follows


def test_bake_job_progress_lines_end_to_end(tmp_path):
    from prtt_addon.core.io.jobfile import save_scene
    from tests.scenes_util import floor_and_box
    save_scene(floor_and_box(res=8), tmp_path / "job.npz")
    r = py("-m", "prtt_addon", "bake-job", "job.npz", "--out", "o", "--rays", "8", "--bounces", "0",
           cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert "\r" not in r.stdout and lines[-1] == f"prtt: done: {tmp_path / 'o' / 'manifest.json'}"
    progress = [line for line in lines if "%" in line]
    assert progress and all(line.startswith("prtt: ") for line in progress)
    assert len(progress) == len(set(progress)), progress           # no stage twice
    assert any(line.startswith("prtt: trace [floor 1/2]") for line in progress), lines


@pytest.mark.blender
def test_blender_bake_progress_and_quiet(tmp_path):
    from tests import real_scenes as rs
    from tests.blender_util import addon_bpy
    bpy = addon_bpy()
    rs.floor(bpy, 4.0)
    rs.add_object(bpy, "Box", rs.cube_mesh(bpy, "box"), location=(0, 0, 0.5))
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    common = ["scene.blend", "--unwrap", "smart", "--resolution", "16", "--rays", "16", "--bounces", "0",
              "--no-save"]
    r = py("-m", "prtt_addon", "bake", *common, "--out", "t1", cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    lines = r.stdout.splitlines()
    progress = [line for line in lines if "%" in line]
    assert progress and len(progress) == len(set(progress)), lines    # each stage once, with its percentage
    assert any(line.startswith("prtt: trace [") for line in progress), lines
    assert lines[-1] == "PRTT: bake finished", lines
    assert (tmp_path / "t1" / "manifest.json").is_file()                # --out relative to the caller
    r = py("-m", "prtt_addon", "bake", *common, "--out", "t2", "--quiet", cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert r.stdout.splitlines() == ["PRTT: bake finished"], r.stdout
