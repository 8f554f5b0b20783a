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
    return p


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
    """Open a .blend and bake it. Returns an exit status (0 ok, 1 failed, 3 cancelled)."""
    args = bake_parser(prog).parse_args(argv)
    scene = open_scene(args.blend, args.scene)
    if scene is None:
        return 1
    if bpy.context.window is not None:
        bpy.context.window.scene = scene
    st = scene.prtt
    if args.out:
        st.output_dir = args.out
    for name in ("resolution", "rays", "bands", "bounces", "bounce_rays", "dilate"):
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
            from .unwrap import unwrap_objects
            todo = [o for o in scene.objects if o.type == "MESH" and o.prtt.bake and "PRTT" not in o.data.uv_layers]
            if todo:
                unwrap_objects(ctx, todo, method=args.unwrap, resolution=st.resolution, padding=st.padding,
                               atlas=st.texture_sets == "ATLAS")
        from .bake_run import bake_blocking

        def progress(e):
            if e.get("type") == "progress" and e.get("fraction") in (0.0, 1.0):
                print(f"prtt: {e.get('stage')} {e.get('set', '')}", flush=True)
            elif e.get("type") == "warning":
                print(f"prtt: warning: {e['message']}", flush=True)

        outcome = bake_blocking(ctx, force=args.force, on_event=progress)
    print(outcome.message, file=sys.stdout if outcome.status in ("done", "skipped") else sys.stderr)
    return {"done": 0, "skipped": 0, "cancelled": 3}.get(outcome.status, 1)


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
