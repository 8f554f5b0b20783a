"""Opening and saving .blend files for the headless commands (``bake``, ``render``)."""
from __future__ import annotations

import contextlib
import os
import sys

import bpy


@contextlib.contextmanager
def blender_log_muted(mute: bool = True):
    """Keep Blender's own stdout lines ("Read blend: ...", "Info: Saved ...",
    written by C code) out of a ``--quiet`` command's output: file descriptor 1
    goes to /dev/null meanwhile. Python's own prints are flushed first."""
    if not mute:
        yield
        return
    sys.stdout.flush()
    try:
        saved = os.dup(1)
    except OSError:
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 1)
        yield
    finally:
        try:
            sys.stdout.flush()
        except (OSError, ValueError):
            pass
        os.dup2(saved, 1)
        os.close(saved)


def open_scene(blend: str, scene_name: str | None, *, quiet: bool = False):
    """Open a .blend and return its scene (the named one, else the active one),
    or None after printing why not. ``quiet``: without Blender's "Read blend" line."""
    try:
        with blender_log_muted(quiet):
            bpy.ops.wm.open_mainfile(filepath=blend, load_ui=False)
    except RuntimeError as exc:
        print(f"prtt: error: cannot open {blend}: {exc}", file=sys.stderr)
        return None
    scene = bpy.data.scenes.get(scene_name) if scene_name else bpy.context.scene
    if scene is None:
        print(f"prtt: error: no scene {scene_name!r} in {blend}", file=sys.stderr)
    return scene


def save_blend(path: str | None, *, quiet: bool = False) -> str:
    """Save the open .blend (over itself, or as ``path``); returns where. Raises OSError.
    ``quiet``: without Blender's "Info: Saved" line."""
    target = os.path.abspath(path) if path else bpy.data.filepath
    try:
        with blender_log_muted(quiet):
            if path:
                bpy.ops.wm.save_as_mainfile(filepath=target, copy=False)
            else:
                bpy.ops.wm.save_mainfile()
    except RuntimeError as exc:
        raise OSError(f"cannot save {target}: {str(exc).strip()}") from exc
    return target
