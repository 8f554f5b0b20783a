"""``python -m prtt_addon.dev.bench auto``: per-set tuning (``--tuning auto``) against
the fixed bake, in time, bytes and preview image error, in one run.

Scenes: the room-class scene (1024^2 atlas, 14 materials) and the paper's
other classes (plants: one 1024^2 atlas; two statues and a monkey, dragon:
a set per object, floor 1024^2, models 512^2; the default glossy material),
one bounce, Blender's "forest" HDRI. Each is baked as before per-set tuning
(``fixed``), the room also with the coarse bounce grid alone, and with
``auto``; each bake is rendered by the viewport's own shaders (offscreen,
llvmpipe where there is no GPU) with its bounce light and compared with the
same render of a converged bake (full grid and bands, float storage; the
room 2048 transfer and 1024 bounce rays, the others 1024 and 512; cached in
.cache/bench). The image error is the relative RMSE over covered pixels;
the fixed bake's error is its Monte Carlo noise. Writes docs/bench/auto.csv
and auto.png, and prints a summary per scene, the room's last:

    auto vs fixed: time ÷ A, bytes ÷ B, image error X % vs Y %

``--quick`` is a smoke test at toy sizes (room and plants).
"""
from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time

import numpy as np

from ...core.bake.pipeline.context import BakeSettings, bounce_seconds
from ...core.bake.pipeline.runner import bake_scene
from ...core.light.envmap import environment_light
from . import scene_library
from .sweep import Previewer, write_csv
from .texture_error import image_error

DOCS_BENCH = os.path.join(scene_library.ROOT, "docs", "bench")


def texture_bytes(out_dir: str, manifest: dict) -> int:
    return sum(os.path.getsize(os.path.join(out_dir, f)) for f in manifest["files"])


def reference_dir(name: str, sc, light, res: int, rays: int, bounce_rays: int) -> str:
    d = os.path.join(scene_library.CACHE, f"auto-ref-{name}-{res}-{rays}-{bounce_rays}-{scene_library.layout_code()}")
    if not os.path.isfile(os.path.join(d, "manifest.json")):
        print(f"converged reference of {name}: {rays} transfer rays, {bounce_rays} bounce rays (once; cached in "
              f"{os.path.relpath(d, scene_library.ROOT)})", flush=True)
        t = time.perf_counter()
        bake_scene(sc, d, BakeSettings(rays=rays, bounces=1, bounce_rays=bounce_rays, half=False, seed=4242,
                                       tuning="fixed", bounce_mode="baked"), light=light, skip_if_unchanged=False)
        print(f"  reference took {time.perf_counter() - t:.0f} s", flush=True)
    return d


#: (name, settings beyond the defaults): the bake before per-set tuning, the
#: coarse bounce grid alone (the room only), auto (the default).
VARIANTS = (
    ("fixed", {"tuning": "fixed"}),
    ("grid 1/2", {"tuning": "fixed", "bounce_downscale": 2}),
    ("auto", {"tuning": "auto"}),
)
#: The room (its materials, one atlas) and the paper's other scene classes
#: (bench/scene_library.py: plants in one atlas, trm and dragon a set per object).
SCENES = ("room", "plants", "trm", "dragon")
#: Converged references: transfer rays, bounce rays (the room's since #18; the
#: larger classes at half, whose noise then adds ~12 % to both bakes' errors).
REFERENCE_RAYS = {"room": (2048, 1024)}
OTHER_REFERENCE_RAYS = (1024, 512)


def scene_and_camera(name: str, res: int):
    """The scene and the Previewer's camera keywords (the room's own camera;
    others framed from their bounds, looking from -Y and above)."""
    if name == "room":
        return scene_library.room_scene(res, atlas=True, materials=True), {}
    sc = scene_library.paper_scene(name, res)
    p = sc.positions.reshape(-1, 3)
    lo, hi = p.min(axis=0), p.max(axis=0)
    c = 0.5 * (lo + hi)
    r = 0.5 * float(np.linalg.norm(hi - lo))
    return sc, {"eye": c + r * np.array([0.0, -1.25, 0.75]), "target": c}


def bake_variant(sc, d: str, light, extra: dict, view, ref_img) -> dict:
    st = BakeSettings(bounces=1, bounce_mode="baked", **extra)
    t = time.perf_counter()
    m = bake_scene(sc, d, st, light=light, skip_if_unchanged=False)
    seconds = time.perf_counter() - t
    sec = m["seconds"]
    transfer_bytes = sum(os.path.getsize(os.path.join(d, f)) for f in m["transfer_files"])
    bounce_bytes = texture_bytes(d, m) - transfer_bytes
    grids = [r.get("grid") for r in m["bounce"]["sets"]]
    shown = sorted({f"1/{g['downscale']} {g.get('bands', 5)} bands" for g in grids if g})
    return {"seconds": seconds, "transfer_seconds": sec["trace"],
            "bounce_seconds": bounce_seconds(sec),
            "bytes": transfer_bytes + bounce_bytes, "transfer_bytes": transfer_bytes, "bounce_bytes": bounce_bytes,
            "image_rel_rmse": image_error(view.render(d), ref_img),
            "rays_traced": m["totals"]["rays_traced"] + m["bounce"]["rays_traced"],
            "grid": "; ".join(shown) or "full, 5 bands"}


