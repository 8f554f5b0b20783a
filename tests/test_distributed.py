"""The bake on a Dask cluster (core/bake/executors/dask_cluster.py, issue #17): the same
bits as the local bake, a lost worker costs only its chunks, a lost
scheduler is a clear error, cancellation stops the cluster, and every entry
point passes ``--dask`` through.

Clusters here are real: LocalCluster worker processes, and for the lost
scheduler a `dask scheduler` and `dask worker` started as separate
processes. Units are made small (UNIT_RAYS) so that a bake is dozens of
tasks and a fault lands in the middle of a pass.
"""
import dataclasses
import hashlib
import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import psutil
import pytest

from prtt_addon.core.bake.estimators.transfer import Chunk
from prtt_addon.core.bake.executors import dask_cluster as dd
from prtt_addon.core.bake.executors import dask_spec, dask_worker
from prtt_addon.core.bake.pipeline.context import BakeSettings
from prtt_addon.core.bake.pipeline.runner import bake_scene
from prtt_addon.core.base.errors import BakeError, Cancelled
from prtt_addon.core.base.memory import MemoryLimitError
from prtt_addon.core.io.jobfile import save_scene
from prtt_addon.core.light.envmap import environment_light
from prtt_addon.dev.bench import scene_library
from tests.scenes_util import floor_and_box

pytest.importorskip("distributed")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = dict(os.environ, PYTHONPATH=ROOT, PYTHONUNBUFFERED="1")
#: Manifest entries that record how long things took (they differ run to run),
#: and with them how many threads traced (the machine's or the cluster's).
TIMING_KEYS = ("seconds", "created", "rays_per_second", "memory")   # measured, not baked
EXECUTION_KEYS = TIMING_KEYS + ("threads",)


def files(folder) -> dict:
    """{name: sha256} of a bake's outputs (textures, vertex transfer, manifest aside)."""
    return {n: hashlib.sha256((folder / n).read_bytes()).hexdigest() for n in sorted(os.listdir(folder))
            if n.endswith((".exr", ".npz"))}


def without(x, keys=TIMING_KEYS):
    """The manifest without fields whose names contain one of ``keys`` (recursively)."""
    if isinstance(x, dict):
        return {k: without(v, keys) for k, v in x.items() if not any(t in k for t in keys)}
    if isinstance(x, list):
        return [without(v, keys) for v in x]
    return x


def manifest(folder, keys=TIMING_KEYS) -> dict:
    return without(json.loads((folder / "manifest.json").read_text()), keys)


def spawned_workers() -> list:
    """This process's LocalCluster worker processes (multiprocessing spawn children)."""
    out = []
    for c in psutil.Process().children(recursive=True):
        try:
            if "spawn_main" in " ".join(c.cmdline()):
                out.append(c)
        except psutil.Error:
            pass
    return out


