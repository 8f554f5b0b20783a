"""``blender -c prtt <command> ...`` and the shared headless entry points.

``render`` (preview/offscreen.py render_file) draws the viewport preview of a
baked .blend offscreen into a PNG/EXR.

``blender -c prtt bake scene.blend [--out DIR] [options]`` and
``python -m prtt_addon bake scene.blend [...]`` (Blender as a Python module)
both call :func:`bake_file`, which opens the .blend and runs the same
``bake.run.bake_blocking`` the operator uses in background mode.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import sys
import threading

import bpy

from ..cli_options import (
    ConsoleProgress,
    add_dask_option,
    add_output_options,
    add_setting_options,
    choice_option,
    given_settings,
)
from ..core import settings_schema as schema
from ..core.base.atomic import atomic_write
from ..core.texels.unwrap import UnwrapError
from .bake.run import bake_blocking, prepare
from .blendfile import blend_relative, open_scene, save_blend
from .gltf.export import export_file
from .preview.offscreen import RenderError, check_out, render_file
from .rna_arrays import RnaArrayError
from .scene.job import ExportError, output_folder, unwrap_resolution
from .scene.uv_maps import bake_downscale, needs_user_unwrap, unwrap_objects

_CLI_HANDLE = None


#: Unwrap methods of ``--unwrap`` (scene.prtt.unwrap_method's identifiers).
UNWRAP_METHODS = ("EXISTING", "SMART", "LIGHTMAP", "XATLAS")


def bake_parser(prog: str) -> argparse.ArgumentParser:
    """Options of ``blender -c prtt bake`` / ``python -m prtt_addon bake``.
    The bake settings are generated from core/settings_schema.py: those the
    scene holds (scene.prtt) are set on it and saved with the .blend; the
    others apply to this bake only."""
    p = argparse.ArgumentParser(
        prog=prog, description="Bake PRTT transfer textures of a .blend file (paths are relative to where "
                               "you run the command).",
        epilog="Exit status: 0 baked (or nothing to do), 1 failed (the message says why), 2 bad options, "
               "3 cancelled (SIGINT/SIGTERM; the .blend and the previous textures unchanged).")
    p.add_argument("blend", help="the .blend file")
    p.add_argument("--out", help="output folder (default: the file's PRTT setting, //prtt/); stored in the "
                                 ".blend relative to it (//textures/), so the project folder can move")
    p.add_argument("--absolute-out", action="store_true",
                   help="store --out in the .blend as an absolute path (what earlier PRTT did)")
    p.add_argument("--scene", help="scene name (default: the file's active scene)")
    in_scene = schema.of_scope("job") + [s for s in schema.SETTINGS if schema.has_ui(s) and s.scope != "job"]
    once = [s for s in schema.core_settings() if not schema.has_ui(s)]
    g = p.add_argument_group("bake settings stored in the scene (scene.prtt; saved with the .blend)")
    add_setting_options(g, in_scene, defaults={s.name: "default: the scene's" for s in in_scene})
    g.add_argument("--atlas", action="store_true", help="one texture set for all objects (Texture Sets: One Atlas)")
    o = p.add_argument_group("bake settings for this bake only (not stored in the .blend)")
    add_setting_options(o, once)
    add_dask_option(o)
    choice_option(p, "--unwrap", values=UNWRAP_METHODS,
                  help="unwrap baked objects without a PRTT UV map first (case-insensitive)")
    p.add_argument("--force", action="store_true", help="bake even if nothing changed")
    p.add_argument("--job-only", metavar="JOB.npz",
                   help="write the job file the bake would run (the scene as the worker reads it, its settings "
                        "and light) to JOB.npz and stop: `bake-job JOB.npz --out DIR [--dask ...]` bakes it on "
                        "any machine (docs/distributed.md); the .blend is saved only if --unwrap changed it")
    save = p.add_mutually_exclusive_group()
    save.add_argument("--no-save", dest="save", action="store_false", default=True,
                      help="do not save the .blend after the bake (its PRTT UV maps and bake "
                           "record are then lost, and `render` finds nothing baked)")
    save.add_argument("--save-as", metavar="PATH",
                      help="save the baked scene to PATH instead of over FILE.blend")
    add_output_options(p)
    return p


def unwrap_todo(scene, view_layer):
    """Baked mesh objects without a PRTT map that an unwrap can write: local
    (not linked) meshes with faces, in the view layer. Everything else (instance
    sources in excluded collections, linked data, geometry-nodes output, curves)
    gets UVs generated at export. Returns (by edit-mode operators, by xatlas):
    objects the viewport hides cannot enter edit mode, so xatlas unwraps them."""
    editable, hidden = [], []
    for o in view_layer.objects:
        if not (o.prtt.bake and needs_user_unwrap(o)):
            continue
        (editable if o.visible_get() and not o.hide_select else hidden).append(o)
    return editable, hidden


def _cancel_on_sigterm() -> None:
    """SIGTERM to a headless bake cancels it like Ctrl+C does (bake_blocking
    turns KeyboardInterrupt into a cancel of its worker, which runs in its own
    session and so does not get the signal itself)."""
    if threading.current_thread() is not threading.main_thread():
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, interrupt)


def _saved_state(st) -> str:
    """What a bake can change in the .blend's PRTT settings and bake record,
    less the record's time stamp: equal before and after a bake that found
    nothing to do, unless an option changed a setting."""
    record = {}
    if st.last_bake:
        try:
            record = json.loads(st.last_bake)
        except ValueError:
            record = {"raw": st.last_bake}
    record.pop("time", None)
    if record.get("out_dir_relative"):
        record.pop("out_dir", None)        # the project folder moved: the relative form says it all
    settings = {p.identifier: getattr(st, p.identifier) for p in st.bl_rna.properties
                if p.identifier not in ("rna_type", "last_bake", "status", "progress", "baking")
                and not p.is_readonly and p.type in {"BOOLEAN", "INT", "FLOAT", "STRING", "ENUM"}
                and not getattr(p, "is_array", False)}
    return json.dumps([settings, record], sort_keys=True, default=str)


def _write_job(ctx, args, overrides: dict, unwrapped: bool) -> int:
    """``bake --job-only JOB.npz``: the job file the bake would run, written
    atomically to JOB.npz (not the output folder's own job file)."""
    target = os.path.abspath(args.job_only)
    if not target.endswith(".npz"):
        print(f"prtt: error: --job-only {args.job_only}: a job file ends in .npz", file=sys.stderr)
        return 2
    try:
        check_out(args.job_only, (".npz",))       # the folder exists and takes a file, as render's --out
    except RenderError as exc:
        print(f"prtt: error: {str(exc).replace('--out', '--job-only', 1)}", file=sys.stderr)
        return 1
    try:
        prepared = prepare(ctx, overrides)
    except (ExportError, ValueError) as exc:
        print(f"prtt: error: {exc}", file=sys.stderr)
        return 1
    with atomic_write(target) as tmp:
        shutil.copyfile(prepared.job, tmp)
    for w in prepared.export.warnings:
        print(f"prtt: warning: {w}", flush=True)
    sets = prepared.export.scene.set_names
    print(f"prtt: wrote {target}: {len(sets)} texture set(s), {prepared.export.scene.n_triangles} triangles; "
          f"bake it with: python -m prtt_addon bake-job {args.job_only} --out DIR [--dask ...]", flush=True)
    if unwrapped and args.save:
        where = save_blend(args.save_as, quiet=args.quiet)
        print(f"prtt: saved {where} (its new PRTT UV maps: the job's)", flush=True)
    return 0


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
    scene = open_scene(args.blend, args.scene, quiet=args.quiet)
    if scene is None:
        return 1
    if bpy.context.window is not None:
        bpy.context.window.scene = scene
    st = scene.prtt
    before = _saved_state(st)
    unwrapped = False
    if args.out:
        # Stored relative to the .blend (Blender's //), so the project can move.
        out = os.path.abspath(args.out)
        st.output_dir = out if args.absolute_out else blend_relative(out, bpy.data.filepath)
    elif args.absolute_out:
        st.output_dir = output_folder(scene)         # the file's folder setting, made absolute
    # Ranges were checked by the options (the properties' hard limits are the same).
    props, overrides = schema.ui_from_values(given_settings(args, schema.SETTINGS))
    for name, v in props.items():
        setattr(st, name, v)
    if args.atlas:
        st.texture_sets = "ATLAS"
    with bpy.context.temp_override(scene=scene):
        ctx = bpy.context
        if args.unwrap:
            editable, hidden = unwrap_todo(scene, ctx.view_layer)
            try:
                for objects, method in ((editable, args.unwrap), (hidden, "XATLAS")):
                    if objects:
                        unwrapped = True
                        unwrap_objects(ctx, objects, method=method, resolution=st.resolution,
                                       padding=st.padding, atlas=st.texture_sets == "ATLAS",
                                       source_map=st.existing_uv_map, dilate=st.dilate,
                                       bounce_downscale=bake_downscale(st),
                                       resolution_of=lambda ob: unwrap_resolution(ob, st))
            except (UnwrapError, RnaArrayError, RuntimeError) as exc:
                print(f"prtt: error: unwrap failed: {exc}", file=sys.stderr)
                return 1
            if hidden and not args.quiet:
                print(f"prtt: note: {len(hidden)} object(s) hidden in the viewport unwrapped with xatlas: "
                      f"{', '.join(o.name for o in hidden[:8])}", flush=True)
        if args.job_only:
            return _write_job(ctx, args, overrides, unwrapped)
        progress = ConsoleProgress(quiet=args.quiet, final=False)
        try:
            outcome = bake_blocking(ctx, overrides=overrides, force=args.force, on_event=progress, dask=args.dask)
        finally:
            progress.end()
    for w in (outcome.warnings or []):
        print(f"prtt: warning: {w}", flush=True)
    code = {"done": 0, "skipped": 0, "cancelled": 3}.get(outcome.status, 1)
    if code != 0:
        print(outcome.message, file=sys.stderr, flush=True)
        return code
    if not args.save:
        print(outcome.message, flush=True)
        return code
    if outcome.status == "skipped" and not unwrapped and not args.save_as and _saved_state(st) == before:
        # Nothing in the file changed: saving would only rotate a .blend1 backup.
        print(f"{outcome.message}; {os.path.basename(bpy.data.filepath)} unchanged, not saved", flush=True)
        return code
    if args.save_as and (st.output_dir or "//prtt/").startswith("//"):
        # relative to the file that holds it: the copy saved elsewhere
        st.output_dir = blend_relative(output_folder(scene), os.path.abspath(args.save_as))
        record = json.loads(st.last_bake) if st.last_bake else {}
        if record.get("out_dir_relative"):
            record["out_dir_relative"] = st.output_dir
            st.last_bake = json.dumps(record)
    try:
        where = save_blend(args.save_as, quiet=args.quiet)
    except OSError as exc:
        print(outcome.message, flush=True)
        print(f"prtt: error: the bake finished but {exc}", file=sys.stderr)
        return 1
    print(f"{outcome.message}; saved {where}", flush=True)
    return code


def _cli(argv) -> int:
    """``blender -c prtt ...``. Returns the exit status (argparse's exits,
    ``-h`` included, become the status instead of a SystemExit in Blender)."""
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: blender -c prtt bake FILE.blend [--out DIR] [options]\n"
              "       blender -c prtt render FILE.blend --out IMAGE.png|exr [--mode tpfl|tp|vertex-tpfl|"
              "vertex-tp|diffuse] [--camera NAME] [--size WxH]\n"
              "       blender -c prtt export FILE.blend --out ROOM.glb\n"
              "       blender -c prtt bake|render|export --help")
        return 0 if argv else 2
    cmd, rest = argv[0], argv[1:]
    try:
        if cmd == "bake":
            return bake_file(rest, prog="blender -c prtt bake")
        if cmd == "render":
            return render_file(rest, prog="blender -c prtt render")
        if cmd == "export":
            return export_file(rest, prog="blender -c prtt export")
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    print(f"prtt: unknown command {cmd!r}; use bake, render or export", file=sys.stderr)
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
