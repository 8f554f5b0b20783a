"""``blender -c prtt <command> ...`` and the shared headless entry points.

``render`` (preview_render.render_file) draws the viewport preview of a baked
.blend offscreen into a PNG/EXR.

``blender -c prtt bake scene.blend [--out DIR] [options]`` and
``python -m prtt_addon bake scene.blend [...]`` (Blender as a Python module)
both call :func:`bake_file`, which opens the .blend and runs the same
``bake_run.bake_blocking`` the operator uses in background mode.
"""
from __future__ import annotations

import argparse
import sys

import bpy

_CLI_HANDLE = None


def bake_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description="Bake PRTT transfer textures of a .blend file.")
    p.add_argument("blend", help="the .blend file")
    p.add_argument("--out", help="output folder (default: the file's PRTT setting, //prtt/)")
    p.add_argument("--scene", help="scene name (default: the file's active scene)")
    p.add_argument("--resolution", type=int)
    p.add_argument("--rays", type=int)
    p.add_argument("--bands", type=int)
    p.add_argument("--bounces", type=int)
    p.add_argument("--bounce-rays", dest="bounce_rays", type=int)
    p.add_argument("--dilate", type=int)
    p.add_argument("--float", dest="half", action="store_false", default=None)
    p.add_argument("--atlas", action="store_true", help="one texture set for all objects")
    p.add_argument("--unwrap", choices=["EXISTING", "SMART", "LIGHTMAP", "XATLAS"],
                   help="unwrap baked objects without a PRTT UV map first")
    p.add_argument("--force", action="store_true", help="bake even if nothing changed")
    save = p.add_mutually_exclusive_group()
    save.add_argument("--no-save", dest="save", action="store_false", default=True,
                      help="do not save the .blend after the bake (its PRTT UV maps and bake "
                           "record are then lost, and `render` finds nothing baked)")
    save.add_argument("--save-as", metavar="PATH",
                      help="save the baked scene to PATH instead of over FILE.blend")
    return p


#: Options stored in scene.prtt, checked against the property's own range
#: (Blender would clamp an out-of-range value without a word).
_SCENE_OPTIONS = ("resolution", "rays", "bands", "bounces", "bounce_rays", "dilate")


def _check_ranges(args, st) -> str | None:
    """An error message for the first option outside its property's range, or None."""
    for name in _SCENE_OPTIONS:
        v = getattr(args, name)
        if v is None:
            continue
        prop = st.bl_rna.properties[name]
        if not prop.hard_min <= v <= prop.hard_max:
            return (f"--{name.replace('_', '-')} {v} is out of range: "
                    f"it must be {prop.hard_min}..{prop.hard_max}")
    return None


def unwrap_todo(scene, view_layer):
    """Baked mesh objects without a PRTT map that an unwrap can write: local
    (not linked) meshes with faces, in the view layer. Everything else (instance
    sources in excluded collections, linked data, geometry-nodes output, curves)
    gets UVs generated at export. Returns (by edit-mode operators, by xatlas):
    objects the viewport hides cannot enter edit mode, so xatlas unwraps them."""
    from .properties import UV_MAP
    editable, hidden = [], []
    for o in view_layer.objects:
        if (o.type != "MESH" or not o.prtt.bake or o.library is not None or o.data.library is not None
                or UV_MAP in o.data.uv_layers or len(o.data.polygons) == 0
                or any(m.type == "NODES" for m in o.modifiers)):
            continue
        (editable if o.visible_get() and not o.hide_select else hidden).append(o)
    return editable, hidden


def _cancel_on_sigterm() -> None:
    """SIGTERM to a headless bake cancels it like Ctrl+C does (bake_blocking
    turns KeyboardInterrupt into a cancel of its worker, which runs in its own
    session and so does not get the signal itself)."""
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread():
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, interrupt)


def save_blend(path: str | None) -> str:
    """Save the open .blend (over itself, or as ``path``); returns where. Raises OSError."""
    import os
    target = os.path.abspath(path) if path else bpy.data.filepath
    try:
        if path:
            bpy.ops.wm.save_as_mainfile(filepath=target, copy=False)
        else:
            bpy.ops.wm.save_mainfile()
    except RuntimeError as exc:
        raise OSError(f"cannot save {target}: {str(exc).strip()}") from exc
    return target