def no_workers_left(timeout=10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not spawned_workers():
            return True
        time.sleep(0.2)
    return False


@pytest.fixture(scope="module")
def room():
    return scene_library.room_scene(64, atlas=False, materials=True), environment_light("forest", 5, 1.0, 0.0)


@pytest.fixture
def small_units(monkeypatch):
    monkeypatch.setattr(dd, "UNIT_RAYS", 1 << 15)


# --- parsing and planning (no cluster) -------------------------------------------------

def test_peer_timeout_from_the_environment_is_bounded():
    """A shared cluster may need longer than 3 s to open a connection under
    load: $PRTT_DASK_PEER_TIMEOUT sets it for a scheduler address, within
    0.5-300 s; anything else is refused naming the value. A local cluster
    keeps the default."""
    env = {"PRTT_DASK_PEER_TIMEOUT": "12.5"}
    assert dask_spec.parse_spec("tls://farm:8786", env).peer_timeout == 12.5
    assert dask_spec.parse_spec("tcp://farm:8786", {}).peer_timeout == dask_spec.PEER_CONNECT_TIMEOUT == 3.0
    assert dask_spec.parse_spec("local:2", env).peer_timeout == dask_spec.PEER_CONNECT_TIMEOUT
    for bad in ("0.1", "301", "nan", "inf", "-3", "soon"):
        with pytest.raises(BakeError, match=rf"PRTT_DASK_PEER_TIMEOUT must be seconds from 0.5 to 300, got '{bad}'"):
            dask_spec.parse_spec("tcp://farm:8786", {"PRTT_DASK_PEER_TIMEOUT": bad})


def test_spec_parsing_and_clear_errors(monkeypatch):
    assert dask_spec.parse_spec("local:3") == dask_spec.DaskSpec("local", 3)
    assert dask_spec.parse_spec("local").workers == max(1, os.cpu_count() or 1)
    assert dask_spec.parse_spec("tcp://farm:8786") == dask_spec.DaskSpec("address", address="tcp://farm:8786")
    assert dask_spec.parse_spec("env", {"DASK_SCHEDULER_ADDRESS": "tls://10.0.0.1:8786"}).address == "tls://10.0.0.1:8786"
    for bad, words in [("local:0", "1..256"), ("local:x", "local:N"), ("farm:8786", "tcp://HOST:PORT"),
                       ("tcp://", "tcp://HOST:PORT"), ("local:300", "1..256")]:
        with pytest.raises(BakeError, match=words):
            dask_spec.parse_spec(bad, {})
    with pytest.raises(BakeError, match="DASK_SCHEDULER_ADDRESS, which is not set"):
        dask_spec.parse_spec("env", {})


def test_units_cover_every_chunk_once_in_order():
    rng = np.random.default_rng(1)
    chunks = [Chunk(0, np.arange(int(n)), False) for n in rng.integers(1, 2048, 300)]
    for threads, cap in [(2, 1 << 23), (64, 1 << 23), (2, 1 << 12)]:
        units = dd.units_of(chunks, 256, threads, cap)
        flat = [c for u in units for c in u]
        assert len(flat) == len(chunks) and all(a is b for a, b in zip(flat, chunks))
        total = sum(c.idx.size for c in chunks) * 256
        limit = max(1, min(cap, total // (dd.UNITS_PER_THREAD * threads)))
        # A unit holds more than the limit only when it is one chunk.
        assert all(len(u) == 1 or sum(c.idx.size for c in u) * 256 <= limit for u in units)
        # So the pass is cut into at least total / limit tasks (fewer only where chunks exceed the limit).
        biggest = max(c.idx.size for c in chunks) * 256
        assert len(units) >= total // max(limit, biggest)
        if limit >= biggest:
            assert len(units) >= min(len(chunks), dd.UNITS_PER_THREAD * threads)
    assert dd.units_of([], 256, 2) == []


# --- real clusters ---------------------------------------------------------------------

@pytest.mark.parametrize("mode", ["baked", "relightable"])
def test_cluster_bake_is_bit_identical(tmp_path, room, small_units, mode):
    """Transfer with mips, vertex transfer and 2 bounce levels (baked or
    relightable) on a local cluster of 2 worker processes: the same files,
    byte for byte, and the same manifest but for its timing fields."""
    sc, light = room
    st = BakeSettings(rays=64, bounces=2, bounce_rays=32, bounce_tolerance=0.0, vertex_mode=True, mips=True,
                      bounce_mode=mode)
    bake_scene(sc, tmp_path / "local", st, light=light)
    events = []
    bake_scene(sc, tmp_path / "dask", st, light=light, dask="local:2", progress=events.append)
    a, b = files(tmp_path / "local"), files(tmp_path / "dask")
    assert len(a) >= 3 * 5 and a == b
    # "threads" counts the threads that traced: the local bake's, or the cluster's worker threads.
    assert manifest(tmp_path / "local", EXECUTION_KEYS) == manifest(tmp_path / "dask", EXECUTION_KEYS)
    assert any(e.get("type") == "info" and e["message"].startswith("Dask: 2 workers") for e in events)
    # The cluster's summary comes before "done", which stays the last event (the worker protocol).
    assert any("dask" in e for e in events) and events[-1]["type"] == "done"
    assert {e.get("stage") for e in events if e.get("type") == "progress"} >= {"trace", "vertex", "bounce"}
    # Each worker's measured peak is in the manifest, beside the estimate its checks made.
    mem = json.loads((tmp_path / "dask" / "manifest.json").read_text())["memory"]["dask_workers"]
    assert len(mem["peak_rss_mb"]) == 2 and mem["max_peak_rss_mb"] == max(mem["peak_rss_mb"].values())
    assert 0.8 <= mem["estimate_mb"] / mem["max_peak_rss_mb"] <= 1.25, mem
    assert no_workers_left()


def test_cluster_bake_under_load_is_bit_identical(tmp_path):
    """The issue's case (issue 50, defect 3: 1 of 3 cluster bakes differed by
    one unit in the last place on a machine at load 4-6): a floor and a
    sphere, 384², 256 rays, one relightable bounce, float storage, baked
    locally and then twice on `local:2` while two processes keep both cores
    busy. Every file byte for byte (measured on 2026-11-28 at load 5-6, with
    the suite running beside it: 6 of 6 cluster bakes identical)."""
    from prtt_addon.dev.bench import meshgen as mg
    sc = mg.assemble([("floor", mg.plane(4.0, subdiv=2)),
                      ("sphere", mg.uv_sphere(0.5, 48, 24).transformed(translate=(0.0, 0, 0.5)))],
                     resolution=384, atlas=False)
    light = environment_light("forest", 5)
    st = BakeSettings(rays=256, bounces=1, bounce_mode="relightable", half=False)
    bake_scene(sc, tmp_path / "local", st, light=light)
    want = files(tmp_path / "local")
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    try:
        for i in range(2):
            bake_scene(sc, tmp_path / f"dask{i}", st, light=light, dask="local:2")
            assert files(tmp_path / f"dask{i}") == want, i
    finally:
        for h in hogs:
            h.kill()
            h.wait(30)
    assert no_workers_left()


def test_cluster_bake_with_a_sun_is_bit_identical_under_load(tmp_path, room, small_units):
    """A bake with a sun (issue 48): masks at Sun Shadow Detail 2, refined in
    their penumbrae, and a relightable bounce that holds the sun's SH, baked
    locally and on `local:2` while two processes keep both cores busy: every
    file (the masks too) byte for byte."""
    import math

    from prtt_addon.core.light.sun import Sun
    sc, light = room
    sun = Sun(direction=(0.45, -0.3, 0.84), angle=math.radians(1.0), strength=3.0)
    st = BakeSettings(rays=64, bounces=1, bounce_rays=32, bounce_mode="relightable", sun_detail=2)
    bake_scene(sc, tmp_path / "local", st, light=light, sun=sun)
    want = files(tmp_path / "local")
    assert sum(n.endswith(".sun.exr") for n in want) == len(sc.set_names)
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    try:
        bake_scene(sc, tmp_path / "dask", st, light=light, sun=sun, dask="local:2")
        bake_scene(sc, tmp_path / "threads1", dataclasses.replace(st, threads=1), light=light, sun=sun)
    finally:
        for h in hogs:
            h.kill()
            h.wait(30)
    assert files(tmp_path / "dask") == want
    assert files(tmp_path / "threads1") == want
    assert no_workers_left()


def test_killed_worker_costs_only_its_chunks(tmp_path, room, small_units):
    """SIGKILL one of the two workers mid-transfer: Dask reruns its units on
    the other (and the restarted) worker; the outputs are still identical.
    The manifest too, but for timing and the count of threads that traced
    (the restarted worker's thread is a third one). With one worker, its
    death loses the only copy of the scene and points: they are sent again."""
    sc, light = room
    st = BakeSettings(rays=128, bounces=2, bounce_rays=32, bounce_tolerance=0.0, vertex_mode=True)
    bake_scene(sc, tmp_path / "local", st, light=light)

    def bake_killing_one(name, workers):
        """Bake on ``workers`` local workers, SIGKILL one of them 20 % into the
        transfer; returns the bake's events."""
        events, killed = [], []

        def kill_one(e):
            events.append(e)
            if e.get("type") == "progress" and e.get("stage") == "trace" and e.get("fraction", 0) > 0.2 \
                    and not killed:
                w = spawned_workers()
                assert len(w) == workers
                w[0].send_signal(signal.SIGKILL)
                killed.append(w[0].pid)

        bake_scene(sc, tmp_path / name, st, light=light, dask=f"local:{workers}", progress=kill_one)
        assert killed
        assert files(tmp_path / "local") == files(tmp_path / name)
        return events

    bake_killing_one("dask", 2)
    a, b = (manifest(tmp_path / d, EXECUTION_KEYS) for d in ("local", "dask"))
    assert a == b
    events = bake_killing_one("one", 1)
    assert any(e.get("type") == "warning" and "sending it again" in e["message"] for e in events)
    threads = [s["threads"] for s in json.loads((tmp_path / "dask" / "manifest.json").read_text())["sets"]]
    assert max(threads) >= 2


def test_cancel_stops_the_cluster_and_keeps_previous_outputs(tmp_path, room, small_units):
    sc, light = room
    out = tmp_path / "out"
    bake_scene(sc, out, BakeSettings(rays=32, bounces=1, bounce_rays=16), light=light)
    before = files(out)
    cancel = threading.Event()
    seen = {}

    def cancel_mid_trace(e):
        if e.get("type") == "progress" and e.get("stage") == "trace" and e.get("fraction", 0) > 0 and not seen:
            seen["t"] = time.monotonic()
            cancel.set()

    with pytest.raises(Cancelled):
        bake_scene(sc, out, BakeSettings(rays=512, seed=7), light=light, dask="local:2", cancel=cancel,
                   progress=cancel_mid_trace)
    assert time.monotonic() - seen["t"] < 5.0
    assert files(out) == before
    assert not [n for n in os.listdir(out) if n.startswith(".prtt-tmp-")]
    assert no_workers_left()


def test_worker_state_keeps_each_tasks_own_scene():
    """WorkerState under threads: every caller gets the BVH of its own scene
    token, each object is built once, old ones are evicted, a bake's slot
    objects are forgotten by its run id."""
    state = dask_worker.WorkerState()
    scenes_ = {f"s{i}": floor_and_box(res=8, box=(1.0, 1.0, 0.5 + i)) for i in range(3)}
    builds = []
    got = {}

    def look(token):
        rs, _ = state.ray_scene(scenes_[token], token)
        k = state.slot("points", f"run1-{token}", lambda: builds.append(token) or object())
        got.setdefault(token, set()).add((id(rs), id(k)))

    threads = [threading.Thread(target=look, args=(t,)) for t in ("s0", "s1", "s0", "s1") * 4]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(len(v) == 1 for v in got.values()) and sorted(builds) == ["s0", "s1"]
    bvh = {t: next(iter(v))[0] for t, v in got.items()}
    assert bvh["s0"] != bvh["s1"]
    look("s2")                                            # a third scene evicts the oldest
    assert len(state.scenes) == dask_worker.KEEP_SCENES and "s2" in state.scenes
    assert state.forget("run1-") == dask_worker.KEEP_PER_SLOT and not state.slots["points"]


def test_worker_memory_check_adds_up_each_hosts_workers():
    """Workers of one machine share its memory: their needs add up against
    the most limited one's; another host is checked on its own; a worker
    that knows no limit passes."""
    need = dask_worker.WorkerNeed(data=300 * 2 ** 20, chunks=40 * 2 ** 20, code=60 * 2 ** 20)
    MiB = 2 ** 20
    a = {"tcp://10.0.0.1:1": {"available": 2000 * MiB, "rss": 100 * MiB, "nthreads": 2, "numba": True},
         "tcp://10.0.0.1:2": {"available": 1900 * MiB, "rss": 100 * MiB, "nthreads": 1, "numba": False},
         "tcp://10.0.0.2:1": {"available": None, "rss": 50 * MiB, "nthreads": 4, "numba": True}}
    est = dask_worker.check_worker_memory("bounce", need, a)
    assert est == {"tcp://10.0.0.1:1": (100 + 300 + 80) * MiB, "tcp://10.0.0.1:2": (100 + 300 + 40 + 60) * MiB,
                   "tcp://10.0.0.2:1": (50 + 300 + 160) * MiB}
    # 380 + 400 = 780 MiB on 10.0.0.1 against 0.8 x 950: refused, naming the host and what to change.
    a["tcp://10.0.0.1:2"]["available"] = 950 * MiB
    with pytest.raises(MemoryLimitError, match=r"bounce pass needs about 0\.76 GiB on Dask host 10\.0\.0\.1 "
                                                  r"\(2 workers.*only 0\.93 GiB is available there.*previous "
                                                  r"outputs are intact.*--bounce-downscale"):
        dask_worker.check_worker_memory("bounce", need, a)
    assert dask_worker.host_of("tls://[::1]:8786") == "[::1]" and dask_worker.host_of("tcp://h:1") == "h"


@pytest.fixture
def external_cluster(tmp_path):
    """A `dask scheduler` process and a `dask worker` process with 2 threads;
    yields (address, scheduler process)."""
    sfile = tmp_path / "scheduler.json"
    logs = {name: open(tmp_path / f"{name}.log", "w") for name in ("scheduler", "worker")}
    sched = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                              "--port", "0", "--scheduler-file", str(sfile), "--no-dashboard"],
                             env=ENV, stdout=logs["scheduler"], stderr=subprocess.STDOUT)
    worker = None
    try:
        deadline = time.monotonic() + 60
        while not (sfile.exists() and sfile.stat().st_size) and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(0.3)
        addr = json.loads(sfile.read_text())["address"]
        # Dask's own reactions to a memory limit (spill, pause, restart) off: a
        # test gives the worker a limit to see PRTT's check, not Dask's.
        quiet = {f"DASK_DISTRIBUTED__WORKER__MEMORY__{k}": "False" for k in ("TARGET", "SPILL", "PAUSE", "TERMINATE")}
        worker = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", addr, "--nthreads", "2",
                                   "--nworkers", "1", "--no-dashboard"], env=dict(ENV, **quiet),
                                  stdout=logs["worker"], stderr=subprocess.STDOUT)
        yield addr, sched
    finally:
        for p in (sched, worker):
            if p is not None:
                p.kill()
                p.wait(30)
        for f in logs.values():
            f.close()


