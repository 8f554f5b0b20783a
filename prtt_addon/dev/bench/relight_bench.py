"""``python -m prtt_addon.dev.bench relight``: relightable bounces against a full
rebake at every World rotation, bake time, frame time and bytes, in one run.

Scenes: the room-class scene (1024^2 atlas, 14 materials, nearly all glossy)
and a floor-and-ball scene (a 4 m glossy floor, a glossy orange ball and a
diffuse box; floor 512^2, objects 256^2), Blender's "forest" HDRI, one
bounce, the default settings otherwise (tuning auto).

Per scene: the transfer is baked once; at each World rotation about Z (0
... 330 degrees in 30 degree steps) the bounce light is rebaked as ``baked``
under the turned light and, beside it, as ``relightable`` (which does not
depend on the light: the same texture every time), with the same rays and
seeds; one untimed bounce bake of each mode comes first (a process's first
level loads its kernels). Timing the two modes in pairs lets the machine's
drifts hit both: the bake ratio is the median relightable bounce time over
the median baked one, and the pairs' ratios give its spread. Both are
rendered by the viewport's shaders (offscreen, llvmpipe where there is no
GPU) under the turned light; the error is the relative RMSE of the relit
frame against the rebaked one over covered pixels (the band limit of
relightable glossy bounce light, docs/shading.md). Then the frame time of
each (median of 9 after the first, the two interleaved), what a new light adds to the first
frame under it (the GPU relight pass, what turning the World costs), and
the bounce texture bytes of each. Writes
docs/bench/relight.csv and docs/images/relight_room_90.png (the room at 90°:
the baking angle, relit, rebaked). ``--quick`` is a smoke test at toy sizes.
"""
from __future__ import annotations

import argparse
import math
import os
import tempfile
import time

import numpy as np

from ...core.bake.pipeline.context import BakeSettings, bounce_seconds
from ...core.bake.pipeline.runner import bake_scene
from ...core.light.envmap import environment_light
from ...core.sh.rotation import rotate_zyz
from . import figures, scene_library
from . import meshgen as mg
from .sweep import Previewer, write_csv
from .texture_error import image_error

DOCS_BENCH = os.path.join(scene_library.ROOT, "docs", "bench")
FLOOR = {"name": "floor", "base_color": [0.55, 0.5, 0.45], "roughness": 0.3, "specular": 0.5}
BALL = {"name": "ball", "base_color": [0.9, 0.6, 0.2], "roughness": 0.35, "metallic": 0.4}
BOX = {"name": "box", "base_color": [0.2, 0.7, 0.3], "specular": 0.0}