def open_scene(blend: str, scene_name: str | None):
    """Open a .blend and return its scene (the named one, else the active one),
    or None after printing why not."""
    try:
        bpy.ops.wm.open_mainfile(filepath=blend, load_ui=False)
    except RuntimeError as exc:
        print(f"prtt: error: cannot open {blend}: {exc}", file=sys.stderr)
        return None
    scene = bpy.data.scenes.get(scene_name) if scene_name else bpy.context.scene
    if scene is None:
        print(f"prtt: error: no scene {scene_name!r} in {blend}", file=sys.stderr)
    return scene


def bake_file(argv, prog="prtt bake") -> int:
    """Open a .blend, bake it and save it (unless --no-save). Returns an exit
    status (0 ok, 1 failed, 2 usage, 3 cancelled: SIGINT/SIGTERM at any stage,
    the .blend and the previous textures untouched)."""
    args = bake_parser(prog).parse_args(argv)
    _cancel_on_sigterm()
    try:
        return _bake_file(args)
    except KeyboardInterrupt:
        print("prtt: cancelled; the .blend and the previous textures are unchanged", file=sys.stderr)
        return 3


def _bake_file(args) -> int:
    scene = open_scene(args.blend, args.scene)
    if scene is None:
        return 1
    if bpy.context.window is not None:
        bpy.context.window.scene = scene
    st = scene.prtt
    bad = _check_ranges(args, st)
    if bad:
        print(f"prtt: error: {bad}", file=sys.stderr)
        return 2
    if args.out:
        import os
        st.output_dir = os.path.abspath(args.out)
    for name in _SCENE_OPTIONS:
        v = getattr(args, name)
        if v is not None:
            setattr(st, name, v)
    if args.half is False:
        st.storage = "FLOAT"
    if args.atlas:
        st.texture_sets = "ATLAS"
    with bpy.context.temp_override(scene=scene):
        ctx = bpy.context
        if args.unwrap:
            from .unwrap import UnwrapError, unwrap_objects
            editable, hidden = unwrap_todo(scene, ctx.view_layer)
            try:
                for objects, method in ((editable, args.unwrap), (hidden, "XATLAS")):
                    if objects:
                        unwrap_objects(ctx, objects, method=method, resolution=st.resolution,
                                       padding=st.padding, atlas=st.texture_sets == "ATLAS")
            except (UnwrapError, RuntimeError) as exc:
                print(f"prtt: error: unwrap failed: {exc}", file=sys.stderr)
                return 1
            if hidden:
                print(f"prtt: note: {len(hidden)} object(s) hidden in the viewport unwrapped with xatlas: "
                      f"{', '.join(o.name for o in hidden[:8])}", flush=True)
        from .bake_run import bake_blocking

        def progress(e):
            if e.get("type") == "progress" and e.get("fraction") in (0.0, 1.0):
                print(f"prtt: {e.get('stage')} {e.get('set', '')}", flush=True)
            elif e.get("type") == "warning":
                print(f"prtt: warning: {e['message']}", flush=True)

        outcome = bake_blocking(ctx, force=args.force, on_event=progress)
    for w in (outcome.warnings or []):
        print(f"prtt: warning: {w}", flush=True)
    print(outcome.message, file=sys.stdout if outcome.status in ("done", "skipped") else sys.stderr)
    code = {"done": 0, "skipped": 0, "cancelled": 3}.get(outcome.status, 1)
    if code == 0 and args.save:
        try:
            where = save_blend(args.save_as)
        except OSError as exc:
            print(f"prtt: error: the bake finished but {exc}", file=sys.stderr)
            return 1
        print(f"prtt: saved {where}", flush=True)
    return code


def _cli(argv) -> int:
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: blender -c prtt bake FILE.blend [--out DIR] [options]\n"
              "       blender -c prtt render FILE.blend --out IMAGE.png|exr [--mode tpfl|tp|vertex-tpfl|"
              "vertex-tp|diffuse] [--camera NAME] [--size WxH]\n"
              "       blender -c prtt bake|render --help")
        return 0 if argv else 2
    cmd, rest = argv[0], argv[1:]
    if cmd == "bake":
        return bake_file(rest, prog="blender -c prtt bake")
    if cmd == "render":
        from .preview_render import render_file
        return render_file(rest, prog="blender -c prtt render")
    print(f"prtt: unknown command {cmd!r}; use bake or render", file=sys.stderr)
    return 2


def register():
    global _CLI_HANDLE
    if hasattr(bpy.utils, "register_cli_command"):
        _CLI_HANDLE = bpy.utils.register_cli_command("prtt", _cli)


def unregister():
    global _CLI_HANDLE
    if _CLI_HANDLE is not None:
        bpy.utils.unregister_cli_command(_CLI_HANDLE)
        _CLI_HANDLE = None