def test_worker_memory_limit_refuses_a_pass_it_cannot_fit(tmp_path, external_cluster):
    """A worker whose ``--memory-limit`` leaves ~100 MB (set on the running
    worker, the limit a user gives `dask worker`): the scene fits, the
    transfer pass of a 1024² set (its points and a ray chunk per thread, ~170
    MB) does not. The bake is refused before the pass is sent, naming the
    worker's host; the previous outputs are intact and nothing is staged."""
    import distributed
    addr, _ = external_cluster
    sc = floor_and_box(res=1024)
    out = tmp_path / "out"
    bake_scene(floor_and_box(res=64), out, BakeSettings(rays=8, bounces=0))
    before, names = files(out), sorted(os.listdir(out))
    with distributed.Client(addr, set_as_default=False) as c:
        c.wait_for_workers(1, timeout=60)
        rss = max(m["rss"] for m in c.run(dask_worker.worker_memory).values())
        c.run(lambda dask_worker, limit=rss + 100 * 2 ** 20: setattr(dask_worker.memory_manager, "memory_limit",
                                                                      limit))
        with pytest.raises(MemoryLimitError, match=r"the transfer pass needs about .* on Dask host 127\.0\.0\.1 "
                                                      r".*only 0\.\d+ GiB is available there.*previous outputs are intact"):
            bake_scene(sc, out, BakeSettings(rays=64, bounces=0), dask=addr)
        assert max(m["peak"] for m in c.run(dask_worker.worker_memory).values()) < rss + 100 * 2 ** 20
    assert files(out) == before and sorted(os.listdir(out)) == names


