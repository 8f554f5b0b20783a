"""Outputs are verifiable and folders are not shared: the manifest's file_info
(size, sha256) catches missing, truncated and replaced outputs, which are
re-baked; stale temporaries of dead bakes are removed, a live bake's kept;
one bake per output folder (core/io/outdir.py, core/base/atomic.py, core/bake/pipeline/runner.py)."""
import json
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from prtt_addon.core.bake.pipeline.context import MANIFEST, BakeSettings
from prtt_addon.core.bake.pipeline.runner import bake_scene
from prtt_addon.core.base import atomic
from prtt_addon.core.base.errors import BakeError, Cancelled
from prtt_addon.core.io import exr_io
from prtt_addon.core.io.outdir import LOCK_FILE, FolderLock, file_info
from tests.scenes_util import floor_and_box

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = dict(os.environ, PYTHONPATH=ROOT)
ST = BakeSettings(rays=16, bounce_rays=8)


def sky():
    light = np.zeros((25, 3))
    light[0] = 2.0
    light[2] = 0.5
    return light


def bake(folder, **kw):
    return bake_scene(floor_and_box(res=16), folder, ST, light=sky(), **kw)


def files(folder):
    return {p.name: p.read_bytes() for p in folder.iterdir()}


def test_manifest_records_size_and_hash(tmp_path):
    m = bake(tmp_path)
    assert sorted(m["file_info"]) == sorted(m["files"])
    for name, info in m["file_info"].items():
        assert info == file_info(tmp_path / name)
        assert info["bytes"] == os.path.getsize(tmp_path / name)
    # The older keys are still there, unchanged.
    for key in ("files", "transfer_files", "input_hash", "settings_hash", "bounce", "sets"):
        assert key in m
    assert bake(tmp_path)["skipped"] is True                 # untouched: nothing to do


@pytest.mark.parametrize("damage", ["truncated", "missing", "same size, other bytes"])
def test_damaged_transfer_is_rebaked(tmp_path, damage):
    bake(tmp_path)
    good = files(tmp_path)
    target = tmp_path / "floor.transfer.exr"
    st = os.stat(target)
    if damage == "truncated":
        target.write_bytes(good["floor.transfer.exr"][:-100])
    elif damage == "missing":
        target.unlink()
    else:
        data = bytearray(good["floor.transfer.exr"])
        data[len(data) // 2] ^= 0xFF
        target.write_bytes(bytes(data))
        os.utime(target, ns=(st.st_atime_ns, st.st_mtime_ns))     # same size, same mtime
    m = bake(tmp_path)
    assert m["skipped"] is False and m["transfer_reused"] is False
    assert any("re-baking the transfer: floor.transfer.exr" in w for w in m["warnings"]), m["warnings"]
    after = files(tmp_path)
    assert after["floor.transfer.exr"] == good["floor.transfer.exr"]     # the bake is deterministic
    assert bake(tmp_path)["skipped"] is True


def test_damaged_bounce_rebakes_only_the_bounce(tmp_path):
    m = bake(tmp_path)
    bounce = m["bounce"]["files"][0]
    (tmp_path / bounce).write_bytes(b"")
    m = bake(tmp_path)
    assert m["skipped"] is False and m["transfer_reused"] is True
    assert any(f"re-baking the bounce textures: {bounce}: 0 bytes" in w for w in m["warnings"])
    assert m["file_info"][bounce] == file_info(tmp_path / bounce)
    assert bake(tmp_path)["skipped"] is True


def test_manifest_without_file_info_is_not_trusted(tmp_path):
    """A manifest of an older PRTT (no file_info) cannot prove its files: re-bake."""
    bake(tmp_path)
    man = json.loads((tmp_path / MANIFEST).read_text())
    del man["file_info"]
    (tmp_path / MANIFEST).write_text(json.dumps(man))
    m = bake(tmp_path)
    assert m["skipped"] is False
    assert any("older PRTT" in w for w in m["warnings"])
    assert "file_info" in json.loads((tmp_path / MANIFEST).read_text())


def dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_stale_temporaries_removed_live_ones_kept(tmp_path):
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        dead = dead_pid()
        names = {
            "dead": f".prtt-tmp-{dead}-floor.transfer-0.exr",
            "dead job": f".prtt-tmp-job-{dead}-0123456789ab.npz",
            "live": f".prtt-tmp-{live.pid}-floor.transfer-0.exr",
            "old, no pid": ".prtt-tmp-floor.transfer-abcd1234.exr",
            "fresh, no pid": ".prtt-tmp-box.transfer-abcd1234.exr",
        }
        for n in names.values():
            (tmp_path / n).write_bytes(b"partial")
        two_hours = time.time() - 7200
        os.utime(tmp_path / names["old, no pid"], (two_hours, two_hours))
        m = bake(tmp_path)
        left = set(os.listdir(tmp_path))
        assert names["live"] in left and names["fresh, no pid"] in left
        assert not {names["dead"], names["dead job"], names["old, no pid"]} & left
        assert any("removed 3 temporary file(s)" in w for w in m["warnings"]), m["warnings"]
    finally:
        live.kill()
        live.wait()


def test_temporaries_carry_the_pid(tmp_path):
    seen = []
    with atomic.atomic_write(tmp_path / "x.exr") as tmp:
        seen.append(os.path.basename(tmp))
        open(tmp, "w").close()
    assert atomic.temporary_pid(seen[0]) == os.getpid()
    assert atomic.temporary_pid(".prtt-tmp-job-123-abc.npz") == 123
    assert atomic.temporary_pid(".prtt-tmp-floor-abc.exr") is None


HOLD = """
import sys, time
from prtt_addon.core.io.outdir import FolderLock
lock = FolderLock(sys.argv[1], job=sys.argv[2], source="/scenes/a.blend").acquire()
print("locked", flush=True)
time.sleep(60)
"""


def test_second_bake_into_a_busy_folder_is_refused(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(out), "/jobs/first.npz"], stdout=subprocess.PIPE,
                              text=True, env=ENV, cwd=ROOT)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(BakeError, match=rf"in use by another bake \(pid {holder.pid} on .*, "
                                            rf"job /jobs/first.npz \(from /scenes/a.blend\), started "):
            bake(out)
        assert not (out / MANIFEST).exists()
    finally:
        holder.kill()
        holder.wait()
        holder.stdout.close()
    # Its process is gone: the kernel released the lock, its record is stale.
    m = bake(out, progress=None)
    assert m["skipped"] is False and not (out / LOCK_FILE).exists()


