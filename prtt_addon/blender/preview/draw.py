"""The viewport preview: a POST_VIEW draw handler on every 3D viewport.

Registered with the add-on, except in background mode (there are no
viewports; offscreen renders use offscreen.py). Draw handlers belong to
the space type, not to a file, so they survive file loads and undo; the
caches of drawlist.py are cleared on both (object pointers change) and the
GPU resources no longer used are freed a few frames later.

The handler draws nothing unless Scene > PRTT > Preview is on. Errors are
shown in the panel (``last_status``), never raised into Blender's draw loop.
"""
from __future__ import annotations

import atexit

import bpy
from bpy.app.handlers import persistent

from ..scene import world_panorama
from ..shared import PREVIEW_MODES, redraw_viewports
from . import colour_management as colour
from . import drawlist
from . import renderer as gpu_preview
from .offscreen import exposure_of, region_view

#: NDC depth bias towards the eye: our copy of a surface must win against
#: Blender's own depth of the same surface (24-bit depth: ~80 steps).
VIEWPORT_DEPTH_BIAS = 1e-5
#: Frames an unused GPU resource survives (several viewports share resources).
KEEP_FRAMES = 8

_HANDLE = None
_RENDERER = None
#: What the last frame found (the panel shows it): PreviewStatus, FrameStats, error text.
last_status = {"status": None, "stats": None, "error": ""}


def draw_view(context, region_data, visible=None, *, sample_display: bool = True):
    """Draw the preview of ``context.scene`` for a view (its region data: the
    perspective and view matrices) into the bound framebuffer, which encodes
    sRGB (the viewport's colour buffer), in the scene's view transform.
    Returns the FrameStats, or None when there is nothing to draw.

    ``sample_display`` False (inside Blender's drawing, where no data-block
    may be made): a view transform not yet sampled is sampled from a timer
    and drawn from the next frame; this one draws Standard."""
    global _RENDERER
    scene = context.scene
    st = scene.prtt
    ps, status = drawlist.collect(context, visible=visible, use_bounces=st.preview_bounces)
    last_status["status"] = status
    if ps is None:
        return None
    if _RENDERER is None:
        _RENDERER = gpu_preview.Renderer()
    vp, cam = region_view(region_data)
    display = colour.display_of(scene, sample=sample_display)
    if display is None and colour.missing(scene):
        colour.schedule(scene, lambda: redraw_viewports(bpy.context))
    skipped = colour.unsupported(scene)
    if skipped:
        status.add("INFO", f"the preview does not draw the colour management's {skipped}")
    stats = _RENDERER.draw(ps, PREVIEW_MODES[st.preview_mode], vp, cam, exposure=exposure_of(scene),
                           depth_bias=VIEWPORT_DEPTH_BIAS, display=display)
    _RENDERER.end_frame(keep=KEEP_FRAMES)
    last_status.update(stats=stats, error="")
    return stats


def _draw() -> None:
    context = bpy.context
    st = getattr(context.scene, "prtt", None)
    if st is None or not st.preview:
        return
    try:
        space = context.space_data
        with world_panorama.drawing():       # a procedural World is rendered from a timer, not here
            draw_view(context, context.region_data, visible=lambda ob: ob.visible_get(viewport=space),
                      sample_display=False)
    except Exception as exc:       # never break Blender's draw loop; say it in the panel
        last_status["error"] = f"{type(exc).__name__}: {exc}"


def free_gpu() -> None:
    global _RENDERER
    if _RENDERER is not None:
        _RENDERER.free()
        _RENDERER = None


# GPU objects still referenced when Blender shuts its GPU module down are
# reported as leaks; let them go first.
atexit.register(free_gpu)


@persistent
def _on_depsgraph(scene, depsgraph):
    drawlist.note_depsgraph_updates(depsgraph)


@persistent
def _on_reset(*_args):
    drawlist.clear_caches()


_APP_HANDLERS = (("depsgraph_update_post", _on_depsgraph), ("load_post", _on_reset),
                 ("undo_post", _on_reset), ("redo_post", _on_reset))


def register():
    global _HANDLE
    for name, fn in _APP_HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        if fn not in lst:
            lst.append(fn)
    if not bpy.app.background and _HANDLE is None:
        _HANDLE = bpy.types.SpaceView3D.draw_handler_add(_draw, (), "WINDOW", "POST_VIEW")


def unregister():
    global _HANDLE
    if _HANDLE is not None:
        bpy.types.SpaceView3D.draw_handler_remove(_HANDLE, "WINDOW")
        _HANDLE = None
    for name, fn in _APP_HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        if fn in lst:
            lst.remove(fn)
    free_gpu()
