"""Fuzzing the job format: every field of a small valid job made wrong in every
way we can think of (dtype, shape, counts declared in headers without the data
behind them, NaN/Inf, truncation, bogus JSON, absurd settings).

Each case must end in a clear error (exit 1, one ``error`` line naming the
problem, no traceback: no unexpected exception) within a few seconds and with
bounded memory, and nothing may be written. The cases run through
``worker.run_job`` in one child process (``DRIVER`` below), which measures
each case's time and peak RSS (VmHWM, reset per case through
/proc/self/clear_refs); a sample also goes through ``python -m
prtt_addon.worker`` itself, its peak RSS from os.wait4. The figures are
printed (pytest -s) and written to the test's tmp folder as fuzz_summary.json.
"""
import io
import json
import os
import re
import subprocess
import sys
import time
import zipfile

import numpy as np
import pytest

from prtt_addon.core.io.jobfile import MAX_MEMBERS, save_scene
from prtt_addon.core.model.scene import MAX_NAME_LENGTH
from tests.scenes_util import floor_and_box_with_every_part

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = dict(os.environ, PYTHONPATH=ROOT, PYTHONUNBUFFERED="1")
#: Limits every case must stay within.
MAX_SECONDS = 5.0
MAX_RSS_MB = 1024


class Lie:
    """A member whose .npy header declares ``shape`` and ``dtype`` but that holds
    only a few bytes: the data the header promises does not exist."""

    def __init__(self, shape, dtype="<f4"):
        self.shape, self.dtype = tuple(shape), np.dtype(dtype)


