"""``python -m prtt_addon.dev.bench sweep``: run time against error, and cost against size.

Everything is measured in this run on this machine and written to
``docs/bench/`` (CSV per sweep, PNG plots, ``sweep_summary.json``):

* **rays** (16 ... 4096 per texel) x **strategy** on the room-class scene
  (512^2 atlas, 84K texels, 5 bands): uniform-hemisphere Monte Carlo, cosine-weighted,
  stratified, Owen-scrambled Sobol' with the balanced estimator (PRTT's
  default), the default without the analytic unoccluded path, and adaptive
  sampling (tolerance sweep, up to 4096 rays). Error: relative RMSE of the
  transfer texels against a converged reference of the same scene (65536
  stratified rays per texel, 8 bands, cached in .cache/bench), and relative
  RMSE of the TPFL preview image against the preview rendered from the
  reference textures. -> rays.csv, error_vs_seconds.png (Pareto frontier).
* **resolution** 128^2 ... 2048^2 (256 rays): bake seconds, peak RSS of the
  bake process, texture bytes, and the preview's image error against a
  ground truth with per-pixel ray-traced transfer (no texture at all).
  -> resolution.csv, resolution.png
* **bands** 2 ... 8: seconds, bytes, texel error against the truncated
  reference, image error against the per-pixel ground truth at those bands.
  -> bands.csv, bands.png
* **storage** half vs float: bytes and the error half precision adds.
  -> storage.csv
* **bounce** / **denoise** (``--only bounce,denoise``): bounce level 1 on the
  room with 16 ... 256 rays, raw and through each denoiser (edge-aware joint
  bilateral within UV islands; OIDN RTLightmap on normalised SH when pyoidn
  is installed), error against a 2048-ray bounce reference, time including
  the denoiser. -> denoise.csv, bounce_denoise.png (bench/denoise_sweep.py)
* **adaptive_bounce** (``--only adaptive_bounce``): the most an adaptive bounce ray count
  could save, from two default bakes that differ in their seed (the oracle
  allocation's ray saving at equal error). -> adaptive_bounce.csv
  (bench/adaptive_bound.py)
* **window** (issue 53's interiors): the room lit only through a window
  (bench/window_room.py, 512² atlas) at 64 ... 1024 rays, each fix on top
  of the one before: nothing (cosine rays), guided rays (aimed at the
  openings), the guided filter, texel validity (= the defaults), and OIDN on
  the defaults when pyoidn is installed. Mean and p99 error of the
  irradiance against a 65,536-ray reference at 2,000 texels, bake seconds.
  -> window.csv
* **scenes** of the paper's table (room 21K, plants 18K, two statues and a
  monkey 458K, dragon-class 1.33M triangles), 256 rays: seconds, peak RSS,
  texels, bytes per texel against the paper's 100 MB per 1024^2 texture.
  -> scenes.csv, triangles.png

``--quick`` runs every part at toy sizes (a smoke test, seconds).
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from ...core.bake.pipeline.context import BakeSettings
from ...core.bake.pipeline.runner import bake_scene
from ...core.io.jobfile import save_scene
from . import scene_library
from .adaptive_bound import sweep_adaptive_bound
from .denoise_sweep import print_rays_needed, sweep_bounce_denoise, sweep_transfer_denoise
from .texture_error import image_error, load_set_textures, texel_error

OUT = os.path.join(scene_library.ROOT, "docs", "bench")

STRATEGIES = {
    "uniform": dict(sampler="random", distribution="uniform", estimator="plain"),
    "cosine": dict(sampler="random", distribution="cosine", estimator="plain"),
    "stratified": dict(sampler="stratified", distribution="cosine", estimator="plain"),
    "sobol (default)": dict(sampler="sobol", distribution="cosine", estimator="balanced"),
    "sobol, no analytic path": dict(sampler="sobol", distribution="cosine", estimator="balanced", analytic=False),
}
ADAPTIVE_TOLS = (0.02, 0.01, 0.005, 0.0025, 0.00125)


class Config:
    def __init__(self, quick: bool):
        self.quick = quick
        self.sweep_res = 64 if quick else 512
        self.ref_rays = 1024 if quick else 65536
        self.ref_bands = 8
        self.rays = (16, 64) if quick else (16, 32, 64, 128, 256, 512, 1024, 2048, 4096)
        self.tols = ADAPTIVE_TOLS[:2] if quick else ADAPTIVE_TOLS
        self.resolutions = (64, 128) if quick else (128, 256, 512, 1024, 2048)
        self.bands = (2, 3) if quick else (2, 3, 4, 5, 6, 7, 8)
        self.image = (96, 54) if quick else (320, 180)
        self.truth_rays = 128 if quick else 1024
        self.scenes = ("room",) if quick else ("room", "plants", "trm", "dragon")
        self.scene_res = 128 if quick else 1024


# --- helpers -------------------------------------------------------------------------------

def timed_bake(sc, out_dir, settings: BakeSettings) -> tuple[float, dict]:
    t = time.perf_counter()
    m = bake_scene(sc, out_dir, settings, skip_if_unchanged=False)
    return time.perf_counter() - t, m


_CHILD = """
import json, sys
from prtt_addon.cli import main
code = main(sys.argv[1:])
hwm = next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM:"))
print(json.dumps({"code": code, "peak_rss_kb": hwm}))
sys.exit(code)
"""


def bake_subprocess(sc, out_dir: str, args: list) -> tuple[dict, float]:
    """Bake in a child process (``prtt_addon bake-job``); returns its manifest
    and its peak RSS in MB. The child reads its own high-water mark (VmHWM):
    a forked child's ru_maxrss would include the parent's pages from before exec."""
    job = os.path.join(out_dir, "job.npz")
    os.makedirs(out_dir, exist_ok=True)
    save_scene(sc, job)
    env = dict(os.environ, PYTHONPATH=scene_library.ROOT)
    r = subprocess.run([sys.executable, "-c", _CHILD, "bake-job", job, "--out", out_dir, "--force",
                        "--bounces", "0", *args], capture_output=True, text=True, env=env)
    if r.returncode != 0:
        raise RuntimeError(f"bake-job failed: {r.stderr[-2000:]}")
    peak = json.loads(r.stdout.strip().splitlines()[-1])["peak_rss_kb"] / 1024.0
    with open(os.path.join(out_dir, "manifest.json"), encoding="utf-8") as f:
        return json.load(f), peak


def write_csv(path: str, rows: list) -> None:
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})


class Previewer:
    """TPFL preview images (offscreen, the viewport's shaders) of baked
    textures, with their bounce light when ``bounces`` (bench auto). The
    camera is the room's unless ``eye`` and ``target`` (metres, Z up) say."""

    def __init__(self, sc, light, size, *, bounces: bool = False, eye=(0.0, -5.6, 2.3), target=(0.0, 0.6, 0.7)):
        import bpy  # noqa: F401  (provides gpu)

        from ...blender.preview.offscreen import ensure_gpu
        from ...blender.preview.renderer import Renderer
        from ...core.preview.reference import look_at, perspective
        ensure_gpu()
        self.sc, self.light, (self.w, self.h), self.bounces = sc, light, size, bounces
        eye = np.asarray(eye, np.float64)
        self.vp = perspective(62.0, self.w / self.h) @ look_at(eye, tuple(target))
        self.cam = np.array([*eye, 1.0])
        self.renderer = Renderer()

    def scene(self, out_dir, bands):
        from ...core.preview.pack import from_core_scene
        return from_core_scene(self.sc, out_dir, self.light, bands, use_bounces=self.bounces)

    def render(self, out_dir, bands=5) -> np.ndarray:
        from ...blender.preview.renderer import render_offscreen
        img, _ = render_offscreen(self.renderer, self.scene(out_dir, bands), "tpfl", self.vp, self.cam, self.w, self.h)
        return img

    def ground_truth(self, out_dir, bands, rays) -> np.ndarray:
        """Per-pixel ray-traced transfer, shaded by the same model (no texture)."""
        from ...core.preview.reference import traced_reference
        img, _ = traced_reference(self.scene(out_dir, bands), self.vp, self.cam, self.w, self.h, rays=rays)
        return img


# --- the parts ---------------------------------------------------------------------------------

def reference(cfg: Config, sc) -> tuple[str, dict]:
    """The converged reference of the sweep scene (cached): folder and textures."""
    d = os.path.join(scene_library.CACHE, f"sweep-ref-{cfg.sweep_res}-{cfg.ref_rays}-b{cfg.ref_bands}-{scene_library.layout_code()}")
    if not os.path.isfile(os.path.join(d, "manifest.json")):
        print(f"  converged reference: {cfg.ref_rays} stratified rays per texel, {cfg.ref_bands} bands "
              f"(once; cached in {os.path.relpath(d, scene_library.ROOT)})", flush=True)
        t = time.perf_counter()
        bake_scene(sc, d, BakeSettings(bands=cfg.ref_bands, rays=cfg.ref_rays, sampler="stratified",
                                       estimator="plain", half=False, seed=12345, bounces=0), skip_if_unchanged=False)
        print(f"  reference took {time.perf_counter() - t:.0f} s", flush=True)
    return d, load_set_textures(d, sc)


def sweep_rays(cfg, sc, ref, ref_img, previewer, tmp) -> list:
    rows = []
    todo = [(name, dict(kw), r) for name, kw in STRATEGIES.items() for r in cfg.rays]
    todo += [("adaptive", dict(adaptive_tol=tol, min_rays=16), max(cfg.rays)) for tol in cfg.tols]
    tiny = scene_library.paper_scene("room", 64)
    for name, kw, rays in todo:
        d = os.path.join(tmp, "rays")
        st = BakeSettings(bands=5, rays=rays, half=False, bounces=0, **kw)
        # Per-process set-up (sampling patterns, estimator tables: up to 0.5 s, once per
        # ray count) is warmed on a tiny bake so the timing compares steady-state work.
        timed_bake(tiny, os.path.join(tmp, "warm"), st)
        seconds, m = timed_bake(sc, d, st)
        err = texel_error(load_set_textures(d, sc), ref)
        img_err = image_error(previewer.render(d), ref_img)
        rows.append({"strategy": name, "rays": rays, "adaptive_tol": kw.get("adaptive_tol", 0.0),
                     "rays_traced": m["totals"]["rays_traced"], "seconds": seconds,
                     "texel_rel_rmse": err, "image_rel_rmse": img_err})
        print(f"  {name:24s} rays {rays:5d} tol {kw.get('adaptive_tol', 0):<8g} {seconds:7.2f} s  "
              f"texel {100 * err:6.2f} %  image {100 * img_err:6.2f} %", flush=True)
    return rows


def sweep_resolution(cfg, light, tmp) -> list:
    rows = []
    truth = None
    for res in cfg.resolutions:
        sc = scene_library.with_room_materials(scene_library.paper_scene("room", res))
        d = os.path.join(tmp, f"res{res}")
        m, rss = bake_subprocess(sc, d, ["--rays", "256"])
        pv = Previewer(sc, light, cfg.image)
        if truth is None:
            truth = pv.ground_truth(d, 5, cfg.truth_rays)
        err = image_error(pv.render(d), truth)
        s = m["sets"][0]
        nbytes = sum(os.path.getsize(os.path.join(d, f)) for f in m["transfer_files"])
        rows.append({"resolution": res, "texels": m["totals"]["texels"], "seconds": m["seconds"]["total"],
                     "trace_seconds": m["seconds"]["trace"], "peak_rss_mb": rss, "exr_bytes": nbytes,
                     "gpu_bytes_half": res * res * 7 * 4 * 2, "image_rel_rmse": err,
                     "rays_traced": s["rays_traced"]})
        print(f"  {res:5d}^2 {m['totals']['texels']:9,d} texels {m['seconds']['total']:7.2f} s  peak RSS {rss:7.0f} MB  "
              f"EXR {nbytes / 2**20:6.1f} MiB  image {100 * err:6.2f} %", flush=True)
    return rows


def sweep_bands(cfg, sc, ref, light_fn, tmp) -> list:
    rows = []
    for n in cfg.bands:
        d = os.path.join(tmp, f"bands{n}")
        seconds, m = timed_bake(sc, d, BakeSettings(bands=n, rays=256, half=False, bounces=0))
        err = texel_error(load_set_textures(d, sc), ref)
        pv = Previewer(sc, light_fn(n), cfg.image)
        img_err = image_error(pv.render(d, n), pv.ground_truth(d, n, cfg.truth_rays))
        nbytes = sum(os.path.getsize(os.path.join(d, f)) for f in m["transfer_files"])
        rows.append({"bands": n, "coefficients": n * n, "seconds": seconds, "exr_bytes": nbytes,
                     "texel_rel_rmse": err, "image_rel_rmse": img_err})
        print(f"  {n} bands ({n * n:2d} coeffs) {seconds:6.2f} s  EXR {nbytes / 2**20:6.2f} MiB  "
              f"texel {100 * err:6.2f} %  image vs per-pixel truth {100 * img_err:6.2f} %", flush=True)
    return rows


def sweep_storage(cfg, sc, ref, previewer, tmp) -> list:
    rows = []
    imgs = {}
    for half in (False, True):
        d = os.path.join(tmp, f"half{half}")
        seconds, m = timed_bake(sc, d, BakeSettings(bands=5, rays=256, half=half, seed=3, bounces=0))
        tex = load_set_textures(d, sc)
        imgs[half] = previewer.render(d)
        nbytes = sum(os.path.getsize(os.path.join(d, f)) for f in m["transfer_files"])
        rows.append({"storage": "half" if half else "float", "seconds": seconds, "exr_bytes": nbytes,
                     "texel_rel_rmse": texel_error(tex, ref), "tex": tex})
    diff = texel_error(rows[1].pop("tex"), rows[0].pop("tex"))
    img_diff = image_error(imgs[True], imgs[False])
    for r in rows:
        r["half_vs_float_texel_rel_rmse"] = diff
        r["half_vs_float_image_rel_rmse"] = img_diff
        print(f"  {r['storage']:5s} {r['seconds']:6.2f} s  EXR {r['exr_bytes'] / 2**20:6.2f} MiB  "
              f"texel error {100 * r['texel_rel_rmse']:.3f} %", flush=True)
    print(f"  half vs float: texels {100 * diff:.4f} %, image {100 * img_diff:.4f} %")
    return rows


#: The window part's bakes, each adding one of issue 53's fixes to the one before.
WINDOW_VARIANTS = {
    "cosine rays": dict(guiding=False, guided_filter=False, texel_validity=False),
    "+ guided rays": dict(guided_filter=False, texel_validity=False),
    "+ guided filter": dict(texel_validity=False),
    "+ texel validity (defaults)": {},
}


def sweep_window(cfg) -> list:
    """Error and seconds of each fix for the window-lit room (WINDOW_VARIANTS,
    then OIDN on the defaults), rows in bake order."""
    from .denoise_sweep import oidn_available
    from .window_room import measure
    res = 128 if cfg.quick else 512
    rays = (64,) if cfg.quick else (64, 256, 1024)
    denoisers = ("none", "oidn") if oidn_available() else ("none",)
    r = measure(res, rays=rays, ref_rays=1024 if cfg.quick else 65536, ref_texels=300 if cfg.quick else 2000,
                variants=list(WINDOW_VARIANTS.values()), denoisers=denoisers)
    labels = [(n, d) for n in WINDOW_VARIANTS for d in denoisers]
    out = []
    for i, row in enumerate(r["rows"]):
        name, den = labels[i % len(labels)]
        if den != "none" and name != "+ texel validity (defaults)":
            continue                                   # OIDN only on top of the defaults
        label = name if den == "none" else "defaults + OIDN"
        out.append(dict(resolution=res, rays=row["rays"], variant=label, mean_error=round(row["mean"], 5),
                        p99_error=round(row["p99"], 5), bake_s=row["bake_s"],
                        denoise_s=row["denoise_s"] if den != "none" else 0.0))
        print(f"  {row['rays']:5d} rays  {label:28s}  mean {row['mean']:6.2%}  p99 {row['p99']:6.1%}  "
              f"bake {row['bake_s']:5.2f} s" + (f" + {row['denoise_s']:.2f} s" if den != "none" else ""),
              flush=True)
    return out


def sweep_scenes(cfg, tmp) -> list:
    rows = []
    for name in cfg.scenes:
        sc = scene_library.paper_scene(name, cfg.scene_res)
        d = os.path.join(tmp, f"scene-{name}")
        m, rss = bake_subprocess(sc, d, ["--rays", "256"])
        texels = m["totals"]["texels"]
        nbytes = sum(os.path.getsize(os.path.join(d, f)) for f in m["transfer_files"])
        res = [int(w) * int(h) for w, h in sc.set_resolution]
        rows.append({"scene": name, "triangles": sc.n_triangles, "sets": sc.n_sets, "texture_texels": sum(res),
                     "texels": texels, "rays_traced": m["totals"]["rays_traced"],
                     "bvh_seconds": m["seconds"]["bvh"], "trace_seconds": m["seconds"]["trace"],
                     "seconds": m["seconds"]["total"], "peak_rss_mb": rss, "exr_bytes": nbytes,
                     "exr_bytes_per_texel": nbytes / texels, "gpu_bytes_per_texel_half": 7 * 4 * 2,
                     "float32_bytes_per_texel": 25 * 4})
        print(f"  {name:7s} {sc.n_triangles:9,d} tris {sc.n_sets:2d} sets {texels:10,d} texels "
              f"{m['seconds']['total']:7.1f} s (BVH {m['seconds']['bvh']:.1f})  peak RSS {rss:6.0f} MB  "
              f"EXR {nbytes / 2**20:6.1f} MiB", flush=True)
    return rows


# --- plots ---------------------------------------------------------------------------------------

def pareto(points):
    """Indices of the lower-left frontier of (seconds, error) points."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    best, keep = np.inf, []
    for i in order:
        if points[i][1] < best:
            best = points[i][1]
            keep.append(i)
    return keep


def plot_all(out: str, results: dict) -> list:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    paths = []
    rays = results.get("rays")
    if rays:
        fig, axes = plt.subplots(1, 2, figsize=(12, 4.6))
        for ax, key, label in ((axes[0], "texel_rel_rmse", "transfer texels"),
                               (axes[1], "image_rel_rmse", "TPFL preview image")):
            for name in list(STRATEGIES) + ["adaptive"]:
                rs = [r for r in rays if r["strategy"] == name]
                ax.loglog([r["seconds"] for r in rs], [r[key] for r in rs], "o-", ms=3, label=name)
            pts = [(r["seconds"], r[key]) for r in rays]
            front = pareto(pts)
            ax.loglog([pts[i][0] for i in front], [pts[i][1] for i in front], "k--", lw=1, label="Pareto frontier")
            ax.set_xlabel("bake seconds (room, 512² atlas, 2 cores)")
            ax.set_ylabel("relative RMSE vs converged reference")
            ax.set_title(f"error of the {label}")
            ax.grid(True, which="both", alpha=0.3)
        axes[0].legend(fontsize=8)
        fig.tight_layout()
        paths.append(os.path.join(out, "error_vs_seconds.png"))
        fig.savefig(paths[-1], dpi=90)
        plt.close(fig)
    res = results.get("resolution")
    if res:
        fig, axes = plt.subplots(1, 3, figsize=(14, 4))
        tx = [r["texels"] for r in res]
        axes[0].loglog(tx, [r["seconds"] for r in res], "o-")
        axes[0].set_ylabel("bake seconds")
        axes[1].loglog(tx, [r["peak_rss_mb"] for r in res], "o-", label="peak RSS of the bake")
        axes[1].loglog(tx, [r["gpu_bytes_half"] / 2**20 for r in res], "s--", label="GPU texture (half)")
        axes[1].set_ylabel("MB")
        axes[1].legend(fontsize=8)
        axes[2].loglog(tx, [r["image_rel_rmse"] for r in res], "o-")
        axes[2].set_ylabel("image rel. RMSE vs per-pixel ray tracing")
        for ax in axes:
            ax.set_xlabel("texels (128² ... 2048² atlas)")
            ax.grid(True, which="both", alpha=0.3)
        fig.tight_layout()
        paths.append(os.path.join(out, "resolution.png"))
        fig.savefig(paths[-1], dpi=90)
        plt.close(fig)
    bands = results.get("bands")
    if bands:
        fig, axes = plt.subplots(1, 3, figsize=(14, 4))
        b = [r["bands"] for r in bands]
        axes[0].plot(b, [r["seconds"] for r in bands], "o-")
        axes[0].set_ylabel("bake seconds")
        axes[1].plot(b, [r["exr_bytes"] / 2**20 for r in bands], "o-")
        axes[1].set_ylabel("EXR MiB (float)")
        axes[2].semilogy(b, [r["texel_rel_rmse"] for r in bands], "o-", label="texels vs reference")
        axes[2].semilogy(b, [r["image_rel_rmse"] for r in bands], "s-", label="image vs per-pixel truth")
        axes[2].legend(fontsize=8)
        for ax in axes:
            ax.set_xlabel("SH bands")
            ax.grid(True, alpha=0.3)
        fig.tight_layout()
        paths.append(os.path.join(out, "bands.png"))
        fig.savefig(paths[-1], dpi=90)
        plt.close(fig)
    sc = results.get("scenes")
    if sc and len(sc) > 1:
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        t = [r["triangles"] for r in sc]
        secs = [r["seconds"] for r in sc]
        rss = [r["peak_rss_mb"] for r in sc]
        axes[0].loglog(t, secs, "o")
        axes[0].loglog(t, [r["bvh_seconds"] for r in sc], "s")
        axes[0].legend(["whole bake (256 rays)", "BVH build"], fontsize=8)
        axes[0].set_ylabel("seconds")
        axes[1].loglog(t, rss, "o")
        axes[1].set_ylabel("peak RSS of the bake, MB")
        for ax, ys in zip(axes, (secs, rss)):
            for r, y in zip(sc, ys):
                ax.annotate(f"{r['scene']} ({r['texels'] / 1e6:.1f}M texels)", (r["triangles"], y), fontsize=8)
            ax.set_xlabel("triangles")
            ax.grid(True, which="both", alpha=0.3)
        fig.tight_layout()
        paths.append(os.path.join(out, "triangles.png"))
        fig.savefig(paths[-1], dpi=90)
        plt.close(fig)
    for key, rays_key, what, fname in (("denoise", "bounce_rays", "bounce", "bounce_denoise.png"),
                                       ("denoise_transfer", "rays", "transfer", "transfer_denoise.png")):
        den = results.get(key)
        if not den:
            continue
        fig, axes = plt.subplots(1, 2, figsize=(12, 4.6))
        for f in sorted({r["filter"] for r in den}):
            rs = sorted((r for r in den if r["filter"] == f), key=lambda r: r[rays_key])
            axes[0].loglog([r["total_s"] for r in rs], [r["error"] for r in rs], "o-", ms=3, label=f)
            axes[1].loglog([r[rays_key] for r in rs], [r["error"] for r in rs], "o-", ms=3, label=f)
        axes[0].set_xlabel(f"{what} bake + denoise seconds (room, 2 cores)")
        axes[1].set_xlabel(f"{what} rays per texel")
        for ax in axes:
            ax.set_ylabel(f"relative RMSE vs converged {what}")
            ax.grid(True, which="both", alpha=0.3)
        axes[0].legend(fontsize=8)
        fig.tight_layout()
        paths.append(os.path.join(out, fname))
        fig.savefig(paths[-1], dpi=90)
        plt.close(fig)
    return paths


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench sweep", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="toy sizes: checks the machinery in seconds")
    p.add_argument("--only", default="rays,resolution,bands,storage,window,scenes",
                   help="comma list of parts to run")
    p.add_argument("--out", default=None, help="folder for CSV/PNG (default docs/bench; --quick: a temp folder)")
    args = p.parse_args(argv)
    cfg = Config(args.quick)
    out = args.out or (tempfile.mkdtemp(prefix="prtt-sweep-") if args.quick else OUT)
    os.makedirs(out, exist_ok=True)
    parts = args.only.split(",")
    from ...core.light.envmap import environment_light
    light_fn = lambda n: environment_light("forest", n)          # noqa: E731
    sc = scene_library.with_room_materials(scene_library.paper_scene("room", cfg.sweep_res))
    results, part_seconds, t_all = {}, {}, time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="prtt-sweep-") as tmp:
        if {"rays", "bands", "storage"} & set(parts):
            ref_dir, ref = reference(cfg, sc)
            previewer = Previewer(sc, light_fn(5), cfg.image)
            ref_img = previewer.render(ref_dir, 5)
        if "rays" in parts:
            print("rays x strategy (room, %d^2):" % cfg.sweep_res, flush=True)
            t = time.perf_counter()
            results["rays"] = sweep_rays(cfg, sc, ref, ref_img, previewer, tmp)
            part_seconds["rays"] = time.perf_counter() - t
        if "resolution" in parts:
            print("resolution (room, 256 rays):", flush=True)
            t = time.perf_counter()
            results["resolution"] = sweep_resolution(cfg, light_fn(5), tmp)
            part_seconds["resolution"] = time.perf_counter() - t
        if "bands" in parts:
            print("bands (room, 256 rays):", flush=True)
            t = time.perf_counter()
            results["bands"] = sweep_bands(cfg, sc, ref, light_fn, tmp)
            part_seconds["bands"] = time.perf_counter() - t
        if "storage" in parts:
            print("storage:", flush=True)
            t = time.perf_counter()
            results["storage"] = sweep_storage(cfg, sc, ref, previewer, tmp)
            part_seconds["storage"] = time.perf_counter() - t
        if "bounce" in parts or "denoise" in parts:
            print("bounce rays x denoiser (room, level 1):", flush=True)
            t = time.perf_counter()
            results["denoise"] = sweep_bounce_denoise(cfg, light_fn(5), tmp, with_denoise="denoise" in parts)
            print_rays_needed(results["denoise"], "bounce_rays", 64, "bounce")    # 64: the default
            if "denoise" in parts:
                print("transfer rays x denoiser (room, %d^2):" % cfg.sweep_res, flush=True)
                results["denoise_transfer"] = sweep_transfer_denoise(cfg, sc, tmp)
                print_rays_needed(results["denoise_transfer"], "rays", 256, "transfer")
            part_seconds["denoise"] = time.perf_counter() - t
        if "adaptive_bounce" in parts:
            print("adaptive bounce rays, the oracle's bound (room, tuning auto):", flush=True)
            t = time.perf_counter()
            results["adaptive_bounce"] = sweep_adaptive_bound(cfg, light_fn(5), tmp)
            part_seconds["adaptive_bounce"] = time.perf_counter() - t
        if "window" in parts:
            print("the window-lit room, issue 53's fixes one on another:", flush=True)
            t = time.perf_counter()
            results["window"] = sweep_window(cfg)
            part_seconds["window"] = time.perf_counter() - t
        if "scenes" in parts:
            print("the paper's scene classes (256 rays):", flush=True)
            t = time.perf_counter()
            results["scenes"] = sweep_scenes(cfg, tmp)
            part_seconds["scenes"] = time.perf_counter() - t
    for name, rows in results.items():
        write_csv(os.path.join(out, f"{name}.csv"), rows)
    summary_path = os.path.join(out, "sweep_summary.json")
    merged = {}
    if os.path.isfile(summary_path):                 # --only: keep the other parts' last results
        with open(summary_path, encoding="utf-8") as f:
            merged = json.load(f)
    merged.update(results, quick=cfg.quick, cpu_count=os.cpu_count())
    merged.setdefault("seconds_per_part", {}).update(part_seconds)
    plots = plot_all(out, {k: merged[k] for k in ("rays", "resolution", "bands", "storage", "scenes", "denoise",
                                                  "denoise_transfer") if k in merged})
    with open(summary_path, "w", encoding="utf-8") as f:
        json.dump(merged, f, indent=1)
    print(f"wrote {len(results)} CSV file(s) and {len(plots)} plot(s) to {out} "
          f"({time.perf_counter() - t_all:.0f} s)")
    return 0
