"""``python -m prtt_addon.dev.bench memory``: peak memory and seconds against texels
and triangles, per stage and per process (issue #35).

Measured in this run, each bake and render in a fresh process:

* **the demo room** (21K triangles, the demo's glossy plank floor and
  furniture, Smart UV unwrapped once into a 1024² atlas as the demo does, the forest HDRI), baked with the
  defaults (transfer, per-vertex transfer, one relightable bounce) at each
  ``--sizes`` atlas (512² ... 4096²) by ``python -m prtt_addon bake`` (the
  Blender side: exports the job, runs the worker, saves the .blend), then
  previewed by ``python -m prtt_addon render`` at 320 x 180:

  - the worker's peak RSS per stage (the manifest's ``memory``: VmHWM reset
    at each stage, base/memory.StagePeaks) and its estimate before the bake
    (memory_check.check_memory), seconds per stage;
  - the Blender-side process's own peak RSS (VmHWM read in that process);
  - the render process's peak RSS and wall seconds, beside the bytes of the
    textures it draws (channels x texels x bytes a sample in the files), the
    bytes its textures take on the GPU, what it held before loading them and
    its own estimate of its peak (what ``prtt render`` prints);
* **room and bunnies** (1.27M triangles: the room plus 18 bunnies of 69K
  triangles, each its own 256² set) baked with ``bake-job`` at the room's
  1024² atlas, the same defaults;
* ``--memray``: the bake at the second largest size under memray, and the
  allocation sites alive at its peak (what the peak is made of).

Writes docs/bench/memory.json and docs/bench/memory.png (``--out`` elsewhere);
``python -m prtt_addon.dev.bench figures`` then writes docs/benchmarks.md's table.
``--quick``: 128² and 256², no bunnies (a smoke test).
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import subprocess
import sys
import tempfile
import time

from . import scene_library

OUT = os.path.join(scene_library.ROOT, "docs", "bench")

#: Runs a prtt_addon command line in this process, then prints the process's
#: own peak RSS (VmHWM: a child's ru_maxrss would include its parent's pages).
_CHILD = """
import json, sys, time
t = time.perf_counter()
if sys.argv[1] == "demo":        # the demo is its own entry point (not a command of the shipped CLI)
    from prtt_addon.dev.demo import main
    args = sys.argv[2:]
else:
    from prtt_addon.__main__ import main
    args = sys.argv[1:]
try:
    code = main(args)
except SystemExit as e:
    code = e.code
