"""Offscreen preview renders: the viewport's draw code into an image.

Used by ``python -m prtt_addon render``, ``blender -c prtt render``, the
Render Preview operator, the docs' pictures and the accuracy tests.

In background mode Blender's ``gpu`` module refuses to draw until something
has initialised the GPU; :func:`ensure_gpu` does that with one 8x8 Workbench
render of a temporary scene (removed again), which works on Mesa's llvmpipe
on machines without a GPU.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import bpy
import numpy as np

from ..shader_source import MODES


class RenderError(ValueError):
    """The render cannot be made as asked; the message says why."""


def gpu_ready() -> bool:
    import gpu
    try:
        gpu.platform.backend_type_get()
        return True
    except SystemError:
        return False


def ensure_gpu() -> None:
    """Make Blender's gpu module usable (background mode: one tiny Workbench render)."""
    if gpu_ready():
        return
    scene = bpy.data.scenes.new("__prtt_gpu_init")
    cam_data = bpy.data.cameras.new("__prtt_gpu_init")
    cam = bpy.data.objects.new("__prtt_gpu_init", cam_data)
    try:
        scene.collection.objects.link(cam)
        scene.camera = cam
        scene.render.engine = "BLENDER_WORKBENCH"
        scene.render.resolution_x = scene.render.resolution_y = 8
        scene.render.resolution_percentage = 100
        bpy.ops.render.render(scene=scene.name)
    finally:
        bpy.data.objects.remove(cam)
        bpy.data.cameras.remove(cam_data)
        bpy.data.scenes.remove(scene)
    if not gpu_ready():
        raise RenderError("Blender's GPU module could not be initialised (no OpenGL/EGL driver? "
                          "install Mesa: libegl1 libegl-mesa0 libgl1-mesa-dri)")


def camera_view(camera_ob, depsgraph, width: int, height: int, scene=None) -> tuple[np.ndarray, np.ndarray]:
    """(view_projection (4, 4), camera (4,)) of a camera object for a width x height image."""
    r = scene.render if scene is not None else None
    proj = camera_ob.calc_matrix_camera(depsgraph, x=width, y=height,
                                        scale_x=r.pixel_aspect_x if r else 1.0,
                                        scale_y=r.pixel_aspect_y if r else 1.0)
    M = np.array(camera_ob.matrix_world, dtype=np.float64)
    view = np.linalg.inv(M)
    vp = np.array(proj, dtype=np.float64) @ view
    if camera_ob.data.type == "ORTHO":
        z = M[:3, 2] / np.linalg.norm(M[:3, 2])
        return vp, np.array([*z, 0.0])
    return vp, np.array([*M[:3, 3], 1.0])


def region_view(rv3d) -> tuple[np.ndarray, np.ndarray]:
    """(view_projection, camera) of a 3D viewport's region data."""
    vp = np.array(rv3d.perspective_matrix, dtype=np.float64)
    inv = np.linalg.inv(np.array(rv3d.view_matrix, dtype=np.float64))
    if rv3d.is_perspective:
        return vp, np.array([*inv[:3, 3], 1.0])
    z = inv[:3, 2] / np.linalg.norm(inv[:3, 2])
    return vp, np.array([*z, 0.0])


def exposure_of(scene) -> float:
    """Scene > Color Management > Exposure as a multiplier."""
    return float(2.0 ** scene.view_settings.exposure)


def render_scene(context, *, mode: str = "tpfl", camera: str | None = None, size=None,
                 bounces: bool = True, prepass: bool = True, renderer=None):
    """Render the scene's last bake offscreen. Returns (pixels (H, W, 4) linear
    RGBA row 0 at the bottom, FrameStats, PreviewStatus, seconds).

    The exposure is not applied to the pixels (write_image applies it)."""
    from . import gpu_preview, preview_scene
    if mode not in MODES:
        raise RenderError(f"unknown mode {mode!r}; use one of {', '.join(MODES)}")
    scene = context.scene
    cam = scene.objects.get(camera) if camera else scene.camera
    if cam is None:
        raise RenderError(f"no camera {camera!r} in the scene" if camera else
                          "the scene has no camera: add one or pass --camera NAME")
    if cam.type != "CAMERA":
        raise RenderError(f"{cam.name!r} is not a camera")
    if size is None:
        pct = scene.render.resolution_percentage / 100.0
        size = (max(1, int(scene.render.resolution_x * pct)), max(1, int(scene.render.resolution_y * pct)))
    w, h = size
    if not (1 <= w <= 16384 and 1 <= h <= 16384):
        raise RenderError(f"image size {w}x{h} is outside 1..16384")
    ensure_gpu()
    ps, status = preview_scene.collect(context, use_bounces=bounces)
    if ps is None:
        raise RenderError("; ".join(t for _, t in status.messages) or "nothing to render")
    depsgraph = context.evaluated_depsgraph_get()
    vp, cam_vec = camera_view(cam.evaluated_get(depsgraph), depsgraph, w, h, scene)
    renderer = renderer or gpu_preview.Renderer()
    t = time.perf_counter()
    pixels, stats = gpu_preview.render_offscreen(renderer, ps, mode, vp, cam_vec, w, h, prepass=prepass)
    return pixels, stats, status, time.perf_counter() - t


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 1920x1080, got {text!r}") from None
    return w, h


def render_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description="Render the PRTT preview of a baked .blend offscreen "
                                "(the viewport's shaders; Mesa llvmpipe where there is no GPU).")
    p.add_argument("blend", help="a .blend file that has been baked")
    p.add_argument("--out", required=True, help="image file: .png (sRGB, 8 bit) or .exr (linear float)")
    p.add_argument("--mode", default="tpfl", choices=list(MODES))
    p.add_argument("--camera", help="camera object (default: the scene camera)")
    p.add_argument("--size", type=parse_size, help="WxH pixels (default: the scene's render size)")
    p.add_argument("--scene", help="scene name (default: the file's active scene)")
    p.add_argument("--no-bounces", dest="bounces", action="store_false", help="leave out bounce textures")
    return p


def render_file(argv, prog="prtt render") -> int:
    """Open a .blend and render its preview. Exit status 0 ok, 1 failed."""
    args = render_parser(prog).parse_args(argv)
    ext = os.path.splitext(args.out)[1].lower()
    if ext not in (".png", ".exr"):
        print(f"prtt: error: --out must end in .png or .exr, got {args.out!r}", file=sys.stderr)
        return 1
    from ..core.image_write import write_image
    from .cli import open_scene
    scene = open_scene(args.blend, args.scene)
    if scene is None:
        return 1
    try:
        with bpy.context.temp_override(scene=scene):
            pixels, stats, status, seconds = render_scene(bpy.context, mode=args.mode, camera=args.camera,
                                                          size=args.size, bounces=args.bounces)
        for level, text in status.messages:
            print(f"prtt: {level.lower()}: {text}", file=sys.stderr if level != "INFO" else sys.stdout)
        for name, why in stats.skipped.items():
            print(f"prtt: warning: {name} not drawn: {why}", file=sys.stderr)
        path = write_image(os.path.abspath(args.out), pixels, exposure=exposure_of(scene))
    except (ValueError, OSError) as exc:
        print(f"prtt: error: {exc}", file=sys.stderr)
        return 1
    h, w = pixels.shape[:2]
    print(f"prtt: rendered {args.mode} {w}x{h}, {len(stats.drawn)} object(s), {stats.triangles} triangles, "
          f"{1000 * seconds:.0f} ms -> {path}")
    return 0
