"""Opening and saving .blend files for the headless commands (``bake``, ``render``)."""
from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading

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


#: Lines Blender's native code writes to stderr that say nothing to a user:
#: Mesa's EGL answers EGL_BAD_MATCH to the context versions Blender tries
#: before the one it gets, on every GPU start-up (the GPU then works).
HARMLESS_STDERR = ("EGL Error (0x3009): EGL_BAD_MATCH",)


@contextlib.contextmanager
def native_stderr_filtered(drop=HARMLESS_STDERR):
    """Run the block with file descriptor 2 (where native code writes, past
    Python's sys.stderr) read through a pipe by a thread that passes every
    line on as it comes, but those starting with one of ``drop``: nothing is
    held back, so a crash inside the block still leaves its lines."""
    sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:
        yield
        return
    try:
        r, w = os.pipe()
    except OSError:
        os.close(saved)
        yield
        return
    prefixes = tuple(drop)

    def forward():
        with os.fdopen(r, "rb") as pipe:
            for line in pipe:
                if not line.decode("utf-8", "replace").startswith(prefixes):
                    os.write(saved, line)

    t = threading.Thread(target=forward, name="prtt-stderr", daemon=True)
    t.start()
    os.dup2(w, 2)
    os.close(w)
    try:
        yield
    finally:
        try:
            sys.stderr.flush()
        except (OSError, ValueError):
            pass
        os.dup2(saved, 2)                      # closes the pipe's last write end: the thread ends
        t.join(timeout=5.0)
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


def blend_relative(folder: str, blend: str) -> str:
    """``folder`` as Blender's ``//``-relative path from the .blend ``blend``
    (``//textures/``), so that the project folder can move or be copied with
    its .blend; ``folder`` itself (absolute) when the .blend is not saved yet
    or lives on another drive (Windows)."""
    folder = os.path.abspath(folder)
    if not blend:
        return folder
    try:
        rel = os.path.relpath(folder, os.path.dirname(os.path.abspath(blend)))
    except ValueError:                      # another drive: no relative path exists
        return folder
    rel = rel.replace(os.sep, "/")
    return "//" if rel == "." else f"//{rel}/"


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


@contextlib.contextmanager
def native_output_captured():
    """Run the block with file descriptors 1 and 2 (Python's and native
    code's output: Blender's reports, an operator's printed traceback) going
    to a temporary file; yields a list that holds the captured text once the
    block ends. What a caller shows only when asked (Blender's glTF
    exporter's INFO lines) or replaces by one line (its failure)."""
    out: list = []
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
    try:
        saved = [os.dup(1), os.dup(2)]
    except OSError:
        yield out
        return
    with tempfile.TemporaryFile() as f:
        os.dup2(f.fileno(), 1)
        os.dup2(f.fileno(), 2)
        try:
            yield out
        finally:
            for stream in (sys.stdout, sys.stderr):
                with contextlib.suppress(OSError, ValueError):
                    stream.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            f.seek(0)
            out.append(f.read().decode("utf-8", "replace"))