def write_npz(path, arrays: dict) -> None:
    """An .npz written member by member, so that members can lie (:class:`Lie`)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        for key, v in arrays.items():
            buf = io.BytesIO()
            if isinstance(v, Lie):
                np.lib.format.write_array_header_1_0(
                    buf, {"descr": np.lib.format.dtype_to_descr(v.dtype), "fortran_order": False,
                          "shape": v.shape})
                buf.write(b"\0" * 16)
            else:
                np.lib.format.write_array(buf, np.asanyarray(v), allow_pickle=False)
            z.writestr(key + ".npy", buf.getvalue())


def base_job(path) -> dict:
    """A small valid job with every optional part (normal map, materials, a
    texture); returns its arrays as a dict."""
    sc = floor_and_box_with_every_part(res=8)
    light = np.zeros((25, 3))
    light[0] = 1.0
    save_scene(sc, path, extra={"settings": {"rays": 8, "bounce_rays": 4},
                                "light": {"coeffs": light.tolist(), "description": "flat"}})
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


FLOAT_FIELDS = ("positions", "normals", "uvs", "nm_uvs", "tangents", "mat_uvs", "nm_strength", "nm_0", "tex_0")
INT_FIELDS = ("set_id", "object_id", "nm_index", "material_id", "set_resolution", "tex_count", "version")
TEXT_FIELDS = ("set_names", "object_names", "extra", "materials", "format")


def field_cases(base: dict):
    """(name, arrays) for every field x every way of being wrong."""
    for key in FLOAT_FIELDS:
        a = base[key]
        yield f"{key}: bool", dict(base, **{key: a.astype(bool)})
        yield f"{key}: text", dict(base, **{key: a.astype(str)})
        yield f"{key}: complex", dict(base, **{key: a.astype(np.complex64)})
        bad = a.astype(np.float64).copy()
        bad.reshape(-1)[0] = np.nan
        yield f"{key}: NaN", dict(base, **{key: bad})
        bad = a.astype(np.float64).copy()
        bad.reshape(-1)[-1] = -np.inf
        yield f"{key}: Inf", dict(base, **{key: bad})
        # Images may be (H, W) or (H, W, C): one axis more is wrong for them.
        wrong = a[None] if key.startswith(("nm_", "tex_")) else a[..., 0]
        yield f"{key}: wrong number of axes", dict(base, **{key: wrong})
        yield f"{key}: scalar", dict(base, **{key: np.float32(1.0)})
        yield f"{key}: 10^9 rows declared", dict(base, **{key: Lie((10 ** 9, *a.shape[1:]), a.dtype)})
    for key in INT_FIELDS:
        a = base[key]
        yield f"{key}: float", dict(base, **{key: a.astype(np.float64)})
        yield f"{key}: bool", dict(base, **{key: a.astype(bool)})
        yield f"{key}: text", dict(base, **{key: a.astype(str)})
        if a.ndim:
            yield f"{key}: 10^9 rows declared", dict(base, **{key: Lie((10 ** 9, *a.shape[1:]), a.dtype)})
            yield f"{key}: wrapping int64", dict(base, **{key: a.astype(np.int64) + (1 << 32) + 7})
            yield f"{key}: shape minus an axis", dict(base, **{key: a.reshape(-1)[:1].reshape(()) if a.ndim == 1
                                                         else a[..., 0]})
    for key in TEXT_FIELDS:
        yield f"{key}: integers", dict(base, **{key: np.arange(3)})
        yield f"{key}: 10^9 characters declared", dict(base, **{key: Lie(base[key].shape, f"<U{10 ** 9}")})
    yield "set_names: 10^9 names declared", dict(base, set_names=Lie((10 ** 9,), "<U8"))
    yield "object_names: 10^9 names declared", dict(base, object_names=Lie((10 ** 9,), "<U8"))
    yield "missing uvs", {k: v for k, v in base.items() if k != "uvs"}
    yield "missing nm_0", {k: v for k, v in base.items() if k != "nm_0"}
    yield "missing tex_0", {k: v for k, v in base.items() if k != "tex_0"}
    yield "no format", {k: v for k, v in base.items() if k != "format"}


def count_cases(base: dict):
    T = base["positions"].shape[0]
    yield "tex_count 10^9", dict(base, tex_count=np.array(10 ** 9))
    yield "tex_count -1", dict(base, tex_count=np.array(-1))
    yield "nm_strength with 10^6 entries", dict(base, nm_strength=np.ones(10 ** 6, np.float32))
    yield "normal map 10^6 x 10^6 declared", dict(base, nm_0=Lie((10 ** 6, 10 ** 6, 3)))
    yield "texture 10^6 x 10^6 x 3 declared", dict(base, tex_0=Lie((10 ** 6, 10 ** 6, 3)))
    yield "texture 20000 x 20000 declared", dict(base, tex_0=Lie((20000, 20000, 3)))
    yield "texture with 7 channels", dict(base, tex_0=np.zeros((4, 4, 7), np.float32))
    yield "set_resolution 10^6", dict(base, set_resolution=np.array([[10 ** 6, 8], [8, 8]]))
    yield "set_resolution 2^32 + 8 (wraps to 8)", dict(base, set_resolution=np.array([[(1 << 32) + 8, 8], [8, 8]]))
    yield f"set name of {MAX_NAME_LENGTH + 100} characters", dict(base, set_names=np.array(["floor", "b" * 300]))
    yield "set name with a NUL", dict(base, set_names=np.array(["floor", "b\x00x"]))
    yield "object name of 10^5 characters", dict(base, object_names=np.array(["o" * 10 ** 5, "p"]))
    yield "set_id 7", dict(base, set_id=np.full(T, 7, np.int32))
    yield "positions 1e300", dict(base, positions=base["positions"] * 1e300)
    yield "tex_0 header of 8 x 8 over 4 x 4 of data", dict(base, tex_0=_lying_member_of(base["tex_0"], (8, 8, 3)))
    yield "positions header of 20 triangles over 14 of data", dict(
        base, positions=_lying_member_of(base["positions"], (T + 6, 3, 3)))
    yield f"{MAX_MEMBERS + 1} archive members", dict(base, **{f"junk{i}": np.zeros(1) for i in range(MAX_MEMBERS + 1)})
    yield "structured dtype", dict(base, set_id=np.zeros(T, dtype=[("a", "<i4")]))


class _Raw:
    """A member given as raw .npy bytes (a header over someone else's data)."""

    def __init__(self, data: bytes):
        self.data = data


def _lying_member_of(a: np.ndarray, shape) -> _Raw:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": a.dtype.str, "fortran_order": False, "shape": shape})
    return _Raw(buf.getvalue() + a.tobytes())


def json_cases(base: dict):
    def extra(d):
        return dict(base, extra=np.array(json.dumps(d)))
    settings = json.loads(str(base["extra"]))["settings"]
    light = json.loads(str(base["extra"]))["light"]
    yield "extra: bogus JSON", dict(base, extra=np.array("{not json"))
    yield "extra: a list", dict(base, extra=np.array("[1, 2]"))
    yield "extra: nested 10^5 deep", dict(base, extra=np.array("[" * 100000 + "]" * 100000))
    yield "materials: bogus JSON", dict(base, materials=np.array("[{"))
    yield "materials: a dict", dict(base, materials=np.array("{}"))
    yield "materials: numbers", dict(base, materials=np.array("[1, 2]"))
    yield "materials: roughness 7", dict(base, materials=np.array(json.dumps([{"name": "m", "roughness": 7}])))
    yield "settings: a list", extra({"settings": [1]})
    yield "two 16384^2 sets at 16 bands (550 GB)", dict(
        extra({"settings": dict(settings, bands=16), "light": light}),
        set_resolution=np.array([[16384, 16384], [16384, 16384]]))
    for key, value in (("n_patterns", 10 ** 6), ("threads", 1000), ("rays", 10 ** 9), ("bands", 100),
                       ("seed", -1), ("seed", 2 ** 40), ("chunk_rays", 10 ** 12), ("dilate", 10 ** 6),
                       ("bounces", 1000), ("bounce_rays", 10 ** 9), ("min_rays", 10 ** 9),
                       ("adaptive_tol", 1e300), ("adaptive_tol", "0.1"), ("rays", 64.5), ("rays", True),
                       ("threads", -1), ("half", "yes"), ("sampler", 3), ("colour", 1)):
        yield f"settings: {key}={value!r}", extra({"settings": dict(settings, **{key: value}), "light": light})
    yield "light: coeffs (25, 2)", extra({"settings": settings, "light": {"coeffs": [[1.0, 2.0]] * 25}})
    yield "light: coeffs NaN", extra({"settings": settings, "light": {"coeffs": [[float("nan")] * 3] * 25}})
    yield "light: a string", extra({"settings": settings, "light": "sky"})
    yield "light: ragged", extra({"settings": settings, "light": {"coeffs": [[1, 2, 3], [1]]}})


def write_case(path, arrays: dict) -> None:
    if any(isinstance(v, _Raw) for v in arrays.values()):
        with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
            for key, v in arrays.items():
                if isinstance(v, _Raw):
                    z.writestr(key + ".npy", v.data)
                else:
                    buf = io.BytesIO()
                    np.lib.format.write_array(buf, np.asanyarray(v), allow_pickle=False)
                    z.writestr(key + ".npy", buf.getvalue())
        return
    write_npz(path, arrays)


def file_cases(folder, base_path):
    """Broken files: empty, truncated at several offsets, garbage, not a zip."""
    data = open(base_path, "rb").read()
    out = []
    empty = os.path.join(folder, "empty.npz")
    open(empty, "wb").close()
    out.append(("0-byte file", empty))
    for cut in (1, 10, 100, 1000, len(data) // 2, len(data) - 100, len(data) - 22, len(data) - 1):
        p = os.path.join(folder, f"cut{cut}.npz")
        with open(p, "wb") as f:
            f.write(data[:cut])
        out.append((f"truncated at {cut} of {len(data)} bytes", p))
    p = os.path.join(folder, "garbage.npz")
    with open(p, "wb") as f:
        f.write(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    out.append(("random bytes", p))
    p = os.path.join(folder, "flipped.npz")
    flipped = bytearray(data)
    for i in range(200, len(flipped) - 200, 997):       # corrupt the members, keep the directory
        flipped[i] ^= 0xFF
    with open(p, "wb") as f:
        f.write(bytes(flipped))
    out.append(("bytes flipped inside members", p))
    return out


# --- the driver: runs every case in-process in one child, measuring each -------------

DRIVER = r"""
import json, os, sys, threading, time
from prtt_addon.worker import run_job

def hwm_mb():
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024

def reset_hwm():
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False

cases = json.load(open(sys.argv[1]))
results = []
for name, path, out in cases:
    events = []
    reset_ok = reset_hwm()
    t = time.perf_counter()
    code = run_job(path, out, events.append, threading.Event())
    results.append({"name": name, "path": path, "code": code, "seconds": time.perf_counter() - t,
                    "rss_mb": hwm_mb(), "hwm_reset": reset_ok, "last": events[-1] if events else None,
                    "written": sorted(os.listdir(out)) if os.path.isdir(out) else []})
json.dump(results, open(sys.argv[2], "w"))
"""


def clear_message(r) -> str | None:
    """Why a case's outcome is not a clear error, or None."""
    last = r["last"] or {}
    if r["code"] != 1 or last.get("type") != "error":
        return f"exit {r['code']}, last event {last}"
    if "traceback" in last:
        return f"unexpected exception: {last['error']}: {last['message']}"
    if last["error"] not in ("SceneError", "ValueError", "MemoryLimitError"):
        return f"error class {last['error']}"
    if len(last["message"]) < 15:
        return f"message too short: {last['message']!r}"
    return None


def test_job_fuzz(tmp_path):
    base_path = str(tmp_path / "base.npz")
    base = base_job(base_path)
    cases = [("control: the valid job", base_path)]
    for i, (name, arrays) in enumerate([*field_cases(base), *count_cases(base), *json_cases(base)]):
        p = str(tmp_path / f"case{i}.npz")
        write_case(p, arrays)
        cases.append((name, p))
    cases += file_cases(str(tmp_path), base_path)
    spec = [(name, path, str(tmp_path / f"out{i}")) for i, (name, path) in enumerate(cases)]
    with open(tmp_path / "cases.json", "w") as f:
        json.dump(spec, f)
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", DRIVER, str(tmp_path / "cases.json"), str(tmp_path / "res.json")],
                       capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=600)
    wall = time.perf_counter() - t
    assert r.returncode == 0, r.stderr[-3000:]
    results = json.load(open(tmp_path / "res.json"))
    control, rest = results[0], results[1:]
    assert control["code"] == 0 and control["last"]["type"] == "done", control   # the harness can succeed
    problems = []
    for res in rest:
        why = clear_message(res)
        if why:
            problems.append(f"{res['name']}: {why}")
        if res["written"]:
            problems.append(f"{res['name']}: wrote {res['written']}")
        if res["seconds"] > MAX_SECONDS:
            problems.append(f"{res['name']}: took {res['seconds']:.1f} s")
        if res["rss_mb"] > MAX_RSS_MB:
            problems.append(f"{res['name']}: peak RSS {res['rss_mb']:.0f} MB")
    assert not problems, "\n".join(problems)
    by = {res["name"]: res["last"]["message"] for res in rest}
    # Spot checks of the wording: the field, the limit, the file.
    assert "set_id: expected integers, got float64" in by["set_id: float"]
    assert "tex_count: 1000000000 textures; must be 0..256" in by["tex_count 10^9"]
    assert "nm_strength: 1000000 normal maps; a job has at most 256" in by["nm_strength with 10^6 entries"]
    assert "tex_0: 1000000x1000000 pixels" in by["texture 10^6 x 10^6 x 3 declared"]
    assert "asks for 4294967304x8 texels" in by["set_resolution 2^32 + 8 (wraps to 8)"]
    assert f"at most {MAX_NAME_LENGTH} bytes" in by[f"set name of {MAX_NAME_LENGTH + 100} characters"]
    assert "n_patterns must be an integer 1..1024, got 1000000" in by["settings: n_patterns=1000000"]
    assert "threads must be an integer 0..256, got 1000" in by["settings: threads=1000"]
    assert re.search(r"case\d+.npz \(its arrays 0.00 GiB, the bake \d+\.\d+ GiB\) needs about \d+\.\d GiB but only",
                     by["two 16384^2 sets at 16 bands (550 GB)"])
    assert "tex_0: its header declares (8, 8, 3) float32 (768 bytes) but the archive member holds 192 bytes" \
        in by["tex_0 header of 8 x 8 over 4 x 4 of data"]
    for res in rest:
        if res["name"].startswith(("0-byte", "truncated", "random bytes", "bytes flipped")):
            assert res["path"] in res["last"]["message"], res
    assert "the file is empty (0 bytes)" in by["0-byte file"]
    summary = {"cases": len(rest), "max_seconds": max(r["seconds"] for r in rest),
               "max_rss_mb": max(r["rss_mb"] for r in rest), "hwm_reset": all(r["hwm_reset"] for r in rest),
               "wall_seconds": wall,
               "slowest": max(rest, key=lambda r: r["seconds"])["name"],
               "largest": max(rest, key=lambda r: r["rss_mb"])["name"]}
    (tmp_path / "fuzz_summary.json").write_text(json.dumps(summary, indent=1))
    print(f"\njob fuzz: {summary}")


@pytest.mark.parametrize("make", ["empty", "truncated", "lying texture", "huge settings"])
def test_worker_subprocess_on_hostile_jobs(tmp_path, make):
    """The same through ``python -m prtt_addon.worker``: exit 1 within seconds,
    an error line naming the file or field, bounded memory (peak RSS of the child)."""
    base_path = str(tmp_path / "base.npz")
    base = base_job(base_path)
    job = str(tmp_path / "job.npz")
    if make == "empty":
        open(job, "wb").close()
    elif make == "truncated":
        with open(job, "wb") as f:
            f.write(open(base_path, "rb").read()[:700])
    elif make == "lying texture":
        write_npz(job, dict(base, tex_0=Lie((10 ** 6, 10 ** 6, 3))))
    else:
        extra = json.loads(str(base["extra"]))
        extra["settings"].update(n_patterns=10 ** 6)
        write_npz(job, dict(base, extra=np.array(json.dumps(extra))))
    t = time.perf_counter()
    # The worker's own peak RSS, read from /proc/self/status (VmHWM) as it
    # exits: getrusage(RUSAGE_CHILDREN) would also count the pages a fork
    # copied from this test process before exec (~1.1 GB once bpy is loaded).
    wrapper = ("import runpy, sys\n"
               "sys.argv = ['prtt_addon.worker'] + sys.argv[1:]\n"
               "try:\n    runpy.run_module('prtt_addon.worker', run_name='__main__')\n"
               "finally:\n"
               "    hwm = [l for l in open('/proc/self/status') if l.startswith('VmHWM')][0]\n"
               "    sys.stderr.write('PEAK ' + hwm.split()[1] + '\\n')\n")
    p = subprocess.run([sys.executable, "-c", wrapper, job, str(tmp_path / "out")],
                       capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=60)
    stdout = p.stdout
    seconds = time.perf_counter() - t
    rss_mb = int(p.stderr.split("PEAK ")[-1].split()[0]) / 1024
    last = json.loads(stdout.splitlines()[-1])
    assert p.returncode == 1 and last["type"] == "error" and "traceback" not in last, stdout
    assert seconds < 10 and rss_mb < MAX_RSS_MB, (seconds, rss_mb)
    print(f"\nworker on {make}: {seconds:.2f} s, peak RSS {rss_mb:.0f} MB")
    want = {"empty": f"{job}: the file is empty (0 bytes)", "truncated": job,
            "lying texture": "tex_0: 1000000x1000000 pixels",
            "huge settings": "n_patterns must be an integer 1..1024, got 1000000"}[make]
    assert want in last["message"]
    assert not os.path.exists(tmp_path / "out")