def test_a_farm_lets_go_of_each_bake(tmp_path, room, external_cluster):
    """Two bakes in a row on a running cluster (issue 50, defect 2): no ERROR
    in the scheduler's or the worker's log (the broadcast that dropped a bake
    was refused on every worker: "Combination not supported"), nothing of a
    bake left in the worker, its memory back to where it was after the first
    (the first bake's imports, Embree and BLAS stay: measured once)."""
    import distributed
    addr, _ = external_cluster
    sc, light = room
    st = BakeSettings(rays=64, bounces=1, bounce_rays=32)
    with distributed.Client(addr, set_as_default=False) as c:
        c.wait_for_workers(1, timeout=60)
        idle = c.run(dask_worker.worker_memory)
        after = []
        for i in range(3):
            bake_scene(sc, tmp_path / f"bake{i}", st, light=light, dask=addr)
            after.append(next(iter(c.run(dask_worker.worker_memory).values())))
    print("idle", idle, "after", after)
    assert all(a["held"] == {"objects": 0, "scenes": 0} for a in after), after
    # the second and third bakes hold nothing more than the first left behind
    assert max(a["rss"] for a in after[1:]) <= after[0]["rss"] + 40 * 2 ** 20, after
    time.sleep(1.0)
    for name in ("scheduler", "worker"):
        text = (tmp_path / f"{name}.log").read_text()
        assert " - ERROR - " not in text and "Combination not supported" not in text, text[-3000:]


