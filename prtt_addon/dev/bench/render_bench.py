"""``python -m prtt_addon.dev.bench render``: preview frame time per mode vs
triangles and resolution.

Scenes (bench/scene_library.py): the room-class scene (21K triangles) alone and with
4 and 18 copies of the 69K-triangle bunny (~300K and ~1.27M triangles, every
one drawn, each copy with its own 256^2 texture set), baked once with 32 rays,
per-vertex transfer and one bounce (cached in .cache/bench/render-*).

Each frame is the preview's own draw code (blender/preview/renderer.py: depth
pre-pass for the fragment modes, then shading) into a float32 offscreen
buffer; a 1-pixel read-back waits for the GPU to finish. The first frame
(shader compile, uploads) is reported separately. The camera sees the room
from its open side, so most pixels hold geometry: the fragment modes' cost
is then bounded by pixels, not triangles (the paper's "lower bound on FPS").

On a machine without a GPU this runs on Mesa llvmpipe (the CPU); the numbers
then measure a software rasteriser, not a graphics card.
"""
from __future__ import annotations

import argparse
import csv
import os
import time

import numpy as np

from . import figures, scene_library

MODES = ("tpfl", "tp", "diffuse", "vertex-tpfl", "vertex-tp")
BUNNIES = {"21K": 0, "300K": 4, "1.3M": 18}


def baked_preview(bunnies: int, light, *, bands: int = 5, rays: int = 32):
    """(PreviewScene, triangles, bake seconds) of the scaling scene with ``bunnies`` copies."""
    from ...core.bake.pipeline.context import BakeSettings
    from ...core.bake.pipeline.runner import bake_scene
    from ...core.preview.pack import from_core_scene
    sc = scene_library.render_scaling_scene(bunnies)
    sc = scene_library.with_room_materials(sc)
    out = os.path.join(scene_library.CACHE, f"render-{bunnies}-{scene_library.layout_code()}")
    t = time.perf_counter()
    st = BakeSettings(bands=bands, rays=rays, vertex_mode=True, bounces=1, bounce_rays=16, bounce_mode="baked")
    print("settings of the bake drawn: " + figures.settings_line(st, BakeSettings()))
    bake_scene(sc, out, st, light=light)
    seconds = time.perf_counter() - t
    return from_core_scene(sc, out, light, bands), sc.n_triangles, seconds


def camera(width: int, height: int):
    from ...core.preview.reference import look_at, perspective
    eye = np.array([0.0, -5.6, 2.3])
    vp = perspective(62.0, width / height) @ look_at(eye, (0.0, 0.6, 0.7))
    return vp, np.array([*eye, 1.0])


def time_frames(renderer, ps, mode, width, height, frames):
    """(first frame seconds, median seconds of the next ``frames``, FrameStats)."""
    import gpu

    from ...blender.preview.renderer import read_pixels
    vp, cam = camera(width, height)
    off = gpu.types.GPUOffScreen(width, height, format="RGBA32F")
    times = []
    try:
        with off.bind():
            fb = gpu.state.active_framebuffer_get()
            for _ in range(frames + 1):
                t = time.perf_counter()
                fb.clear(color=(0.0, 0.0, 0.0, 0.0), depth=1.0)
                stats = renderer.draw(ps, mode, vp, cam)
                buf = gpu.types.Buffer("FLOAT", 4)
                fb.read_color(0, 0, 1, 1, 4, 0, "FLOAT", data=buf)   # waits for the frame
                times.append(time.perf_counter() - t)
            covered = float((read_pixels(fb, width, height)[..., 3] > 0.5).mean())
        renderer.end_frame()
    finally:
        off.free()
    return times[0], float(np.median(times[1:])), stats, covered


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench render", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", default="21K,300K,1.3M", help=f"comma list of {', '.join(BUNNIES)}")
    p.add_argument("--sizes", default="640x360,1280x720,1920x1080", help="comma list of WxH")
    p.add_argument("--modes", default=",".join(MODES))
    p.add_argument("--frames", type=int, default=3, help="timed frames per point (median)")
    p.add_argument("--csv", help="also write the table to this CSV file")
    args = p.parse_args(argv)
    import bpy  # noqa: F401  (Blender as a module provides gpu)
    import gpu

    from ...blender.preview.offscreen import ensure_gpu
    from ...blender.preview.renderer import Renderer
    from ...core.light.envmap import environment_light
    ensure_gpu()
    print(f"GPU: {gpu.platform.renderer_get()} ({gpu.platform.backend_type_get()}), {os.cpu_count()} CPU cores")
    light = environment_light("forest", 5)
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    modes = args.modes.split(",")
    rows = []
    print(f"{'scene':>6} {'triangles':>10} {'size':>10} {'mode':>12} {'first ms':>9} {'frame ms':>9} "
          f"{'FPS':>7} {'ns/pixel':>9} {'covered':>8}")
    for name in args.scenes.split(","):
        ps, tris, bake_s = baked_preview(BUNNIES[name], light)
        verts = sum(m.positions.shape[0] for m in ps.meshes)
        print(f"# {name}: {tris} triangles, {verts} vertices after merging, bake {bake_s:.1f} s "
              f"(cached when unchanged)")
        renderer = Renderer()
        for w, h in sizes:
            for mode in modes:
                first, frame, stats, covered = time_frames(renderer, ps, mode, w, h, args.frames)
                row = {"scene": name, "triangles": tris, "vertices": verts, "width": w, "height": h,
                       "mode": mode, "first_ms": 1000 * first, "frame_ms": 1000 * frame, "fps": 1.0 / frame,
                       "ns_per_pixel": 1e9 * frame / (w * h), "covered": covered}
                rows.append(row)
                print(f"{name:>6} {tris:10d} {f'{w}x{h}':>10} {mode:>12} {row['first_ms']:9.0f} "
                      f"{row['frame_ms']:9.1f} {row['fps']:7.2f} {row['ns_per_pixel']:9.1f} {covered:8.2f}",
                      flush=True)
        renderer.free()
    _summary(rows)
    if args.csv:
        with open(args.csv, "w", newline="", encoding="utf-8") as f:
            wr = csv.DictWriter(f, fieldnames=list(rows[0]))
            wr.writeheader()
            wr.writerows(rows)
        print(f"wrote {args.csv}")
        # the date, machine and GPU beside it, for bench figures
        figures.write_record(f"{args.csv}.meta.json", "bench render", argv,
                             {"gpu": f"{gpu.platform.renderer_get()} ({gpu.platform.backend_type_get()})"})
    return 0


def _summary(rows) -> None:
    """Frame time growth from the smallest to the largest scene, per mode, at the largest size."""
    if not rows:
        return
    big = max((r["width"] * r["height"], r["width"], r["height"]) for r in rows)[1:]
    sel = [r for r in rows if (r["width"], r["height"]) == big]
    scenes_ = sorted({r["triangles"] for r in sel})
    if len(scenes_) < 2:
        return
    print(f"\nframe time at {big[0]}x{big[1]}, {scenes_[-1]} vs {scenes_[0]} triangles "
          f"({scenes_[-1] / scenes_[0]:.0f}x more):")
    for mode in sorted({r["mode"] for r in sel}, key=MODES.index):
        a = next(r for r in sel if r["mode"] == mode and r["triangles"] == scenes_[0])
        b = next(r for r in sel if r["mode"] == mode and r["triangles"] == scenes_[-1])
        print(f"  {mode:12s} {a['frame_ms']:8.1f} ms -> {b['frame_ms']:8.1f} ms  (x{b['frame_ms'] / a['frame_ms']:.2f})")