def ball_scene(resolution: int):
    """The floor-and-ball scene: floor at ``resolution``, ball and box at half."""
    from ...core.model.scene import validate
    objs = [("floor", mg.plane(4.0, 4.0)),
            ("ball", mg.uv_sphere(0.6, 48, 24).transformed(translate=(-0.5, 0.2, 0.65))),
            ("box", mg.box((0.7, 0.7, 0.7), (0.8, -0.4, 0.35)).transformed(rotate_z=0.5))]
    half = max(32, resolution // 2)
    sc = mg.assemble(objs, resolution=resolution, resolutions={"ball": half, "box": half})
    sc.materials = [FLOOR, BALL, BOX]
    sc.material_id = sc.object_id.copy()
    validate(sc)
    return sc, {"eye": (3.2, -3.4, 2.6), "target": (0.0, 0.0, 0.3)}


def bake_relightable(sc, folder: str, light) -> dict:
    """Rebake the relightable bounce in ``folder`` (its transfer up to date: bounces only)."""
    for f in os.listdir(folder):
        if f.endswith(".relight.exr"):
            os.remove(os.path.join(folder, f))
    m = bake_scene(sc, folder, BakeSettings(bounces=1, bounce_mode="relightable"), light=light)
    assert m["transfer_reused"]
    return m


def turned(light: np.ndarray, degrees: float) -> np.ndarray:
    """(K, 3) SH light turned about Z."""
    a = math.radians(degrees)
    L = np.asarray(light, np.float64)
    return rotate_zyz(L.T, np.full(3, a), np.zeros(3), np.zeros(3)).T


def frame_ms(pairs: list, frames: int = 9) -> list[float]:
    """Median frame time (ms) of each (Previewer, folder) pair, their frames
    interleaved (llvmpipe's frame times drift by tens of per cent within a
    minute: each drift hits every folder); one Previewer per folder, so that
    each keeps its textures uploaded. The first frame of each (uploads,
    shader compile, the relight pass) is not counted."""
    for view, d in pairs:
        view.render(d)
    times = [[] for _ in pairs]
    for _ in range(frames):
        for (view, d), ts in zip(pairs, times):
            t = time.perf_counter()
            view.render(d)
            ts.append(time.perf_counter() - t)
    return [1000.0 * float(np.median(ts)) for ts in times]


#: Display exposure of the figure (the forest HDRI through the room's camera).
FIGURE_EXPOSURE = 1.0


def save_figure(path: str, images: dict, degrees: float, err: float) -> str:
    """The room at the turned World: the frame at the baking angle, relit, and rebaked."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ...core.io.image_write import srgb_encode
    titles = {"baked": "World at the baking angle (0°)", "relit": f"World turned {degrees:g}°: relit, no rebake",
              "rebaked": f"World turned {degrees:g}°: full rebake"}
    fig, axes = plt.subplots(1, 3, figsize=(15, 3.3))
    for ax, key in zip(axes, ("baked", "relit", "rebaked")):
        img = images[key]
        rgb = srgb_encode(FIGURE_EXPOSURE * img[::-1, :, :3]) * img[::-1, :, 3:] + (1 - img[::-1, :, 3:])
        ax.imshow(np.clip(rgb, 0, 1))
        ax.set_axis_off()
        ax.set_title(titles[key] + (f"\nrelit vs rebaked {100 * err:.2f} %" if key == "relit" else ""), fontsize=9)
    fig.tight_layout()
    os.makedirs(os.path.dirname(path), exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def run_scene(name: str, sc, camera: dict, light, size, angles, tmp: str, figure: str | None = None) -> list:
    rl, bk = os.path.join(tmp, f"{name}-relight"), os.path.join(tmp, f"{name}-baked")
    for mode in ("relightable", "baked"):
        print(f"{name} settings, {mode}: " + figures.settings_line(BakeSettings(bounces=1, bounce_mode=mode),
                                                                    BakeSettings()))
    bake_scene(sc, rl, BakeSettings(bounces=0), light=light)
    bake_scene(sc, bk, BakeSettings(bounces=0), light=light)
    # One untimed bounce bake of each mode first: a process's first level loads its kernels.
    m = bake_relightable(sc, rl, light)
    bake_scene(sc, bk, BakeSettings(bounces=1, bounce_mode="baked"), light=light)
    rl_bytes = sum(os.path.getsize(os.path.join(rl, f)) for f in m["bounce"]["files"])
    view = Previewer(sc, light, size, bounces=True, **camera)
    rows = []
    for deg in angles:
        L = turned(light, deg)
        view.light = L
        mb = bake_scene(sc, bk, BakeSettings(bounces=1, bounce_mode="baked"), light=L)
        assert mb["transfer_reused"]
        # The relightable bounce rebaked beside each baked one (it does not depend
        # on the light: the same texture every time), so the VM's drifts hit both.
        t_rl = bounce_seconds(bake_relightable(sc, rl, light)["seconds"])
        img_rl, img_bk = view.render(rl), view.render(bk)
        err = image_error(img_rl, img_bk)
        if figure and deg == 90.0:
            view.light = light
            base = view.render(rl)
            view.light = L
            save_figure(figure, {"baked": base, "relit": img_rl, "rebaked": img_bk}, deg, err)
        row = {"scene": name, "degrees": deg, "relit_vs_rebaked": err,
               "baked_bounce_seconds": bounce_seconds(mb["seconds"]), "relight_bounce_seconds": t_rl,
               "baked_bounce_bytes": sum(os.path.getsize(os.path.join(bk, f)) for f in mb["bounce"]["files"])}
        rows.append(row)
        print(f"  {name:6s} {deg:5.0f} deg  relit vs rebaked {100 * err:6.3f} %  (bounce: baked rebake "
              f"{row['baked_bounce_seconds']:5.2f} s, relightable {t_rl:5.2f} s)", flush=True)
    view.light = light
    bake_scene(sc, bk, BakeSettings(bounces=1, bounce_mode="baked"), light=light)
    other = Previewer(sc, light, size, bounces=True, **camera)
    f_bk, f_rl = frame_ms([(other, bk), (view, rl)])
    # A turned World: the first frame under each new light runs the relight pass.
    turns = []
    for deg in (10.0, 20.0, 30.0):
        view.light = turned(light, deg)
        t = time.perf_counter()
        view.render(rl)
        turns.append(1000.0 * (time.perf_counter() - t) - f_rl)
    view.light = light
    apply_ms = float(np.median(turns))
    t_bk = float(np.median([r["baked_bounce_seconds"] for r in rows]))
    t_rl = float(np.median([r["relight_bounce_seconds"] for r in rows]))
    pair = [r["relight_bounce_seconds"] / r["baked_bounce_seconds"] for r in rows]
    summary = {"scene": name, "median_relight_bounce_seconds": t_rl, "median_baked_bounce_seconds": t_bk,
               "bake_ratio": t_rl / t_bk, "bake_ratio_pairs_min": min(pair), "bake_ratio_pairs_max": max(pair),
               "relight_frame_ms": f_rl, "baked_frame_ms": f_bk,
               "frame_ratio": f_rl / f_bk, "relight_apply_ms": apply_ms, "relight_bytes": rl_bytes,
               "baked_bytes": rows[0]["baked_bounce_bytes"],
               "max_relit_vs_rebaked": max(r["relit_vs_rebaked"] for r in rows)}
    for r in rows:
        r.update({k: v for k, v in summary.items() if k not in r})
    print(f"  {name}: relightable bounce {t_rl:.2f} s vs baked {t_bk:.2f} s (x{t_rl / t_bk:.2f}, pairs "
          f"x{min(pair):.2f}-{max(pair):.2f}); frame "
          f"{f_rl:.1f} ms vs {f_bk:.1f} ms (x{f_rl / f_bk:.2f}); a new light adds {apply_ms:.0f} ms to its "
          f"first frame (the relight pass); "
          f"bytes {rl_bytes / 1e6:.1f} MB vs {summary['baked_bytes'] / 1e6:.1f} MB; relit vs rebaked at most "
          f"{100 * summary['max_relit_vs_rebaked']:.3f} %", flush=True)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench relight", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="toy sizes (a smoke test)")
    p.add_argument("--out", default=DOCS_BENCH, help="folder for relight.csv (default docs/bench)")
    p.add_argument("--figure", default=os.path.join(scene_library.ROOT, "docs", "images", "relight_room_90.png"),
                   help="the room at 90 deg: relit beside rebaked (with --quick: not written)")
    args = p.parse_args(argv)
    light = environment_light("forest", 5)
    if args.quick:
        res, size, angles = 64, (160, 90), (0.0, 90.0)
    else:
        res, size, angles = 1024, (640, 360), tuple(float(a) for a in range(0, 360, 30))
    rows = []
    with tempfile.TemporaryDirectory(prefix="prtt-bench-relight-") as tmp:
        sc, cam = ball_scene(res // 2)
        print(f"floor and ball: {sc.n_triangles} triangles, {sc.n_sets} sets", flush=True)
        rows += run_scene("ball", sc, cam, light, size, angles, tmp)
        sc = scene_library.room_scene(res, atlas=True, materials=True)
        print(f"room: {sc.n_triangles} triangles, {res}^2 atlas", flush=True)
        rows += run_scene("room", sc, {}, light, size, angles, tmp, figure=None if args.quick else args.figure)
    if not args.quick:
        os.makedirs(args.out, exist_ok=True)
        write_csv(os.path.join(args.out, "relight.csv"), rows)
    return 0