def test_shared_cluster_with_threaded_workers(tmp_path, room, small_units, external_cluster):
    """A running scheduler and a worker with 2 threads (tasks of a pass run
    side by side in one process): two bakes of two scenes, one after the
    other on the same cluster, each equal to its local bake."""
    addr, _ = external_cluster
    sc, light = room
    st = BakeSettings(rays=64, bounces=1, bounce_rays=32, bounce_tolerance=0.0)
    for name, scene in (("room", sc), ("box", floor_and_box(res=64))):
        bake_scene(scene, tmp_path / f"{name}-local", st, light=light)
        bake_scene(scene, tmp_path / f"{name}-dask", st, light=light, dask=addr)
        assert files(tmp_path / f"{name}-local") == files(tmp_path / f"{name}-dask")


@pytest.mark.parametrize("when", ["mid-pass", "between-passes"])
def test_lost_scheduler_is_a_clear_error(tmp_path, monkeypatch, external_cluster, when):
    """A scheduler process killed mid-bake: BakeError naming it, within
    seconds, previous outputs intact. Between passes (the transfer traced, the
    bounce not yet sent) a scatter to the dead scheduler waited out Dask's 20 s
    connect timeout (CI, 2026-11-24; 4 of 4 before the mend)."""
    monkeypatch.setattr(dd, "UNIT_RAYS", 1 << 15)
    addr, sched = external_cluster
    sc = floor_and_box(res=128)
    out = tmp_path / "out"
    bake_scene(sc, out, BakeSettings(rays=16))
    before = files(out)
    killed = {}

    stages = []

    def kill_scheduler(e):
        if e.get("type") != "progress" or killed:
            return
        stages.append(e.get("stage"))
        if (e.get("stage") == "trace" and 0 < e.get("fraction", 0) < 1) if when == "mid-pass" else \
                ("trace" in stages and e.get("stage") != "trace"):
            killed["t"] = time.monotonic()
            sched.kill()
            sched.wait()        # dead before the bake's next call to it (else racing its exit)

    with pytest.raises(BakeError, match=f"lost the Dask scheduler at {addr}.*previous outputs are intact"):
        bake_scene(sc, out, BakeSettings(rays=2048, seed=3), dask=addr, progress=kill_scheduler)
    # Dask cancels every future when the connection breaks: the bake ends at once.
    assert killed, stages
    assert time.monotonic() - killed["t"] < 5
    assert files(out) == before


