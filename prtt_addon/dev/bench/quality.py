"""``python -m prtt_addon.dev.bench quality``: the lightmap artefacts of issue 53
in one table, each measured before its fix and at today's defaults.

* dark creases at a contact (bench contact-profile: a box resting on a
  floor, 1.8 cm texels): the lowest baked / traced ratio in the first three
  quarter-texel bins beside the box, without and with texel validity;
* a bright leak under a wall of a single plane (contact-profile --leak: the
  shed): the highest ratio on the floor inside its back wall, and the
  lowest outside (the dark line the fix leaves);
* a room lit only through a window (bench window-room): the mean and p99
  error of the irradiance against a converged reference, before (no guided
  rays, no filter, no validity) and now, and the bake's time against the
  bake before guided rays (fastest of ``--repeat``
  interleaved runs);
* seams (bench seam_error, a torus unwrapped in Blender by Lightmap Pack and
  Smart UV Project): the p99 error of the pixels within a texel of an island
  border, TPFL against a traced truth (needs bpy; ``--no-seams`` skips it);
* the crease and the leak again against Cycles (bench/contact_cycles.py: the
  same scenes in Blender under a band-limited World, the floor's irradiance
  from an orthographic Cycles render; needs bpy, ``--no-cycles`` skips it),
  with the traced reference's own distance from Cycles beside them.

Every reference is traced, not baked: the traced transfer at the points
themselves (contacts, leak), cosine rays without guiding (the window room);
Cycles confirms the first two.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np


def contacts(resolution: int = 112) -> dict:
    from ...core.bake.pipeline.context import BakeSettings
    from .contact_profile import leak_profile, profile
    out = {}
    for name, tv in (("before", False), ("now", True)):
        st = BakeSettings(rays=256, bounces=0, texel_validity=tv)
        c = profile(resolution, ref_rays=2048, samples=200, settings=st)
        leak = leak_profile(resolution, ref_rays=2048, samples=200, settings=st)
        out[name] = {"crease": float(c["ratio"][:3].min()), "leak_inside": float(leak["inside"].max()),
                     "leak_outside": float(leak["outside"].min())}
    return out


def window(resolution: int, repeat: int) -> dict:
    from ...core.bake.pipeline.context import BakeSettings
    from ...core.bake.pipeline.runner import bake_scene
    from . import window_room as wr
    # Before (no guided rays, no filter, no validity) and now, against one reference.
    before, now = wr.measure(resolution, rays=(256,), ref_rays=65536, ref_texels=2000,
                             variants=(dict(guiding=False, guided_filter=False, texel_validity=False), {}))["rows"]
    sc = wr.build(resolution)
    runs = {"unguided": dict(guiding=False, texel_validity=False), "now": {}}
    best = dict.fromkeys(runs, float("inf"))
    with tempfile.TemporaryDirectory(prefix="prtt-quality-") as d:
        bake_scene(sc, os.path.join(d, "w"), BakeSettings(rays=256, bounces=0, vertex_mode=False))   # warm
        for _ in range(max(1, repeat)):
            for k, kw in runs.items():
                t = time.perf_counter()
                bake_scene(sc, os.path.join(d, k), BakeSettings(rays=256, bounces=0, vertex_mode=False, **kw),
                           skip_if_unchanged=False)
                best[k] = min(best[k], time.perf_counter() - t)
    return {"before": before, "now": now, "seconds": best}


def cycles(resolution: int = 112, samples: int = 256) -> dict:
    """The crease and the leak's profiles against Cycles, before and now."""
    from ...core.bake.pipeline.context import BakeSettings
    from .contact_cycles import cycles_profile
    variants = {k: BakeSettings(rays=256, bounces=0, texel_validity=k == "now") for k in ("before", "now")}
    box = cycles_profile("box", resolution, samples=samples, variants=variants)
    shed = cycles_profile("shed", resolution, samples=samples, variants=variants)
    out = {k: {"crease": float(box["baked"][k]["out"][:3].min()),
               "leak_inside": float(shed["baked"][k]["inside"].max()),
               "leak_outside": float(shed["baked"][k]["outside"].min())} for k in variants}
    out["traced_off"] = float(max(np.abs(box["traced"]["out"] - 1).max(),
                                  *(np.abs(v - 1).max() for v in shed["traced"].values())))
    return out