hwm = next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM:"))
print(json.dumps({"code": code, "peak_rss_kb": hwm, "seconds": time.perf_counter() - t}))
sys.exit(code or 0)
"""


def run_measured(args: list, *, cwd: str, timeout: float = 3600) -> dict:
    """Run ``python -m prtt_addon ARGS`` (``demo ARGS``: ``python -m prtt_addon.dev.demo ARGS``) in a
    child; {code, peak_rss_mb, seconds, tail}."""
    env = dict(os.environ, PYTHONPATH=scene_library.ROOT)
    r = subprocess.run([sys.executable, "-c", _CHILD, *args], capture_output=True, text=True, env=env,
                       cwd=cwd, timeout=timeout)
    last = r.stdout.strip().splitlines()[-1] if r.stdout.strip() else "{}"
    try:
        rec = json.loads(last)
    except json.JSONDecodeError:
        rec = {}
    if r.returncode != 0 or "peak_rss_kb" not in rec:
        raise RuntimeError(f"prtt_addon {' '.join(args)} failed ({r.returncode}): {(r.stderr or r.stdout)[-2000:]}")
    return {"code": rec["code"], "peak_rss_mb": rec["peak_rss_kb"] / 1024.0, "seconds": rec["seconds"],
            "stdout": r.stdout}


def texture_bytes(folder: str) -> dict:
    """{file: bytes} of the EXRs in ``folder`` as drawn: channels x texels x sample bytes (from headers)."""
    import OpenEXR
    out = {}
    for f in sorted(os.listdir(folder)):
        if not f.endswith(".exr") or f.startswith("."):
            continue
        with OpenEXR.File(os.path.join(folder, f), header_only=True) as ef:
            h = ef.header()
            (x0, y0), (x1, y1) = h["dataWindow"]
            texels = (x1 - x0 + 1) * (y1 - y0 + 1)
            # A PRTT texture's channels all have its storage's type (the header says which).
            out[f] = int(texels) * len(h["channels"]) * (2 if h.get("prtt_storage") == "half" else 4)
    return out


def demo_blend(folder: str, resolution: int = 1024) -> str:
    """The demo scene as `prtt demo --no-relight` makes it (Smart UV into a 1024² atlas, its default); its .blend."""
    d = os.path.join(folder, "demo")
    run_measured(["demo", "--out", d, "--resolution", str(resolution), "--no-relight", "--size", "160x90"],
                 cwd=folder)
    return os.path.join(d, "prtt_demo.blend")


def bake_size(blend: str, folder: str, size: int) -> dict:
    tex = os.path.join(folder, f"tex{size}")
    baked = os.path.join(folder, f"demo{size}.blend")
    side = run_measured(["bake", blend, "--out", tex, "--resolution", str(size), "--save-as", baked, "--force",
                         "-q"], cwd=folder)
    with open(os.path.join(tex, "manifest.json"), encoding="utf-8") as f:
        m = json.load(f)
    mem = m.get("memory") or {}
    tb = texture_bytes(tex)
    disk = sum(os.path.getsize(os.path.join(tex, f)) for f in os.listdir(tex) if not f.startswith("."))
    rec = {"size": size, "texels": m["totals"]["texels"], "atlas_texels": size * size,
           "triangles": None, "seconds": {k: round(v, 3) for k, v in m["seconds"].items()},
           "worker_peak_mb": mem.get("process_peak_rss_mb"), "stages_mb": mem.get("peak_rss_mb"),
           "estimate_mb": mem.get("estimate_mb"), "blender_side_peak_mb": round(side["peak_rss_mb"], 1),
           "bake_wall_s": round(side["seconds"], 2), "disk_bytes": disk, "texture_bytes": sum(tb.values())}
    r = run_measured(["render", baked, "--out", os.path.join(folder, f"r{size}.png"), "--size", "320x180"],
                     cwd=folder)
    rec["render_peak_mb"] = round(r["peak_rss_mb"], 1)
    rec["render_s"] = round(r["seconds"], 2)
    # What `prtt render` says of its memory (offscreen.check_memory): textures on the GPU, what it held
    # before loading them, its estimate of the peak.
    m = re.search(r"prtt: memory: (\d+) MiB of textures on the GPU, (\d+) MiB held before them, "
                  r"estimated peak (\d+) MiB", r["stdout"])
    if m is None:
        raise RuntimeError(f"prtt render did not report its memory: {r['stdout'][-1000:]}")
    rec["render_gpu_mb"], rec["render_base_mb"], rec["render_estimate_mb"] = (int(v) for v in m.groups())
    return rec


def bunnies_bake(folder: str, resolution: int) -> dict:
    from ...core.io.jobfile import save_scene
    sc = scene_library.render_scaling_scene(18, resolution=resolution)
    sc = scene_library.with_room_materials(sc)
    job = os.path.join(folder, "bunnies.npz")
    save_scene(sc, job)
    out = os.path.join(folder, "bunnies")
    r = run_measured(["bake-job", job, "--out", out, "--force", "-q", "--env", "forest", "--vertex"], cwd=folder)
    with open(os.path.join(out, "manifest.json"), encoding="utf-8") as f:
        m = json.load(f)
    mem = m.get("memory") or {}
    return {"scene": "room + 18 bunnies", "triangles": int(sc.n_triangles), "sets": len(sc.set_names),
            "texels": m["totals"]["texels"], "seconds": {k: round(v, 3) for k, v in m["seconds"].items()},
            "worker_peak_mb": mem.get("process_peak_rss_mb"), "stages_mb": mem.get("peak_rss_mb"),
            "estimate_mb": mem.get("estimate_mb"), "wall_s": round(r["seconds"], 2)}


_MEMRAY_CHILD = """
import sys, threading
from prtt_addon.worker import run_job
sys.exit(run_job(sys.argv[1], sys.argv[2], lambda e: None, threading.Event(), resolution=int(sys.argv[3]),
                 force=True))