def test_bad_cluster_inputs_are_clear_errors(tmp_path, monkeypatch):
    sc = floor_and_box(res=16)
    st = BakeSettings(rays=8, bounces=0)
    monkeypatch.setattr(dd, "CONNECT_TIMEOUT", 1.0)
    t = time.monotonic()
    with pytest.raises(BakeError, match="cannot use the Dask scheduler at tcp://127.0.0.1:9"):
        bake_scene(sc, tmp_path / "a", st, dask="tcp://127.0.0.1:9")
    assert time.monotonic() - t < 30
    # A worker running other code than the client fails the bake, not its bits.
    monkeypatch.setattr(dask_worker, "_IDENTITY", "0" * 64)
    with pytest.raises(BakeError, match="runs other PRTT code"):
        bake_scene(sc, tmp_path / "b", st, dask="local:1")
    monkeypatch.setattr(dask_worker, "_IDENTITY", None)
    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(BakeError, match="optional packages dask and distributed"):
        bake_scene(sc, tmp_path / "c", st, dask="local:1")
    assert not (tmp_path / "c" / "manifest.json").exists()
    assert no_workers_left()


# --- the command lines -----------------------------------------------------------------

def test_bake_job_dask_option_end_to_end(tmp_path):
    """``bake-job --dask local:2`` equals ``bake-job``; a bad value is a usage
    error; SIGTERM mid-trace exits 3 within 2 s and leaves no worker process."""
    job = tmp_path / "job.npz"
    save_scene(floor_and_box(res=64), job, extra={"settings": {"rays": 64, "bounces": 0}})
    cmd = [sys.executable, "-m", "prtt_addon", "bake-job", str(job), "-q"]
    r1 = subprocess.run(cmd + ["--out", str(tmp_path / "local")], capture_output=True, text=True, env=ENV,
                        cwd=ROOT, timeout=300)
    r2 = subprocess.run(cmd + ["--out", str(tmp_path / "dask"), "--dask", "local:2"], capture_output=True,
                        text=True, env=ENV, cwd=ROOT, timeout=300)
    assert r1.returncode == 0 and r2.returncode == 0, r1.stderr + r2.stderr
    assert files(tmp_path / "local") == files(tmp_path / "dask")
    assert "Traceback" not in r2.stderr
    bad = subprocess.run(cmd + ["--out", str(tmp_path / "x"), "--dask", "local:0"], capture_output=True,
                         text=True, env=ENV, cwd=ROOT, timeout=120)
    assert bad.returncode == 2 and "--dask local:N needs N = 1..256" in bad.stderr
    save_scene(floor_and_box(res=256), job, extra={"settings": {"rays": 4096, "bounces": 0}})
    p = subprocess.Popen([sys.executable, "-m", "prtt_addon.worker", str(job), str(tmp_path / "local"), "--force",
                          "--dask", "local:2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env=ENV, cwd=ROOT)
    kids, t0 = [], None
    for line in p.stdout:
        e = json.loads(line)
        if e.get("type") == "progress" and e.get("stage") == "trace" and e.get("fraction", 0) > 0:
            kids = [c for c in psutil.Process(p.pid).children(recursive=True)]
            t0 = time.monotonic()
            p.send_signal(signal.SIGTERM)
            break
    p.communicate(timeout=60)
    assert t0 is not None and p.returncode == 3 and time.monotonic() - t0 < 2.0
    assert len(kids) >= 2
    time.sleep(1.0)
    assert not [k for k in kids if k.is_running() and k.status() != psutil.STATUS_ZOMBIE]
    assert files(tmp_path / "local") == files(tmp_path / "dask")


# The baked case is slow-marked for CI time (31 s): the relightable one is the
# issue's case, and tests/test_determinism.py checks both modes' order in-process.
@pytest.mark.parametrize("mode, half", [pytest.param("baked", True, marks=pytest.mark.slow), ("relightable", False)])
def test_cluster_bake_does_not_depend_on_the_order_units_finish(tmp_path, room, small_units, monkeypatch, mode,
                                                                half):
    """Issue 38: the client handles the units of every pass in a forced,
    shuffled order (all of a pass's units finish first, then are handed over
    in a seeded random order, twice with different seeds): the files stay the
    local bake's, byte for byte."""
    import random

    import distributed
    sc, light = room
    st = BakeSettings(rays=64, bounces=1, bounce_rays=32, bounce_tolerance=0.0, bounce_mode=mode, half=half)
    bake_scene(sc, tmp_path / "local", st, light=light)
    real_wait = distributed.wait
    for seed in (1, 2):
        rng = random.Random(seed)
        seen = []

        def shuffled_wait(futures, timeout=None, return_when="ALL_COMPLETED", rng=rng, seen=seen):
            done, _ = real_wait(futures, return_when="ALL_COMPLETED")
            done = sorted(done, key=lambda f: f.key)
            rng.shuffle(done)
            seen.append([f.key for f in done])
            return done, set()

        monkeypatch.setattr(distributed, "wait", shuffled_wait)
        out = tmp_path / f"dask{seed}"
        bake_scene(sc, out, st, light=light, dask="local:2")
        monkeypatch.setattr(distributed, "wait", real_wait)
        assert any(len(keys) > 2 and keys != sorted(keys, key=lambda k: int(k.rsplit("-", 1)[1]))
                   for keys in seen), seen                      # the order was truly not the submission order
        assert files(tmp_path / "local") == files(out)
    assert no_workers_left()
