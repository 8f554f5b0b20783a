"""The main job (``./prtt.sh demo``, ``python -m prtt_addon.dev.demo``).

In real Blender (bpy), through the add-on's own operators:

1. build the room-class demo scene: floor and walls of two triangles each, a
   table, rug, chairs, shelf, spot the cow, a metal sphere, a torus, a vase, a
   lamp; a glossy wooden floor with textured roughness and colour; Blender's
   "forest" HDRI as the World;
2. unwrap every object into one 1024^2 atlas (PRTT > Unwrap, Smart UV Project);
3. bake transfer, per-vertex transfer and one bounce (PRTT > Bake Transfer,
   in the worker process; relightable, the default bounce mode);
4. render the preview offscreen from the scene camera: fragment TPFL (PRTT)
   and vertex TPFL (the traditional baseline), side by side, into one image;
5. relightable bounces: turn the World by 90 degrees and render step 3's
   bounces relit, beside a full rebake of the bounce (``--bounce-mode
   baked``) under the turned World (in a copy of the texture folder: the
   saved .blend and its textures stay as step 3 made them). ``--no-relight``
   skips this step.

It prints each stage's time and where everything went (``out/demo`` by
default: the .blend, the textures, the pictures). Needs no network.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import time

import numpy as np

from .. import register
from ..cli_options import CheckedValue, int_range, parse_size
from ..core import settings_schema as schema
from ..core.bake.pipeline.context import bounce_seconds
from ..core.io.image_write import srgb_encode, write_image
from ..core.settings_schema import BY_NAME as _SETTINGS
from .bench.texture_error import image_error

_BOUNCE_RAYS_DEFAULT = _SETTINGS["bounce_rays"].default

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _world_image_beside(bpy, out_dir: str) -> None:
    """Copy the World's HDRI (Blender's studio light, inside its install or
    the .venv) into ``out_dir`` and point the World at it ``//``-relative, so
    that a copied or moved demo folder still renders and exports."""
    for node in bpy.context.scene.world.node_tree.nodes:
        img = getattr(node, "image", None)
        if img is None or img.packed_file:
            continue
        src = bpy.path.abspath(img.filepath)
        dst = os.path.join(out_dir, os.path.basename(src))
        if os.path.abspath(src) != os.path.abspath(dst):
            shutil.copyfile(src, dst)
        img.filepath = "//" + os.path.basename(src)     # relative to the .blend saved beside it


def side_by_side(left: np.ndarray, right: np.ndarray, labels, path: str, *, exposure: float = 1.0,
                 title: str = "") -> str:
    """Two (H, W, 4) linear renders, row 0 at the bottom, as one labelled PNG
    (a label over each half, ``title`` over both)."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:                       # inside Blender's own Python: no labels
        return write_image(path, np.concatenate([left, right], axis=1), exposure=exposure)
    fig = labelled_figure(plt, left, right, labels, exposure=exposure, title=title)
    fig.savefig(path)
    plt.close(fig)
    return path


#: Points per inch, and the width of an average character in ems (DejaVu Sans):
#: what wraps a caption to the picture it stands over.
_PT, _EM = 72.0, 0.6


def _wrapped(text: str, width_px: float, size_pt: float) -> str:
    """``text`` wrapped to lines of at most ``width_px`` pixels at 100 dpi."""
    import textwrap
    chars = max(8, int(width_px / (size_pt * 100.0 / _PT * _EM)))
    return "\n".join(textwrap.wrap(text, chars)) if text else ""


def labelled_figure(plt, left: np.ndarray, right: np.ndarray, labels, *, exposure: float = 1.0, title: str = ""):
    """The matplotlib figure of :func:`side_by_side`: each picture at its
    pixel size, every caption wrapped to the width it has (at a small --size
    they ran into each other) and stacked above them at its measured height."""
    h, w = left.shape[:2]
    label_size, title_size = (11, 10) if w >= 480 else (8, 7)
    pad = 4.0                                               # pixels between the rows
    fig = plt.figure(figsize=(2 * w / 100, 1.0), dpi=100)
    caps = [fig.text(0.25 + 0.5 * k, 0.0, _wrapped(t, w - 2 * pad, label_size), fontsize=label_size,
                     ha="center", va="bottom") for k, t in enumerate(labels)]
    top = fig.text(0.5, 1.0, _wrapped(title, 2 * w - 2 * pad, title_size), fontsize=title_size,
                   ha="center", va="top") if title else None
    fig.canvas.draw()                                       # text sizes in pixels (points at a fixed dpi)
    r = fig.canvas.get_renderer()
    cap_h = max(c.get_window_extent(r).height for c in caps)
    title_h = top.get_window_extent(r).height + pad if top is not None else 0.0
    total = h + pad + cap_h + pad + title_h
    fig.set_size_inches(2 * w / 100, total / 100)
    for k, (img, cap) in enumerate(zip((left, right), caps)):
        ax = fig.add_axes((0.5 * k, 0.0, 0.5, h / total))
        rgb = srgb_encode(exposure * img[::-1, :, :3]) * img[::-1, :, 3:] + (1.0 - img[::-1, :, 3:])
        ax.imshow(np.clip(rgb, 0, 1), aspect="auto", interpolation="nearest")
        ax.set_axis_off()
        cap.set_y((h + pad) / total)
    if top is not None:
        top.set_y(1.0 - pad / total)
    return fig


