"""Offscreen preview renders: the viewport's draw code into an image.

Used by ``python -m prtt_addon render``, ``blender -c prtt render``, the
Render Preview operator, the docs' pictures and the accuracy tests.

In background mode Blender's ``gpu`` module refuses to draw until something
has initialised the GPU; :func:`ensure_gpu` does that with one 8x8 Workbench
render of a temporary scene (removed again), which works on Mesa's llvmpipe
on machines without a GPU.

An offscreen render never returns (or writes) a partial or made-up image:
every failure is a :class:`RenderError` whose message names what the user
gave (the .blend, the texture file, the ``--out`` path) and what to do, and
limits are checked before anything large is allocated (the GPU's largest
image, the memory the frame and its file need). ``render_file`` turns that
into exit status 1 with the message on stderr, leaving ``--out`` untouched;
docs/preview.md lists the cases.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import bpy
import numpy as np

from ...cli_options import choice_option, parse_size
from ...core.base.atomic import TMP_PREFIX
from ...core.base.memory import GiB, MiB, available_bytes, resident_bytes
from ...core.io.image_write import WRITE_BYTES_PER_PIXEL, ImageWriteError, write_image
from ...core.preview.shader_source import MODES
from ..blendfile import native_stderr_filtered, open_scene
from . import colour_management as colour
from . import drawlist
from . import renderer as gpu_preview
from .shaders import ShaderError

#: Peak bytes per pixel while a frame renders, measured on llvmpipe at 2048^2
#: and 4096^2 (VmHWM, 56.1): the RGBA32F colour target (16), its depth buffer
#: (4), the read-back buffer (16) and its numpy copy (16). Rounded up. Of
#: that, 40 stay resident while the image is encoded (the pixels and what the
#: driver keeps of the freed frame), so the file's share is added on top.
RENDER_BYTES_PER_PIXEL = 64
#: Kept in memory instead of written (the Render Preview operator): the
#: exposed copy and Blender's float image.
KEEP_BYTES_PER_PIXEL = 32
#: The largest share of available memory a render may plan to use (as the bake's check).
MEMORY_FRACTION = 0.8
#: Image files render_file writes.
IMAGE_EXTENSIONS = (".png", ".exr")


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
        with native_stderr_filtered():
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


def frame_bytes(width: int, height: int, ext: str | None = None) -> int:
    """Peak memory of rendering a width x height frame and writing it as
    ``ext`` (.png/.exr; None: kept as a Blender image). On llvmpipe the GPU
    buffers are host memory too; on a GPU this overestimates, erring on the
    safe side."""
    return width * height * (RENDER_BYTES_PER_PIXEL + WRITE_BYTES_PER_PIXEL.get(ext, KEEP_BYTES_PER_PIXEL))


def check_frame(width: int, height: int, what: str, ext: str | None = None) -> None:
    """Refuse a frame the GPU or the memory cannot hold, before allocating it.

    ``what`` names the size as the user gave it ("--size 100000x10").
    Call after :func:`ensure_gpu` (the limits come from the GPU module)."""
    import gpu
    limit = gpu.capabilities.max_texture_size_get()
    if width > limit or height > limit:
        raise RenderError(f"{what}: larger than this GPU's largest image, {limit} pixels per side "
                          f"({gpu.platform.renderer_get()}); render smaller (--size WxH)")
    needed, avail = frame_bytes(width, height, ext), available_bytes()
    if avail is not None and needed > MEMORY_FRACTION * avail:
        raise RenderError(f"{what}: the render and its image need about {needed / GiB:.1f} GiB of memory, "
                          f"more than {MEMORY_FRACTION:.0%} of the {avail / GiB:.1f} GiB available; "
                          f"render smaller (--size WxH)")


def check_memory(renderer, ps, mode: str, width: int, height: int, ext: str | None = None) -> tuple:
    """Refuse a render whose textures, staging and frame would not fit in the
    memory available, before any is read. This process's peak RSS is then
    estimated as what it holds now, the textures still to upload
    (Renderer.planned_bytes: on llvmpipe the GPU's memory is this process's),
    the largest upload band and the frame (:func:`frame_bytes`). Returns
    (bytes held now, bytes to come): their sum is the estimated peak RSS."""
    textures, staging = renderer.planned_bytes(ps, mode)
    needed = textures + staging + frame_bytes(width, height, ext)
    avail = available_bytes()
    if avail is not None and needed > MEMORY_FRACTION * avail:
        raise RenderError(f"the baked textures ({textures / GiB:.2f} GiB on the GPU) and the {width}x{height} image need "
                          f"about {needed / GiB:.1f} GiB of memory, more than {MEMORY_FRACTION:.0%} of the "
                          f"{avail / GiB:.1f} GiB available; bake at a lower resolution or a larger Bounce "
                          f"Downscale, render --no-bounces, or render smaller (--size WxH)")
    return resident_bytes() or 0, needed


def scene_camera(scene, camera: str | None):
    """The named camera object, else the scene's; RenderError when there is none."""
    cam = scene.objects.get(camera) if camera else scene.camera
    if cam is None:
        raise RenderError(f"no camera {camera!r} in the scene" if camera else
                          "the scene has no camera: add one or pass --camera NAME")
    if cam.type != "CAMERA":
        raise RenderError(f"{cam.name!r} is not a camera")
    return cam