"""


def memray_sites(blend_job: str, folder: str, size: int, top: int = 12) -> dict:
    """The bake of job ``blend_job`` at ``size`` under memray: its heap peak and
    the allocation sites alive then, grouped by their three innermost PRTT frames."""
    import collections

    from memray import FileReader
    path = os.path.join(folder, f"memray{size}.bin")
    env = dict(os.environ, PYTHONPATH=scene_library.ROOT)
    subprocess.run([sys.executable, "-m", "memray", "run", "-q", "-o", path, "-c", _MEMRAY_CHILD, blend_job,
                    os.path.join(folder, f"memray{size}"), str(size)], check=True, env=env, capture_output=True)
    reader = FileReader(path)
    by = collections.Counter()
    for rec in reader.get_high_watermark_allocation_records(merge_threads=True):
        st = rec.stack_trace(max_stacks=40)
        frames = [f"{fn} ({os.path.basename(fi)}:{ln})" for fn, fi, ln in st if "prtt_addon" in fi]
        by[" < ".join(frames[:3]) if frames else "outside PRTT (Python, numpy, Embree internals)"] += rec.size
    return {"size": size, "heap_peak_mb": round(reader.metadata.peak_memory / 2 ** 20, 1),
            "sites": [{"mb": round(v / 2 ** 20, 1), "where": k} for k, v in by.most_common(top)]}


def dask_bake(job: str, folder: str, size: int, workers: int = 2) -> dict:
    """The demo's worker job baked by ``bake-job --dask local:N`` at ``size``:
    the client's peak (this process: it plans, builds G-buffers, exit tables
    and writes) and estimate, each worker's measured peak and the largest
    estimate its checks made (the manifest's memory.dask_workers)."""
    out = os.path.join(folder, f"dask{size}")
    r = run_measured(["bake-job", job, "--out", out, "--resolution", str(size), "--force", "-q",
                      "--dask", f"local:{workers}"], cwd=folder)
    with open(os.path.join(out, "manifest.json"), encoding="utf-8") as f:
        mem = json.load(f)["memory"]
    w = mem.get("dask_workers") or {}
    return {"size": size, "workers": workers, "client_peak_mb": mem.get("process_peak_rss_mb"),
            "client_estimate_mb": mem.get("estimate_mb"), "client_stages_mb": mem.get("peak_rss_mb"),
            "worker_peaks_mb": sorted((w.get("peak_rss_mb") or {}).values()),
            "worker_estimate_mb": w.get("estimate_mb"), "wall_s": round(r["seconds"], 2)}


def export_job(blend: str, folder: str) -> str:
    """The worker's job file for ``blend`` (what `prtt bake` hands its worker), for memray."""
    code = (
        "import shutil, sys, bpy\n"
        "import prtt_addon\nprtt_addon.register()\n"
        f"bpy.ops.wm.open_mainfile(filepath={blend!r})\n"
        "from prtt_addon.blender.bake.run import prepare\n"
        f"p = prepare(bpy.context)\nshutil.move(p.job, {os.path.join(folder, 'demo_job.npz')!r})\n")
    env = dict(os.environ, PYTHONPATH=scene_library.ROOT)
    subprocess.run([sys.executable, "-c", code], check=True, env=env, capture_output=True, cwd=folder)
    return os.path.join(folder, "demo_job.npz")


def plot(rec: dict, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = rec["demo"]
    tx = [r["atlas_texels"] for r in rows]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    ax = axes[0]
    ax.loglog(tx, [r["worker_peak_mb"] for r in rows], "o-", label="bake worker (largest process)")
    ax.loglog(tx, [r["estimate_mb"] for r in rows], "x--", label="its estimate before the bake")
    ax.loglog(tx, [r["blender_side_peak_mb"] for r in rows], "s-", label="Blender side (bake command)")
    ax.loglog(tx, [r["render_peak_mb"] for r in rows], "^-", label="render (preview, 320x180)")
    ax.loglog(tx, [r.get("render_estimate_mb", float("nan")) for r in rows], "^--", alpha=0.6,
              label="render's estimate")
    ax.loglog(tx, [r["texture_bytes"] / 2 ** 20 for r in rows], ":", color="grey", label="texture bytes drawn")
    stages = sorted({k for r in rows for k in (r["stages_mb"] or {})})
    for s in stages:
        if s in ("trace", "gbuffer", "write transfer", "bounce", "write relight"):
            ax.loglog(tx, [(r["stages_mb"] or {}).get(s, float("nan")) for r in rows], lw=0.8, alpha=0.6,
                      label=f"worker stage: {s}")
    ax.set_xlabel("atlas texels")
    ax.set_ylabel("peak RSS, MiB")
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    ax = axes[1]
    ax.semilogx(tx, [1e6 * r["seconds"]["total"] / r["atlas_texels"] for r in rows], "o-",
                label="bake seconds per million atlas texels")
    ax.semilogx(tx, [1e6 * r["render_s"] / r["atlas_texels"] for r in rows], "^-",
                label="render seconds per million atlas texels")
    ax.set_xlabel("atlas texels")
    ax.set_ylabel("seconds per million texels")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    fig.suptitle("PRTT: memory and time against the atlas (demo room, defaults)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def print_table(rec: dict) -> None:
    print(f"{'atlas':>7} {'texels':>10} {'bake s':>7} {'us/texel':>8} {'worker MB':>9} {'estimate':>8} "
          f"{'Blender MB':>10} {'render MB':>9} {'its est.':>8} {'GPU MB':>7} {'render s':>8} {'textures MB':>11}")
    for r in rec["demo"]:
        print(f"{r['size']:>6}² {r['texels']:>10,} {r['seconds']['total']:>7.1f} "
              f"{1e6 * r['seconds']['total'] / r['atlas_texels']:>8.2f} {r['worker_peak_mb']:>9.0f} "
              f"{r['estimate_mb'] or 0:>8.0f} {r['blender_side_peak_mb']:>10.0f} {r['render_peak_mb']:>9.0f} "
              f"{r.get('render_estimate_mb', 0):>8.0f} {r.get('render_gpu_mb', 0):>7.0f} {r['render_s']:>8.1f} {r['texture_bytes'] / 2 ** 20:>11.0f}")
        print("        stages: " + ", ".join(f"{k} {v:.0f}" for k, v in (r["stages_mb"] or {}).items()))
    b = rec.get("bunnies")
    if b:
        print(f"{b['scene']}: {b['triangles']:,} triangles, {b['texels']:,} texels, {b['seconds']['total']:.1f} s, "
              f"worker peak {b['worker_peak_mb']:.0f} MB (estimate {b['estimate_mb'] or 0:.0f})")
    m = rec.get("memray")
    if m:
        print(f"memray at {m['size']}²: heap peak {m['heap_peak_mb']:.0f} MB, made of:")
        for s in m["sites"]:
            print(f"  {s['mb']:8.1f} MB  {s['where']}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench memory", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", default=None, help="atlas sizes, comma-separated (default 512,1024,2048,4096)")
    p.add_argument("--quick", action="store_true", help="128² and 256², no bunnies, no memray (smoke test)")
    p.add_argument("--no-bunnies", action="store_true", help="skip the 1.27M-triangle scene")
    p.add_argument("--memray", action="store_true", help="also attribute the peak at the second largest size")
    p.add_argument("--out", default=OUT, help="folder for memory.json and memory.png (default docs/bench)")
    p.add_argument("--dask-sizes", default=None,
                   help="atlas sizes baked on a local Dask cluster of 2 workers (default 1024,2048; 'none': skip)")
    p.add_argument("--dask-only", action="store_true",
                   help="only the Dask bakes, replacing the \"dask\" part of the record in --out")
    args = p.parse_args(argv)
    sizes = [] if args.dask_only else [
        int(s) for s in (args.sizes or ("128,256" if args.quick else "512,1024,2048,4096")).split(",")]
    dask_text = args.dask_sizes or ("none" if args.quick else "1024,2048")
    dask_sizes = [] if dask_text == "none" else [int(s) for s in dask_text.split(",")]
    command = " ".join(["python -m prtt_addon.dev.bench memory", *(argv if argv is not None else sys.argv[1:])])
    if args.dask_only:
        with open(os.path.join(args.out, "memory.json"), encoding="utf-8") as f:
            rec = json.load(f)
    else:
        rec = {"command": command, "date": datetime.date.today().isoformat(), "machine": machine(),
               "commit": commit(), "demo": []}
    with tempfile.TemporaryDirectory(prefix="prtt-memory-") as tmp:
        t = time.perf_counter()
        blend = demo_blend(tmp, 256 if args.quick else 1024)
        print(f"demo scene built and unwrapped in {time.perf_counter() - t:.1f} s")
        if dask_sizes:
            job = export_job(blend, tmp)
            rec["dask"] = {"command": command, "date": datetime.date.today().isoformat(), "commit": commit(),
                           "runs": []}
            for size in dask_sizes:
                d = dask_bake(job, tmp, size)
                rec["dask"]["runs"].append(d)
                print(f"{size}² on Dask local:2: client peak {d['client_peak_mb']:.0f} MB (estimate "
                      f"{d['client_estimate_mb']:.0f}), workers {', '.join(f'{v:.0f}' for v in d['worker_peaks_mb'])} "
                      f"MB (estimate {d['worker_estimate_mb']:.0f})", flush=True)
        for size in sizes:
            r = bake_size(blend, tmp, size)
            rec["demo"].append(r)
            print(f"{size}²: bake {r['seconds']['total']:.1f} s, worker peak {r['worker_peak_mb']:.0f} MB "
                  f"(estimate {r['estimate_mb'] or 0:.0f}), Blender side {r['blender_side_peak_mb']:.0f} MB, "
                  f"render {r['render_peak_mb']:.0f} MB in {r['render_s']:.1f} s", flush=True)
        if not (args.quick or args.no_bunnies or args.dask_only):
            rec["bunnies"] = bunnies_bake(tmp, 1024)
        if args.memray and len(sizes) > 1:
            rec["memray"] = memray_sites(export_job(blend, tmp), tmp, sorted(sizes)[-2])
    print_table(rec)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "memory.json"), "w", encoding="utf-8") as f:
        json.dump(rec, f, indent=1)
        f.write("\n")
    plot(rec, os.path.join(args.out, "memory.png"))
    print(f"wrote {os.path.join(args.out, 'memory.json')} and memory.png")
    return 0


def commit() -> str | None:
    r = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=scene_library.ROOT, capture_output=True, text=True)
    return r.stdout.strip() or None


def machine() -> dict:
    from .figures import machine as described  # CPU, cores, memory, OS, library versions
    return described()

if __name__ == "__main__":
    sys.exit(main())