def _bake_copy(bpy, bake_blocking, out_dir: str, home: str, mode: str, mapping, turn0: float) -> float:
    """Bake the bounces of ``mode`` in a copy of the texture folder ``home``
    (the transfer reused): relightable under the World as it was, baked
    under the World turned 90 degrees. Leaves the scene pointing at the
    copy (relight_step puts it back). Returns the bounce stages' seconds."""
    import shutil
    st = bpy.context.scene.prtt
    folder = os.path.join(out_dir, f"textures_{mode.lower()}_90")
    if os.path.isdir(folder):
        shutil.rmtree(folder)
    shutil.copytree(bpy.path.abspath(home), folder)
    st.output_dir, st.bounce_mode = folder, mode
    mapping.inputs["Rotation"].default_value[2] = turn0 + (math.pi / 2 if mode == "BAKED" else 0.0)
    outcome = bake_blocking(bpy.context)
    if outcome.status != "done":
        raise RuntimeError(outcome.message)
    if not outcome.manifest.get("transfer_reused"):
        raise RuntimeError(f"{folder}: the transfer was baked again, not reused")
    return bounce_seconds(outcome.manifest["seconds"])


def relight_step(bpy, out_dir: str, size, exposure: float, log=print) -> dict:
    """Step 5: the room's bounce light relit under a World turned by 90
    degrees, beside the bounce rebaked under it. Step 3's relightable
    bounces (the default bounce mode) are relit as they are; a mode step 3
    did not bake is baked in a copy of the texture folder (the transfer is
    reused there: only bounces are baked). Puts the scene's settings and
    World back afterwards. Returns the picture, the two renders, their
    relative RMSE and each mode's bounce seconds (the bake's stages)."""
    from ..blender.bake.run import bake_blocking  # needs bpy (see run)
    from ..blender.preview.offscreen import render_scene  # needs bpy (see run)
    st = bpy.context.scene.prtt
    world = bpy.context.scene.world
    mapping = next((n for n in world.node_tree.nodes if n.bl_idname == "ShaderNodeMapping"), None) if world else None
    if mapping is None:
        raise RuntimeError("the relight step turns the World's Mapping node, and this World has none")
    home, mode0, turn0 = st.output_dir, st.bounce_mode, mapping.inputs["Rotation"].default_value[2]
    shots, secs = {}, {}
    try:
        for mode in ("RELIGHTABLE", "BAKED"):
            if mode == "RELIGHTABLE" == mode0:
                # Step 3 baked them under the World as it was: turn it, and relight.
                with open(os.path.join(bpy.path.abspath(home), "manifest.json"), encoding="utf-8") as f:
                    secs["bake relightable"] = bounce_seconds(json.load(f)["seconds"])
            else:
                secs[f"bake {mode.lower()}"] = _bake_copy(bpy, bake_blocking, out_dir, home, mode, mapping, turn0)
            mapping.inputs["Rotation"].default_value[2] = turn0 + math.pi / 2
            t = time.perf_counter()
            shots[mode], _, status, _ = render_scene(bpy.context, mode="tpfl", size=size)
            secs[f"render {mode.lower()}"] = time.perf_counter() - t
            for level, text in status.messages:
                if level != "INFO":
                    log(f"      {level.lower()}: {text}")
    finally:
        st.output_dir, st.bounce_mode = home, mode0
        mapping.inputs["Rotation"].default_value[2] = turn0
    relit, rebaked = shots["RELIGHTABLE"], shots["BAKED"]
    rmse = image_error(relit, rebaked)          # bench relight's measure: RMSE over covered pixels / mean
    image = side_by_side(relit, rebaked,
                         ("relightable bounces, baked at 0\u00b0, relit with the World turned 90\u00b0",
                          "baked bounces, rebaked with the World turned 90\u00b0"),
                         os.path.join(out_dir, "demo_relight_90.png"), exposure=exposure,
                         title=f"turning the World without a rebake: image difference {100 * rmse:.2f} % "
                               f"(relative RMSE); bounce bake: relightable {secs['bake relightable']:.1f} s, "
                               f"baked at 90\u00b0 {secs['bake baked']:.1f} s")
    return {"image": image, "rmse": rmse, "seconds": secs, "shots": shots}


