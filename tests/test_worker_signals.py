"""SIGTERM/SIGINT stop the worker within 2 s at every stage, exit 3, and leave
the previous outputs byte-identical with no temporaries (worker.Watchdog,
core/bake/pipeline/runner.py's cancel checks, core/base/atomic.py).

Each test starts ``python -m prtt_addon.worker`` on a job that spends a few
seconds in one stage (natural inputs: a 2M-triangle floor for loading, BVH and
the analytic test; a big atlas for the G-buffer; 1024 adaptive ray patterns
for the tables; many rays for tracing and bouncing; 16-band float textures
for writing), sends the signal as soon as the JSON progress shows that stage,
and times the exit. The seconds per stage are printed (pytest -s).
"""
import json
import os
import signal
import subprocess
import sys
import time

import pytest

from prtt_addon.core.io.jobfile import save_scene
from prtt_addon.dev.bench import meshgen as mg
from tests.scenes_util import floor_and_box, planar_uvs, scene_from

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = dict(os.environ, PYTHONPATH=ROOT, PYTHONUNBUFFERED="1")
#: The promise: exit within this many seconds of the signal.
EXIT_WITHIN = 2.0
TIMES = {}


def outputs(folder):
    return {p.name: p.read_bytes() for p in folder.iterdir()}


