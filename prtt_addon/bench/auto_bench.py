"""``python -m prtt_addon.bench auto``: per-set tuning (``--tuning auto``) against
the fixed bake, in time, bytes and preview image error, in one run.

The room-class scene (1024^2 atlas, 11 materials, one bounce, Blender's
"forest" HDRI) is baked with the default settings (``fixed``), with each part
of ``auto`` alone, and with ``auto``; each bake is rendered by the viewport's
own shaders (offscreen, llvmpipe where there is no GPU) with its bounce light
and compared with the same render of a converged bake (2048 transfer rays,
1024 bounce rays, full grid and bands, float storage; cached in .cache/bench).
The image error is the relative RMSE over covered pixels; the default bake's
error is its Monte Carlo noise. Writes docs/bench/auto.csv and prints, last:

    auto vs fixed: time ÷ A, bytes ÷ B, image error X % vs Y %

``--quick`` is a smoke test at toy sizes.
"""
from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time

from ..cli import env_light
from ..core.bake.runner import BakeSettings, bake_scene
from . import scenes
from .sweep import Previewer, image_error, write_csv

DOCS_BENCH = os.path.join(scenes.ROOT, "docs", "bench")


def texture_bytes(out_dir: str, manifest: dict) -> int:
    return sum(os.path.getsize(os.path.join(out_dir, f)) for f in manifest["files"])


def reference_dir(sc, light, res: int, rays: int, bounce_rays: int) -> str:
    d = os.path.join(scenes.CACHE, f"auto-ref-room-{res}-{rays}-{bounce_rays}")
    if not os.path.isfile(os.path.join(d, "manifest.json")):
        print(f"converged reference: {rays} transfer rays, {bounce_rays} bounce rays (once; cached in "
              f"{os.path.relpath(d, scenes.ROOT)})", flush=True)
        t = time.perf_counter()
        bake_scene(sc, d, BakeSettings(rays=rays, bounces=1, bounce_rays=bounce_rays, half=False, seed=4242),
                   light=light, skip_if_unchanged=False)
        print(f"  reference took {time.perf_counter() - t:.0f} s", flush=True)
    return d


#: (name, settings beyond the defaults): the default bake, each part of auto, auto.
VARIANTS = (
    ("fixed", {}),
    ("grid 1/2", {"bounce_downscale": 2}),
    ("auto", {"tuning": "auto"}),
)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.bench auto", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="toy sizes (a smoke test)")
    p.add_argument("--out", default=DOCS_BENCH, help="folder for auto.csv (default docs/bench)")
    args = p.parse_args(argv)
    res, ref_rays, ref_bounce, size = (128, 256, 64, (160, 90)) if args.quick else (1024, 2048, 1024, (640, 360))
    sc = scenes.room_scene(res, atlas=True, materials=True)
    light = env_light("forest", 5)
    print(f"room-class scene: {sc.n_triangles} triangles, {res}^2 atlas, one bounce, light 'forest'", flush=True)
    ref = reference_dir(sc, light, res, ref_rays, ref_bounce)
    view = Previewer(sc, light, size, bounces=True)
    ref_img = view.render(ref)
    rows = []
    with tempfile.TemporaryDirectory(prefix="prtt-bench-auto-") as tmp:
        for name, extra in VARIANTS:
            d = os.path.join(tmp, name.replace(" ", "_").replace("/", "-"))
            st = BakeSettings(bounces=1, **extra)
            t = time.perf_counter()
            m = bake_scene(sc, d, st, light=light, skip_if_unchanged=False)
            seconds = time.perf_counter() - t
            sec = m["seconds"]
            bounce_s = sec["bounce_exit"] + sec["bounce_trace"] + sec["bounce_write"]
            transfer_bytes = sum(os.path.getsize(os.path.join(d, f)) for f in m["transfer_files"])
            bounce_bytes = texture_bytes(d, m) - transfer_bytes
            err = image_error(view.render(d), ref_img)
            grids = [r.get("grid") for r in m["bounce"]["sets"]]
            rows.append({"variant": name, "seconds": seconds, "transfer_seconds": sec["trace"],
                         "bounce_seconds": bounce_s, "bytes": transfer_bytes + bounce_bytes,
                         "transfer_bytes": transfer_bytes, "bounce_bytes": bounce_bytes,
                         "image_rel_rmse": err, "rays_traced": m["totals"]["rays_traced"]
                         + m["bounce"]["rays_traced"],
                         "grid": "; ".join(f"1/{g['downscale']} {g.get('bands', 5)} bands" for g in grids if g)
                         or "full, 5 bands"})
            shutil.rmtree(d, ignore_errors=True)
            r = rows[-1]
            print(f"  {name:10s} {r['seconds']:7.1f} s (transfer {r['transfer_seconds']:5.1f}, bounce "
                  f"{r['bounce_seconds']:5.1f})  {r['bytes'] / 1e6:7.1f} MB (bounce {r['bounce_bytes'] / 1e6:6.1f})  "
                  f"image error {100 * r['image_rel_rmse']:.3f} %  [{r['grid']}]", flush=True)
    os.makedirs(args.out, exist_ok=True)
    if not args.quick:
        write_csv(os.path.join(args.out, "auto.csv"), rows)
    fixed, auto = rows[0], rows[-1]
    print(f"auto vs fixed: time ÷ {fixed['seconds'] / auto['seconds']:.2f}, bytes ÷ "
          f"{fixed['bytes'] / auto['bytes']:.2f}, image error {100 * auto['image_rel_rmse']:.3f} % vs "
          f"{100 * fixed['image_rel_rmse']:.3f} %")
    return 0