def frame_size(scene, size) -> tuple[int, int, str]:
    """(width, height, how the user asked for it): ``size`` or the scene's render size."""
    if size is not None:
        w, h = size
        what = f"--size {w}x{h}"
    else:
        pct = scene.render.resolution_percentage / 100.0
        w, h = max(1, int(scene.render.resolution_x * pct)), max(1, int(scene.render.resolution_y * pct))
        what = f"the scene's render size {w}x{h} (Output Properties > Format)"
    if w < 1 or h < 1:
        raise RenderError(f"{what}: width and height must be at least 1")
    return w, h, what


def _names(names: list, most: int = 8) -> str:
    shown = ", ".join(names[:most])
    return shown + (f" and {len(names) - most} more" if len(names) > most else "")


def undrawable_message(mode: str, skipped: dict) -> str:
    """Why a render refuses rather than leave objects out (the image would look
    finished): the objects, grouped by reason; each reason says what to do."""
    by_reason: dict = {}
    for name, why in skipped.items():
        by_reason.setdefault(why, []).append(name)
    lines = [f"  {_names(names)}: {why}" for why, names in by_reason.items()]
    return f"cannot render {mode}: {len(skipped)} baked object(s) cannot be drawn:\n" + "\n".join(lines)


def check_collected(ps, status) -> None:
    """The scene must be complete: an ERROR from collecting it (a set's
    transfer texture missing: its objects left out) or nothing to draw fails."""
    errors = [text for level, text in status.messages if level == "ERROR"]
    if ps is None or errors:
        raise RenderError("; ".join(errors or [t for _, t in status.messages]) or "nothing to render")
    if not ps.meshes:
        raise RenderError("none of the baked objects is in the scene and visible: nothing to render")


def render_scene(context, *, mode: str = "tpfl", camera: str | None = None, size=None,
                 bounces: bool = True, prepass: bool = True, renderer=None, out_ext: str | None = None):
    """Render the scene's last bake offscreen. Returns (pixels (H, W, 4) linear
    RGBA row 0 at the bottom, FrameStats, PreviewStatus, seconds).

    Every baked object that is in the scene and visible is drawn, or RenderError
    says which cannot be and why (no per-vertex transfer for a vertex mode, an
    unreadable texture); the frame is checked against the GPU's and the
    memory's limits first (``out_ext``: the file it will be written to, for the
    estimate). The exposure is not applied to the pixels (write_image applies it)."""
    if mode not in MODES:
        raise RenderError(f"unknown mode {mode!r}; use one of {', '.join(MODES)}")
    scene = context.scene
    cam = scene_camera(scene, camera)
    w, h, what = frame_size(scene, size)
    ensure_gpu()
    check_frame(w, h, what, out_ext)
    ps, status = drawlist.collect(context, use_bounces=bounces)
    check_collected(ps, status)
    renderer = renderer or gpu_preview.Renderer()
    base, coming = check_memory(renderer, ps, mode, w, h, out_ext)
    skipped = renderer.prepare(ps, mode)      # reads and uploads every texture the frame needs
    if skipped:
        raise RenderError(undrawable_message(mode, skipped))
    depsgraph = context.evaluated_depsgraph_get()
    vp, cam_vec = camera_view(cam.evaluated_get(depsgraph), depsgraph, w, h, scene)
    t = time.perf_counter()
    try:
        pixels, stats = gpu_preview.render_offscreen(renderer, ps, mode, vp, cam_vec, w, h, prepass=prepass)
    except gpu_preview.OffscreenError as exc:
        raise RenderError(f"{what}: {exc}; render smaller (--size WxH)") from exc
    if stats.skipped:           # a texture changed on disk since prepare()
        raise RenderError(undrawable_message(mode, stats.skipped))
    stats.base_bytes, stats.estimate_bytes = base, base + coming
    return pixels, stats, status, time.perf_counter() - t


