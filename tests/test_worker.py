"""The worker as a plain command-line program, and ``python -m prtt_addon bake-job``."""
import json
import os
import signal
import subprocess
import sys

import pytest

from prtt_addon.core.io.jobfile import save_scene
from tests.scenes_util import floor_and_box

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = dict(os.environ, PYTHONPATH=ROOT, PYTHONUNBUFFERED="1")


def run_worker(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "prtt_addon.worker", *map(str, args)],
                          capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=timeout)


def events(stdout):
    return [json.loads(line) for line in stdout.splitlines() if line.strip()]


def test_worker_streams_json_and_finishes(tmp_path):
    save_scene(floor_and_box(res=16), tmp_path / "job.npz", extra={"settings": {"rays": 32}})
    r = run_worker(tmp_path / "job.npz", tmp_path / "out")
    assert r.returncode == 0, r.stderr
    ev = events(r.stdout)
    assert ev[0] == {"type": "progress", "stage": "load", "fraction": 0.0}    # headers checked, loading
    assert ev[1]["type"] == "start" and ev[1]["sets"] == ["floor", "box"]
    assert ev[1]["settings"]["rays"] == 32
    stages = {e["stage"] for e in ev if e["type"] == "progress"}
    assert {"bvh", "gbuffer", "trace"} <= stages
    assert all(0.0 <= e["fraction"] <= 1.0 for e in ev if e["type"] == "progress")
    assert ev[-1]["type"] == "done" and ev[-1]["skipped"] is False
    assert os.path.isfile(ev[-1]["manifest"])
    again = events(run_worker(tmp_path / "job.npz", tmp_path / "out").stdout)
    assert again[-1] == {"type": "done", "skipped": True, "manifest": ev[-1]["manifest"]}


def test_worker_reports_bad_input(tmp_path):
    r = run_worker(tmp_path / "missing.npz", tmp_path / "out")
    assert r.returncode == 1
    ev = events(r.stdout)
    assert ev[-1]["type"] == "error" and ev[-1]["error"] == "SceneError"
    assert "no such job/scene file" in ev[-1]["message"]
    save_scene(floor_and_box(res=8), tmp_path / "job.npz", extra={"settings": {"rays": -3}})
    r = run_worker(tmp_path / "job.npz", tmp_path / "out")
    assert r.returncode == 1 and "rays must be an integer 1..65536, got -3" in events(r.stdout)[-1]["message"]
    save_scene(floor_and_box(res=8), tmp_path / "job2.npz", extra={"settings": {"colour": 1}})
    r = run_worker(tmp_path / "job2.npz", tmp_path / "out")
    assert r.returncode == 1 and "unknown bake settings" in events(r.stdout)[-1]["message"]
    assert not os.path.exists(tmp_path / "out") or not os.listdir(tmp_path / "out")
    r = run_worker()
    assert r.returncode == 2


def outputs(folder, staged: bool = True):
    """{name: bytes} of a bake folder's files; staged=False leaves out the
    temporaries and the (unlocked) lock file a killed worker could not clean up."""
    return {p.name: p.read_bytes() for p in folder.iterdir()
            if staged or not (p.name.startswith(".prtt-tmp-") or p.name == ".prtt-lock")}


def previous_bake_and_long_job(tmp_path):
    """A finished small bake in tmp/out (returned as {file: bytes}) and a running
    worker on a long job writing to the same folder."""
    save_scene(floor_and_box(res=16), tmp_path / "small.npz", extra={"settings": {"rays": 16}})
    assert run_worker(tmp_path / "small.npz", tmp_path / "out").returncode == 0
    before = outputs(tmp_path / "out")
    save_scene(floor_and_box(res=256), tmp_path / "big.npz", extra={"settings": {"rays": 4096}})
    p = subprocess.Popen([sys.executable, "-m", "prtt_addon.worker", str(tmp_path / "big.npz"),
                          str(tmp_path / "out")], stdout=subprocess.PIPE, text=True, env=ENV, cwd=ROOT)
    return before, p


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_worker_cancels_cleanly_on_signal(tmp_path, sig):
    before, p = previous_bake_and_long_job(tmp_path)
    seen = []
    for line in p.stdout:
        seen.append(json.loads(line))
        if seen[-1].get("stage") == "trace":
            p.send_signal(sig)
            break
    rest = p.stdout.read()
    code = p.wait(timeout=60)
    p.stdout.close()
    assert code == 3
    assert events(rest)[-1]["type"] == "cancelled"
    assert outputs(tmp_path / "out") == before


