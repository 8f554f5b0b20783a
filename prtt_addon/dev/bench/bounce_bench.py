"""``python -m prtt_addon.dev.bench bounce``: inter-reflection bake on the room scene.

Bakes the room-class scene (1024^2 atlas, glossy floor and table, diffuse
walls, a metal sphere, ...) lit by Blender's "forest" HDRI: the transfer
textures first (timed apart), then the bounce levels, and prints per level the
seconds, texels skipped without rays, rays traced, hits shaded (shading
evaluations) and rays/s. ``--scene demo``: the demo's own scene instead
(``./prtt.sh demo``: built in Blender, its textured wooden floor, unwrapped
by PRTT's Unwrap with Smart UV Project, exported as the add-on exports it).
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time

from ...core.bake.pipeline.context import BakeSettings, bounce_seconds
from ...core.bake.pipeline.runner import bake_scene
from ...core.base import jit
from ...core.light.envmap import environment_light
from . import figures, scene_library


def demo_scene(resolution: int):
    """The demo's scene (scene_build.demo_scene) built and unwrapped in Blender and
    exported as the add-on does: (core Scene, the World's light as SH)."""
    import bpy  # Blender as a module: only this scene needs it

    from ... import register
    from ...blender.scene.job import export_scene  # needs bpy
    from .scene_build import demo_scene  # needs bpy
    bpy.ops.wm.read_factory_settings(use_empty=True)
    if not hasattr(bpy.types.Scene, "prtt"):
        register()
    objects = demo_scene()
    st = bpy.context.scene.prtt
    st.resolution, st.texture_sets, st.unwrap_method = resolution, "ATLAS", "SMART"
    for ob in bpy.context.view_layer.objects:
        ob.select_set(ob.type == "MESH")
    bpy.context.view_layer.objects.active = objects["floor"]
    if bpy.ops.prtt.unwrap() != {"FINISHED"}:
        raise RuntimeError("unwrap failed")
    exp = export_scene(bpy.context, with_light=True)
    return exp.scene, exp.light


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench bounce", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=1024)
    p.add_argument("--rays", type=int, default=256, help="transfer rays per texel")
    p.add_argument("--bounces", type=int, default=1)
    p.add_argument("--bounce-rays", type=int, default=BakeSettings().bounce_rays)
    p.add_argument("--bounce-denoise", default=BakeSettings().bounce_denoise)
    p.add_argument("--tuning", default=BakeSettings().tuning, choices=("fixed", "auto"),
                   help="per-set tuning of the bounce textures (auto: coarser grid, fewer bands where they "
                        "are not read)")
    p.add_argument("--env", default="forest")
    p.add_argument("--scene", default="room", choices=("room", "demo"),
                   help="room: the bench's room-class atlas; demo: the demo's scene, unwrapped in Blender")
    p.add_argument("--no-combined", dest="combined", action="store_false",
                   help="skip the third bake (transfer and bounces in one run)")
    args = p.parse_args(argv)
    if args.scene == "demo":
        sc, light = demo_scene(args.resolution)
    else:
        sc = scene_library.room_scene(args.resolution, atlas=True, materials=True)
        light = environment_light(args.env, 5)
    st = BakeSettings(rays=args.rays, bounces=args.bounces, bounce_mode="baked", bounce_rays=args.bounce_rays,
                      bounce_denoise=args.bounce_denoise, tuning=args.tuning)
    print("settings: " + figures.settings_line(st, BakeSettings()))
    print(f"{args.scene} scene: {sc.n_triangles} triangles, {args.resolution}^2 atlas, "
          f"{len(sc.materials)} materials, light '{args.env}'; transfer {args.rays} rays, "
          f"{args.bounces} bounce(s) x {args.bounce_rays} rays, denoise {args.bounce_denoise}, "
          f"tuning {args.tuning}")
    with tempfile.TemporaryDirectory(prefix="prtt-bench-") as d:
        # Cold, the transfer-only bake that the ratios divide by carried the process's set-up.
        scene_library.warm_up(os.path.join(d, "warm"), st, light)
        t = time.perf_counter()
        bake_scene(sc, d, BakeSettings(rays=args.rays, bounces=0, tuning=args.tuning), light=light)
        t_transfer = time.perf_counter() - t
        t = time.perf_counter()
        m = bake_scene(sc, d, st, light=light)                 # reuses the transfer: bounces only
        t_bounce = time.perf_counter() - t
        assert m["transfer_reused"]
        b = m["bounce"]
        sec = m["seconds"]
        print(f"\ntransfer bake: {t_transfer:.2f} s")
        print(f"bounce bake:   {t_bounce:.2f} s (loading the transfer textures included): exit radiance "
              f"{sec.get('bounce_exit', 0.0):.2f} s, trace+shade {sec['bounce_trace']:.2f} s, "
              f"dilate+write {sec['bounce_write']:.2f} s")
        print(f"bounce / transfer: {t_bounce / t_transfer:.3f} (target <= 0.5)")
        print(f"  {'set':8s} {'level':>5} {'texels':>8} {'skipped':>8} {'rays':>12} {'hits shaded':>12} "
              f"{'seconds':>8} {'Mrays/s':>8}")
        for r in b["sets"]:
            sec = r.get("seconds", 0.0)
            print(f"  {r['name']:8s} {r['level']:5d} {r['texels']:8d} {r.get('skipped_texels', r['texels']):8d} "
                  f"{r['rays_traced']:12,d} {r['hits_shaded']:12,d} {sec:8.2f} "
                  f"{(r['rays_traced'] / sec / 1e6 if sec else 0):8.2f}")
        print(f"total: {b['rays_traced']:,} rays, {b['hits_shaded']:,} shading evaluations; "
              f"trace+shade {m['seconds']['bounce_trace']:.2f} s, dilate+write {m['seconds']['bounce_write']:.2f} s")
        print(f"bounce texture bytes on disk: {sum(os.path.getsize(os.path.join(d, f)) for f in b['files']):,}")
        print(f"hit shading: {', '.join(sorted({r.get('hit_shading', '?') for r in b['sets']}))} "
              f"(numba {'off or missing: PRTT_NO_NUMBA or not installed' if not jit.available() else 'on'})")
        if b.get("stopped_early"):
            print(f"stopped early: {b['stopped_early']}")
    if args.combined:
        with tempfile.TemporaryDirectory(prefix="prtt-bench-") as d:
            t = time.perf_counter()
            mb = bake_scene(sc, d, st, light=light)
            t_both = time.perf_counter() - t
        print(f"default bake (transfer + {args.bounces} bounce(s), one run): {t_both:.2f} s = "
              f"{t_both / t_transfer:.3f} x the transfer-only bake (target <= 1.5)")
        sec = mb["seconds"]
        tr = sum(sec[k] for k in ("bvh", "analytic_test", "gbuffer", "trace", "dilate", "write"))
        bo = bounce_seconds(sec)
        print(f"within that bake: transfer stages {tr:.2f} s (bvh, analytic test, G-buffer, trace, dilate, write), "
              f"bounce stages {bo:.2f} s (exit {sec['bounce_exit']:.2f}, trace+shade {sec['bounce_trace']:.2f}, "
              f"dilate+write {sec['bounce_write']:.2f}): ratio {bo / tr:.3f}")
    return 0