def seams() -> dict:
    import bpy

    import prtt_addon
    if not hasattr(bpy.types.Scene, "prtt"):       # the add-on registered once in this process
        prtt_addon.register()
    from .seam_error import torus_errors
    return {m: torus_errors(m)["seam"]["p99"] for m in ("SMART", "LIGHTMAP")}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench quality", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=512, help="the window room's atlas")
    p.add_argument("--repeat", type=int, default=4, help="interleaved runs of the timed window-room bakes")
    p.add_argument("--no-seams", action="store_true", help="skip the seam row (it needs bpy)")
    p.add_argument("--no-cycles", action="store_true", help="skip the rows against Cycles (they need bpy)")
    p.add_argument("--samples", type=int, default=256, help="Cycles' samples a pixel for those rows")
    p.add_argument("--figures", action="store_true",
                   help="also draw docs/images/quality_window.png and quality_contact.png (bench/quality_figures.py)")
    p.add_argument("--only-figures", action="store_true", help="draw the pictures and measure nothing")
    a = p.parse_args(argv)
    if a.figures or a.only_figures:
        from . import quality_figures as qf
        for path in qf.save(qf.window_images(), qf.contact_images()):
            print(f"wrote {os.path.relpath(path, qf.scene_library.ROOT)}", flush=True)
        if a.only_figures:
            return 0
    c = contacts()
    w = window(a.resolution, a.repeat)
    ratio = w["seconds"]["now"] / w["seconds"]["unguided"]
    rows = [
        ("dark crease beside a box on a floor (lowest of the first 3 quarter-texel bins)",
         f"{c['before']['crease']:.3f}", f"{c['now']['crease']:.3f}", ">= 0.9"),
        ("bright leak under a single-plane wall, inside (highest bin)",
         f"{c['before']['leak_inside']:.2f}x", f"{c['now']['leak_inside']:.2f}x", "no bright leak"),
        ("  ... the floor outside that wall (lowest bin)",
         f"{c['before']['leak_outside']:.3f}", f"{c['now']['leak_outside']:.3f}", ""),
        (f"window room {a.resolution}², 256 rays: mean error (p99)",
         f"{w['before']['mean']:.2%} ({w['before']['p99']:.1%})", f"{w['now']['mean']:.2%} ({w['now']['p99']:.1%})",
         "<= 3 %"),
        (f"window room: bake time x the bake before guiding (fastest of {a.repeat})",
         "1.00", f"{ratio:.2f} ({w['seconds']['now']:.2f} s / {w['seconds']['unguided']:.2f} s)", "<= 1.5"),
    ]
    if not a.no_cycles:
        y = cycles(samples=a.samples)
        rows += [
            ("crease against Cycles (lowest of the first 3 bins)", f"{y['before']['crease']:.3f}",
             f"{y['now']['crease']:.3f}", ">= 0.9"),
            ("leak against Cycles, inside (highest bin)", f"{y['before']['leak_inside']:.2f}x",
             f"{y['now']['leak_inside']:.2f}x", "no bright leak"),
            ("  ... outside (lowest bin)", f"{y['before']['leak_outside']:.3f}", f"{y['now']['leak_outside']:.3f}",
             ""),
            (f"  (the traced reference's largest distance from Cycles, {a.samples} samples a pixel)", "",
             f"{y['traced_off']:.1%}", ""),
        ]
    if not a.no_seams:
        s = seams()
        rows.append(("seam p99, torus 512²: Lightmap Pack (Smart UV Project beside it)",
                     "1.46 % (0.94 %), 2026-11-29", f"{s['LIGHTMAP']:.2%} ({s['SMART']:.2%})",
                     "no worse than Smart UV"))
    print("issue 53's artefacts, before their fixes and at today's defaults (baked against traced):")
    width = max(len(r[0]) for r in rows)
    print(f"  {'':{width}}  {'before':>28}  {'now':>28}  goal")
    for r in rows:
        print(f"  {r[0]:{width}}  {r[1]:>28}  {r[2]:>28}  {r[3]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