def render_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog, description="Render the PRTT preview of a baked .blend offscreen "
        "(the viewport's shaders; Mesa llvmpipe where there is no GPU).",
        epilog="Exit status: 0 the image was written; 1 it was not (the message says why: the .blend, "
               "a texture, the mode, the size, --out), and an existing file at --out is left as it was; "
               "2 bad options.")
    p.add_argument("blend", help="a .blend file that has been baked")
    p.add_argument("--out", required=True, help="image file: .png (8 bit, in the scene's view transform: AgX, Filmic, "
                   "Standard, ...) or .exr (linear float), "
                                                "relative to where you run the command")
    choice_option(p, "--mode", values=MODES, default="tpfl",
                  help="case-insensitive; vertex-tpfl and vertex-tp need a bake with Vertex Transfer "
                       "(default: tpfl)")
    p.add_argument("--camera", help="camera object (default: the scene camera)")
    p.add_argument("--size", type=parse_size, help="WxH pixels (default: the scene's render size), at most "
                   "the GPU's image size limit and what memory allows")
    p.add_argument("--scene", help="scene name (default: the file's active scene)")
    p.add_argument("--no-bounces", dest="bounces", action="store_false", help="leave out bounce textures")
    return p


def check_out(out: str, extensions=None) -> None:
    """Refuse an --out that cannot be written, before the .blend is even
    opened; messages name ``out`` as the user gave it. ``extensions``: the
    file types allowed (default: the render's images; `export` asks .glb).

    The folder is probed by creating (and removing) a temporary file there,
    the very thing the atomic write will do: permission bits alone mislead
    (root, ACLs, read-only mounts)."""
    ext = os.path.splitext(out)[1].lower()
    allowed = IMAGE_EXTENSIONS if extensions is None else tuple(extensions)
    if ext not in allowed:
        raise RenderError(f"--out must end in {' or '.join(allowed)}, got {out!r}")
    if os.path.isdir(out):
        raise RenderError(f"--out {out}: is a folder; give a file name")
    folder = os.path.dirname(os.path.abspath(out))
    shown = os.path.dirname(out) or "."
    if not os.path.isdir(folder):
        why = "is a file, not a folder" if os.path.exists(folder) else "does not exist"
        raise RenderError(f"--out {out}: the folder {shown} {why}")
    try:
        # Named like atomic_write's temporaries (pid first), so a probe left by a
        # kill between these lines is cleaned up as theirs are.
        fd, probe = tempfile.mkstemp(prefix=f"{TMP_PREFIX}{os.getpid()}-probe-", suffix=ext, dir=folder)
        os.close(fd)
        os.remove(probe)
    except OSError as exc:
        raise RenderError(f"--out {out}: cannot write in the folder {shown}: {exc.strerror or exc}") from None


def _fail(message) -> int:
    print(f"prtt: error: {message}", file=sys.stderr)
    return 1


def render_file(argv, prog="prtt render") -> int:
    """Open a .blend and render its preview. Exit status 0 ok, 1 failed (no
    file written), 2 bad options (argparse exits)."""
    args = render_parser(prog).parse_args(argv)
    try:
        check_out(args.out)
    except RenderError as exc:
        return _fail(exc)
    scene = open_scene(args.blend, args.scene)
    if scene is None:
        return 1
    ext = os.path.splitext(args.out)[1].lower()
    try:
        with bpy.context.temp_override(scene=scene):
            pixels, stats, status, seconds = render_scene(bpy.context, mode=args.mode, camera=args.camera,
                                                          size=args.size, bounces=args.bounces, out_ext=ext)
        for level, text in status.messages:
            print(f"prtt: {level.lower()}: {text}", file=sys.stderr if level != "INFO" else sys.stdout)
        display = colour.display_of(scene) if ext == ".png" else None
        if display is not None:
            print(f"prtt: colour: {display.name}, exposure {scene.view_settings.exposure:g} "
                  f"(Blender's colour management, sampled)")
        if colour.unsupported(scene):
            print(f"prtt: info: the image does not show the colour management's {colour.unsupported(scene)}")
        write_image(args.out, pixels, exposure=exposure_of(scene), display=display)
    except (RenderError, ImageWriteError, ShaderError) as exc:
        return _fail(exc)
    except MemoryError:
        return _fail(f"out of memory rendering {args.blend}; render smaller (--size WxH)")
    except (ValueError, OSError) as exc:        # e.g. the World's image cannot be read
        return _fail(f"{args.blend}: {exc}")
    h, w = pixels.shape[:2]
    print(f"prtt: rendered {args.mode} {w}x{h}, {len(stats.drawn)} object(s), {stats.triangles} triangles, "
          f"{1000 * seconds:.0f} ms -> {os.path.abspath(args.out)}")
    print(f"prtt: memory: {stats.texture_bytes / MiB:.0f} MiB of textures on the GPU, "
          f"{stats.base_bytes / MiB:.0f} MiB held before them, estimated peak {stats.estimate_bytes / MiB:.0f} MiB")
    return 0