def previous_outputs(tmp_path):
    """A finished small bake in tmp/out; returns {file: bytes}."""
    save_scene(floor_and_box(res=16), tmp_path / "small.npz", extra={"settings": {"rays": 16}})
    r = subprocess.run([sys.executable, "-m", "prtt_addon.worker", str(tmp_path / "small.npz"),
                        str(tmp_path / "out")], capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    return outputs(tmp_path / "out")


def signal_at_stage(tmp_path, job, stage, *, sig=signal.SIGTERM, set_name=None, timeout=60):
    """Run the worker on ``job`` into tmp/out (which holds a previous bake),
    send ``sig`` when a progress event of ``stage`` (and ``set_name``) appears.
    Returns (seconds from the signal to the exit, exit code, events before the
    signal, events after it)."""
    before = previous_outputs(tmp_path)
    p = subprocess.Popen([sys.executable, "-m", "prtt_addon.worker", str(job), str(tmp_path / "out"), "--force"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV, cwd=ROOT)
    seen, t0 = [], None
    deadline = time.monotonic() + timeout
    try:
        for line in p.stdout:
            e = json.loads(line)
            seen.append(e)
            if e.get("type") == "progress" and e.get("stage") == stage and set_name in (None, e.get("set")):
                t0 = time.monotonic()
                p.send_signal(sig)
                break
            assert time.monotonic() < deadline, f"no {stage} stage within {timeout} s"
        assert t0 is not None, f"the worker never reached {stage}: {seen[-3:]}, {p.stderr.read()[-2000:]}"
        rest = p.stdout.read()
        code = p.wait(timeout=30)
        seconds = time.monotonic() - t0
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        p.stdout.close()
        p.stderr.close()
    after = [json.loads(line) for line in rest.splitlines() if line.strip()]
    assert outputs(tmp_path / "out") == before, "previous outputs changed or temporaries left"
    TIMES[stage] = round(seconds, 2)
    print(f"\n{stage}: exit {code} {seconds:.2f} s after SIGTERM; last events {[e.get('type') for e in after]}")
    return seconds, code, seen, after


def check_cancelled(seconds, code, after, stage):
    assert code == 3, (stage, code, after)
    assert seconds < EXIT_WITHIN, f"{stage}: exited {seconds:.2f} s after the signal"
    assert after and after[-1]["type"] == "cancelled", after
    assert not any(e.get("type") == "done" for e in after)


@pytest.fixture(scope="module")
def big_job(tmp_path_factory):
    """A 2M-triangle floor (330 MB job): ~0.4 s to load, ~2.5 s of BVH, seconds
    of analytic test on 2 cores."""
    d = tmp_path_factory.mktemp("big")
    f = mg.plane(4.0, subdiv=1000)
    sc = scene_from([("big", f, planar_uvs(f))], 64)
    save_scene(sc, d / "big.npz", extra={"settings": {"rays": 16, "bounces": 0}})
    return d / "big.npz"


@pytest.mark.parametrize("stage", ["load", "bvh", "analytic-test"])
def test_signal_while_loading_and_building(tmp_path, big_job, stage):
    seconds, code, seen, after = signal_at_stage(tmp_path, big_job, stage)
    check_cancelled(seconds, code, after, stage)
    if stage == "load":
        assert not any(e["type"] == "start" for e in seen + after)     # it was still loading


def test_signal_while_building_tables(tmp_path):
    """1024 patterns and four adaptive prefixes: ~8 s of ray tables on 2 cores."""
    save_scene(floor_and_box(res=16), tmp_path / "job.npz",
               extra={"settings": {"rays": 512, "n_patterns": 1024, "adaptive_tol": 0.01, "bounces": 0}})
    seconds, code, seen, after = signal_at_stage(tmp_path, tmp_path / "job.npz", "tables")
    check_cancelled(seconds, code, after, "tables")


def test_signal_while_building_a_gbuffer(tmp_path):
    """A 2048^2 set of 180K triangles: ~9 s of rasterising."""
    f = mg.plane(4.0, subdiv=300)
    small = mg.plane(1.0).transformed(translate=(10, 0, 0))
    sc = scene_from([("small", small, planar_uvs(small)), ("big", f, planar_uvs(f))], [8, 2048])
    save_scene(sc, tmp_path / "job.npz", extra={"settings": {"rays": 1, "bounces": 0}})
    seconds, code, seen, after = signal_at_stage(tmp_path, tmp_path / "job.npz", "gbuffer", set_name="big")
    check_cancelled(seconds, code, after, "gbuffer")


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_while_tracing(tmp_path, sig):
    save_scene(floor_and_box(res=256), tmp_path / "job.npz", extra={"settings": {"rays": 4096, "bounces": 0}})
    seconds, code, seen, after = signal_at_stage(tmp_path, tmp_path / "job.npz", "trace", sig=sig)
    check_cancelled(seconds, code, after, "trace")


def test_signal_while_bouncing(tmp_path):
    from tests.test_bounce import corner_scene, sky
    sc = corner_scene({"name": "w", "base_color": [0.5, 0.5, 0.5]})
    save_scene(sc, tmp_path / "job.npz", extra={"settings": {"rays": 16, "bounces": 2, "bounce_rays": 16384},
                                                "light": {"coeffs": sky().tolist(), "description": "sky"}})
    seconds, code, seen, after = signal_at_stage(tmp_path, tmp_path / "job.npz", "bounce")
    check_cancelled(seconds, code, after, "bounce")


def test_signal_while_writing(tmp_path):
    """16 bands of noisy float32 at 512^2: ~1.7 s per EXR (one native call; the
    watchdog ends it when the normal path cannot)."""
    save_scene(floor_and_box(res=512), tmp_path / "job.npz",
               extra={"settings": {"rays": 16, "bands": 16, "half": False, "estimator": "plain",
                                   "sampler": "random", "bounces": 0}})
    seconds, code, seen, after = signal_at_stage(tmp_path, tmp_path / "job.npz", "write")
    check_cancelled(seconds, code, after, "write")


def test_bake_job_cli_stops_on_sigint(tmp_path):
    """``python -m prtt_addon bake-job`` has the same watchdog: exit 3 within 2 s."""
    before = previous_outputs(tmp_path)
    save_scene(floor_and_box(res=256), tmp_path / "job.npz", extra={"settings": {"rays": 4096, "bounces": 0}})
    p = subprocess.Popen([sys.executable, "-m", "prtt_addon", "bake-job", str(tmp_path / "job.npz"),
                          "--out", str(tmp_path / "out")], stdout=subprocess.PIPE, text=True, env=ENV, cwd=ROOT)
    t0 = None
    for line in p.stdout:
        if line.startswith("prtt: trace"):
            t0 = time.monotonic()
            p.send_signal(signal.SIGINT)
            break
    rest = p.stdout.read()
    code = p.wait(timeout=30)
    p.stdout.close()
    assert t0 is not None and code == 3 and time.monotonic() - t0 < EXIT_WITHIN, (code, rest)
    assert "cancelled; previous outputs are intact" in rest
    assert outputs(tmp_path / "out") == before


def test_watchdog_ends_a_stuck_main_thread(tmp_path):
    """The backstop itself: a main thread that never checks the cancel flag (a
    long native call) is ended by the watchdog 1.2 s after the signal, exit 3,
    with this process's temporaries deleted and a 'cancelled' line."""
    probe = (
        "import os, sys, threading, time\n"
        "from prtt_addon import worker\n"
        "from prtt_addon.core.base import atomic\n"
        "cancel = threading.Event()\n"
        "w = worker.install_cancel_handlers(cancel, worker.JsonLines())\n"
        f"tmp = os.path.join({str(tmp_path)!r}, atomic.temp_prefix('stuck') + '0.exr')\n"
        "open(tmp, 'w').write('partial')\n"
        "atomic.register(tmp)\n"
        "print('{\"type\": \"ready\"}', flush=True)\n"
        "time.sleep(30)   # ignores cancel, like a native call would\n"
    )
    p = subprocess.Popen([sys.executable, "-c", probe], stdout=subprocess.PIPE, text=True, env=ENV, cwd=ROOT)
    assert json.loads(p.stdout.readline())["type"] == "ready"
    t0 = time.monotonic()
    p.send_signal(signal.SIGTERM)
    rest = p.stdout.read()
    code = p.wait(timeout=10)
    seconds = time.monotonic() - t0
    p.stdout.close()
    assert code == 3 and 1.1 < seconds < EXIT_WITHIN, (code, seconds)
    assert json.loads(rest.splitlines()[-1]) == {"type": "cancelled"}
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".prtt-tmp-")]