def summary(fixed: dict, auto: dict) -> str:
    return (f"auto vs fixed: time ÷ {fixed['seconds'] / auto['seconds']:.2f}, bytes ÷ "
            f"{fixed['bytes'] / auto['bytes']:.2f}, image error {100 * auto['image_rel_rmse']:.3f} % vs "
            f"{100 * fixed['image_rel_rmse']:.3f} %")


def plot(path: str, rows: list) -> None:
    """Image error against bake seconds and against texture bytes, fixed -> auto per scene."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for i, name in enumerate(dict.fromkeys(r["scene"] for r in rows)):
        mine = {r["variant"]: r for r in rows if r["scene"] == name}
        f, a = mine["fixed"], mine["auto"]
        for ax, key, scale in ((axes[0], "seconds", 1.0), (axes[1], "bytes", 1e-6)):
            xs = [f[key] * scale, a[key] * scale]
            ys = [100 * f["image_rel_rmse"], 100 * a["image_rel_rmse"]]
            ax.plot(xs, ys, "-", color=f"C{i}", alpha=0.5)
            ax.plot(xs[:1], ys[:1], "o", color=f"C{i}", label=f"{name} fixed")
            ax.plot(xs[1:], ys[1:], "^", color=f"C{i}", label=f"{name} auto")
    axes[0].set_xlabel("bake seconds (transfer + 1 bounce), 2 cores")
    axes[1].set_xlabel("texture MB on disk (transfer + bounce)")
    for ax in axes:
        ax.set_ylabel("preview image error vs converged, %")
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=7, ncol=2)
    fig.suptitle("bench auto: per-set tuning (triangles) against the fixed bake (circles)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench auto", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="toy sizes (a smoke test)")
    p.add_argument("--scenes", default=",".join(SCENES),
                   help=f"comma-separated, from {', '.join(SCENES)} (the room's line is printed last)")
    p.add_argument("--out", default=DOCS_BENCH, help="folder for auto.csv and auto.png (default docs/bench)")
    args = p.parse_args(argv)
    names = [n for n in args.scenes.split(",") if n]
    unknown = sorted(set(names) - set(SCENES))
    if unknown:
        p.error(f"unknown scene(s) {', '.join(unknown)}; choose from {', '.join(SCENES)}")
    if args.quick:
        names = [n for n in names if n in ("room", "plants")]
    names.sort(key=lambda n: n == "room")              # the room's summary is the last line
    res, size = (128, (160, 90)) if args.quick else (1024, (640, 360))
    light = environment_light("forest", 5)
    rows = []
    for name in names:
        sc, camera = scene_and_camera(name, res if name == "room" or not args.quick else 64)
        rays, bounce_rays = ((256, 64) if args.quick else REFERENCE_RAYS.get(name, OTHER_REFERENCE_RAYS))
        print(f"{name}: {sc.n_triangles} triangles, {sc.n_sets} set(s), one bounce, light 'forest'", flush=True)
        ref = reference_dir(name, sc, light, int(sc.set_resolution.max()), rays, bounce_rays)
        view = Previewer(sc, light, size, bounces=True, **camera)
        ref_img = view.render(ref)
        with tempfile.TemporaryDirectory(prefix="prtt-bench-auto-") as tmp:
            for variant, extra in VARIANTS:
                if variant == "grid 1/2" and name != "room":
                    continue
                d = os.path.join(tmp, variant.replace(" ", "_").replace("/", "-"))
                # Cold, the first variant (fixed) paid the process's set-up.
                scene_library.warm_up(os.path.join(tmp, "warm"), BakeSettings(bounces=1, bounce_mode="baked", **extra), light)
                r = {"scene": name, "variant": variant, **bake_variant(sc, d, light, extra, view, ref_img)}
                rows.append(r)
                shutil.rmtree(d, ignore_errors=True)
                print(f"  {variant:10s} {r['seconds']:7.1f} s (transfer {r['transfer_seconds']:5.1f}, bounce "
                      f"{r['bounce_seconds']:5.1f})  {r['bytes'] / 1e6:7.1f} MB (bounce {r['bounce_bytes'] / 1e6:6.1f})"
                      f"  image error {100 * r['image_rel_rmse']:.3f} %  [{r['grid']}]", flush=True)
    if not args.quick:
        os.makedirs(args.out, exist_ok=True)
        write_csv(os.path.join(args.out, "auto.csv"), rows)
        plot(os.path.join(args.out, "auto.png"), rows)
    for name in names:
        mine = {r["variant"]: r for r in rows if r["scene"] == name}
        line = summary(mine["fixed"], mine["auto"])
        print(line if name == "room" else f"{name}: {line}")
    return 0