def test_a_dead_bakes_lock_is_taken_over(tmp_path):
    (tmp_path / LOCK_FILE).write_text(json.dumps({"pid": dead_pid(), "host": "here", "job": "/old.npz"}))
    events = []
    bake(tmp_path, progress=events.append)
    assert any(e.get("type") == "warning" and "took over the lock" in e["message"] for e in events)
    assert not (tmp_path / LOCK_FILE).exists()


def test_lock_released_on_every_exit_path(tmp_path):
    with pytest.raises(ValueError):                  # refused before the folder is touched
        bake_scene(floor_and_box(res=8), tmp_path, BakeSettings(rays=0))
    cancel = threading.Event()
    cancel.set()
    with pytest.raises(Cancelled):
        bake(tmp_path, cancel=cancel)
    assert not (tmp_path / LOCK_FILE).exists()
    with pytest.raises(BakeError, match="unknown texture sets"):
        bake(tmp_path, sets=["nope"])
    assert not (tmp_path / LOCK_FILE).exists()
    with FolderLock(tmp_path):                       # free again
        assert (tmp_path / LOCK_FILE).exists()
    assert not os.listdir(tmp_path)


def test_hashing_cost_of_a_1024_texture(tmp_path):
    """What verification costs: sha256 of a 1024^2, 25-channel half texture
    (noisy, so it compresses like a real one at low ray counts)."""
    data = np.random.default_rng(0).normal(0.5, 0.1, (1024, 1024, 25)).astype(np.float32)
    exr_io.write_sh_exr(tmp_path / "t.exr", data, kind="transfer")
    size = os.path.getsize(tmp_path / "t.exr")
    file_info(tmp_path / "t.exr")                   # page cache warm, as right after a bake
    t = time.perf_counter()
    for _ in range(5):
        file_info(tmp_path / "t.exr")
    seconds = (time.perf_counter() - t) / 5
    print(f"\nsha256 of a 1024^2 x 25 half EXR ({size / 1e6:.1f} MB): {seconds * 1000:.1f} ms, "
          f"{size / seconds / 1e9:.2f} GB/s")
    assert seconds < 1.0


def test_hostile_manifest_is_ignored_not_obeyed(tmp_path):
    """manifest.json is read from disk: a forged one cannot make the bake delete
    files outside the folder, nor crash it."""
    out = tmp_path / "out"
    out.mkdir()
    victim = tmp_path / "victim.bounce1.exr"
    victim.write_bytes(b"keep me")
    (out / MANIFEST).write_text(json.dumps({"files": ["../victim.bounce1.exr"], "sets": [1, "x"], "vertex": 3,
                                            "input_hash": 5, "file_info": []}))
    m = bake(out)
    assert m["skipped"] is False and victim.read_bytes() == b"keep me"
    (out / MANIFEST).write_text("[1, 2, 3]")
    assert bake(out)["skipped"] is False
