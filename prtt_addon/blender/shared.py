"""What every Blender-side folder shares (ui, export, preview, bake import
it; it imports nothing of theirs): the names PRTT gives things in a .blend,
and the viewport redraw."""

#: Name of the UV map PRTT bakes into; unwrapping writes only this map.
UV_MAP = "PRTT"
#: Property value of each preview mode -> shader mode name.
PREVIEW_MODES = {"TPFL": "tpfl", "TP": "tp", "VERTEX_TPFL": "vertex-tpfl", "VERTEX_TP": "vertex-tp",
                 "DIFFUSE": "diffuse"}


def redraw_viewports(context) -> None:
    """Ask every 3D viewport to redraw (no-op in background mode: no windows)."""
    wm = context.window_manager
    for window in (wm.windows if wm is not None else []):
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()