def test_worker_killed_leaves_previous_outputs(tmp_path):
    before, p = previous_bake_and_long_job(tmp_path)
    for line in p.stdout:
        if json.loads(line).get("stage") == "trace":
            p.kill()
            break
    p.wait(timeout=30)
    p.stdout.close()
    assert outputs(tmp_path / "out", staged=False) == before
    # The next bake takes the dead bake's lock over and removes its temporaries.
    r = run_worker(tmp_path / "small.npz", tmp_path / "out", "--force")
    assert r.returncode == 0, r.stdout
    warnings = [e["message"] for e in events(r.stdout) if e["type"] == "warning"]
    assert any(f"took over the lock of a bake that is gone (pid {p.pid})" in w for w in warnings), warnings
    assert sorted(outputs(tmp_path / "out")) == sorted(before)


def test_bake_job_cli_overrides(tmp_path):
    save_scene(floor_and_box(res=16), tmp_path / "job.npz", extra={"settings": {"rays": 32}})
    r = subprocess.run([sys.executable, "-m", "prtt_addon", "bake-job", str(tmp_path / "job.npz"),
                        "--out", str(tmp_path / "o"), "--rays", "48", "--resolution", "24",
                        "--float", "--bands", "3", "--dilate", "1", "--vertex"],
                       capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "done:" in r.stdout
    man = json.loads((tmp_path / "o" / "manifest.json").read_text())
    assert man["settings"]["rays"] == 48 and man["settings"]["bands"] == 3
    assert man["settings"]["half"] is False and man["sets"][0]["resolution"] == [24, 24]
    assert "floor.vertex.npz" in man["files"]
    bad = subprocess.run([sys.executable, "-m", "prtt_addon", "bake-job", str(tmp_path / "job.npz"),
                          "--out", str(tmp_path / "o2"), "--resolution", "0"],
                         capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=60)
    assert bad.returncode == 2 and "--resolution 0 is out of range: it must be 1..16384" in bad.stderr
    for option, value, message in (("--env-strength", "-1", "is out of range: it must be > 0 and <= 1000000"),
                                   ("--env-strength", "inf", "is not a finite number: it must be > 0"),
                                   ("--threads", "1000", "is out of range: it must be 0..256"),
                                   ("--rays", "1e9", "is not an integer: it must be 1..65536"),
                                   ("--bands", "17", "is out of range: it must be 1..16")):
        bad = subprocess.run([sys.executable, "-m", "prtt_addon", "bake-job", str(tmp_path / "job.npz"),
                              "--out", str(tmp_path / "o3"), option, value],
                             capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=60)
        assert bad.returncode == 2 and f"error: {option} {value} {message}" in bad.stderr, (option, bad.stderr)
    assert not os.path.exists(tmp_path / "o3")


def test_worker_bakes_bounces_with_the_jobs_light(tmp_path):
    from tests.test_bounce import corner_scene, sky
    sc = corner_scene({"name": "w", "base_color": [0.5, 0.5, 0.5]})
    save_scene(sc, tmp_path / "job.npz", extra={"settings": {"rays": 32, "bounces": 1, "bounce_rays": 16,
                                                                     "bounce_mode": "baked"},
                                                "light": {"coeffs": sky().tolist(), "description": "sky"}})
    r = run_worker(tmp_path / "job.npz", tmp_path / "out")
    assert r.returncode == 0, r.stderr
    ev = events(r.stdout)
    assert ev[1]["type"] == "start" and ev[1]["light"] == "sky"
    assert any(e.get("stage") == "bounce" for e in ev)
    man = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert "floor.bounce1.exr" in man["files"]
    save_scene(sc, tmp_path / "bad.npz", extra={"light": {"coeffs": [[1.0, 2.0]]}})
    r = run_worker(tmp_path / "bad.npz", tmp_path / "out2")
    assert r.returncode == 1 and "coeffs must be (K, 3)" in events(r.stdout)[-1]["message"]