def run(out_dir: str, *, resolution: int = 1024, rays: int = 256, bounce_rays: int | None = None,
        size=(960, 540), relight: bool = True, log=print) -> dict:
    import bpy

    # The Blender side needs bpy: this module loads without it (the CLI's parser).
    from ..blender.bake.run import bake_blocking  # needs bpy (see above)
    from ..blender.blendfile import blend_relative  # needs bpy (see above)
    from ..blender.preview.offscreen import exposure_of, render_scene  # needs bpy (see above)
    from ..blender.shared import UV_MAP  # needs bpy (see above)
    from .bench.scene_build import demo_scene  # needs bpy (see above)
    t_all = time.perf_counter()
    times = {}
    n = 5 if relight else 4                  # steps
    os.makedirs(out_dir, exist_ok=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    if not hasattr(bpy.types.Scene, "prtt"):
        register()

    t = time.perf_counter()
    objects = demo_scene()
    tris = 0
    for ob in objects.values():
        ob.data.calc_loop_triangles()
        tris += len(ob.data.loop_triangles)
    times["build scene"] = time.perf_counter() - t
    log(f"[1/{n}] built the room-class scene: {len(objects)} objects, {tris} triangles "
        f"({times['build scene']:.1f} s)")

    st = bpy.context.scene.prtt
    st.output_dir = os.path.join(out_dir, "textures")
    st.resolution, st.rays, st.texture_sets, st.unwrap_method = resolution, rays, "ATLAS", "SMART"
    if bounce_rays is None:
        bounce_rays = int(_BOUNCE_RAYS_DEFAULT)
    st.bounces, st.bounce_rays, st.vertex_transfer = 1, bounce_rays, True
    for ob in bpy.context.view_layer.objects:
        ob.select_set(ob.type == "MESH")
    bpy.context.view_layer.objects.active = objects["floor"]
    t = time.perf_counter()
    if bpy.ops.prtt.unwrap() != {"FINISHED"}:
        raise RuntimeError("unwrap failed")
    times["unwrap"] = time.perf_counter() - t
    assert all(UV_MAP in ob.data.uv_layers for ob in objects.values())
    log(f"[2/{n}] unwrapped into one {resolution}x{resolution} atlas (Smart UV Project, "
        f"'{UV_MAP}' UV map) ({times['unwrap']:.1f} s)")

    t = time.perf_counter()

    def progress(e):
        if e.get("type") == "progress" and e.get("fraction") == 1.0:
            log(f"      {e.get('stage')} {e.get('set', '')} done")

    outcome = bake_blocking(bpy.context, force=True, on_event=progress)
    if outcome.status != "done":
        raise RuntimeError(outcome.message)
    times["bake"] = time.perf_counter() - t
    m = outcome.manifest
    sec = m["seconds"]
    b = m.get("bounce") or {}
    log(f"[3/{n}] baked transfer ({rays} rays/texel, {m['totals']['texels']:,} texels, "
        f"{m['totals']['rays_traced'] / 1e6:.0f}M rays), per-vertex transfer and "
        f"{b.get('levels', 0)} bounce ({bounce_rays} rays) in {times['bake']:.1f} s "
        f"[transfer {sec.get('trace', 0) + sec.get('gbuffer', 0) + sec.get('dilate', 0):.1f} s, "
        f"vertex {sec.get('vertex', 0):.1f} s, bounce {sec.get('bounce_trace', 0) + sec.get('bounce_write', 0):.1f} s]")
    blend = os.path.join(out_dir, "prtt_demo.blend")
    st.output_dir = blend_relative(bpy.path.abspath(st.output_dir), blend)   # //textures/: the folder can move
    _world_image_beside(bpy, out_dir)
    bpy.ops.wm.save_as_mainfile(filepath=blend)

    w, h = size
    shots = {}
    for mode in ("tpfl", "vertex-tpfl"):
        t = time.perf_counter()
        pixels, stats, status, _ = render_scene(bpy.context, mode=mode, size=(w, h))
        times[f"render {mode}"] = time.perf_counter() - t
        shots[mode] = pixels
        for level, text in status.messages:
            if level != "INFO":
                log(f"      {level.lower()}: {text}")
    exposure = exposure_of(bpy.context.scene)
    files = [write_image(os.path.join(out_dir, f"demo_{mode}.png"), px, exposure=exposure)
             for mode, px in shots.items()]
    st = bpy.context.scene.prtt
    image = side_by_side(shots["vertex-tpfl"], shots["tpfl"],
                         (f"vertex TPFL: per-vertex transfer at the {tris} triangles' vertices "
                          f"(the traditional baseline)",
                          f"PRTT: fragment TPFL, {resolution}\u00b2 transfer texture + {st.bounces} bounce"),
                         os.path.join(out_dir, "demo_side_by_side.png"), exposure=exposure,
                         title=f"room-class scene, {tris} triangles; {st.bands} SH bands, {rays} rays/texel, "
                               f"{bounce_rays} bounce rays; light: {json.loads(st.last_bake).get('light') or 'World'}; "
                               f"{w}x{h}, rendered on {_gpu_name()}")
    log(f"[4/{n}] rendered {w}x{h} previews on {_gpu_name()}: fragment TPFL {times['render tpfl']:.1f} s, "
        f"vertex TPFL {times['render vertex-tpfl']:.1f} s (first frames: shader compile and uploads included)")
    rl = None
    if relight:
        t = time.perf_counter()
        rl = relight_step(bpy, out_dir, (w, h), exposure, log)
        times["relight step"] = time.perf_counter() - t
        sec = rl["seconds"]
        log(f"[5/5] relightable bounces (bounce stages {sec['bake relightable']:.1f} s): the World turned 90\u00b0 "
            f"and relit; a baked bounce rebaked under the turned World took {sec['bake baked']:.1f} s; "
            f"the two pictures differ by {100 * rl['rmse']:.2f} % (relative RMSE)")
    times["total"] = time.perf_counter() - t_all
    log("")
    log(f"side by side:  {os.path.relpath(image)}")
    if rl is not None:
        log(f"relit at 90\u00b0: {os.path.relpath(rl['image'])}")
    log(f"single images: {', '.join(os.path.relpath(f) for f in files)}")
    log(f"the .blend:    {os.path.relpath(blend)}   (open it in Blender with PRTT installed: "
        f"Sidebar > PRTT > Preview)")
    log(f"textures:      {os.path.relpath(bpy.path.abspath(st.output_dir))}/ ({', '.join(m['files'])})")
    log("stage times: " + ", ".join(f"{k} {v:.1f} s" for k, v in times.items()))
    return {"image": image, "files": files, "blend": blend, "times": times, "manifest": m, "shots": shots,
            "relight": rl}


def _gpu_name() -> str:
    import gpu
    try:
        return gpu.platform.renderer_get()
    except SystemError:
        return "the GPU"


#: The smallest atlas the demo bakes: a Smart UV Project of the room with its
#: island margins needs some texels per island.
MIN_DEMO_RESOLUTION = 16


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The demo's options, each checked here (exit 2 naming the option) before
    any work: the ranges are the bake's (core/settings_schema.py)."""
    def checked(name, lo=None):
        s = schema.get(name)
        lo = s.lo if lo is None else lo
        return dict(action=CheckedValue, convert=int_range(lo, s.hi), metavar="N",
                    help=f"{s.help} ({lo}..{s.hi} {s.unit})")
    p.add_argument("--out", default=os.path.join(ROOT, "out", "demo"), help="output folder (default out/demo)")
    p.add_argument("--resolution", default=1024, **checked("resolution", MIN_DEMO_RESOLUTION))
    p.add_argument("--rays", default=256, **checked("rays"))
    p.add_argument("--bounce-rays", default=None, **checked("bounce_rays"))
    p.add_argument("--size", default=(960, 540), type=parse_size, metavar="WxH",
                   help="each preview image, WxH pixels (default 960x540)")
    p.add_argument("--no-relight", dest="relight", action="store_false",
                   help="skip step 5 (relightable bounces, the World turned by 90 degrees)")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.demo", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(p)
    return run_args(p.parse_args(argv))


def run_args(args) -> int:
    try:
        import bpy  # noqa: F401
    except ImportError:
        print("prtt: error: the demo needs Blender as a Python module (pip install bpy==5.0.1; "
              "./prtt.sh demo installs it)", file=sys.stderr)
        return 1
    w, h = args.size
    print("PRTT demo: room-class scene, unwrap, bake (transfer + 1 bounce), TPFL vs vertex-TPFL preview")
    try:
        run(args.out, resolution=args.resolution, rays=args.rays, bounce_rays=args.bounce_rays, size=(w, h),
            relight=args.relight)
    except (RuntimeError, ValueError, OSError) as exc:
        print(f"prtt: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
