"""Argument parsing for ``python -m prtt_addon``.

The options and the progress display both command lines share are in
prtt_addon/cli_options.py (their names stay importable from here). The
Blender-side commands (``bake``, ``render``) hand their arguments to
prtt_addon/blender/commands.py inside bpy.
"""
from __future__ import annotations

import argparse
import sys
import threading

from . import register
from .cli_options import (
    CheckedValue,
    ConsoleProgress,
    add_dask_option,
    add_output_options,
    add_setting_options,
    choice_option,
    given_settings,
    int_range,
    number_range,
)
from .core import settings_schema as schema
from .core.base.memory import MemoryLimitError
from .core.light.envmap import environment_light
from .env_report import report


def _cmd_env(args) -> int:
    report(args.source, args.bands, method=args.method)
    return 0


#: --env-strength: 0 or less would bake no light (or negative light), silently.
ENV_STRENGTH_MAX = 1e6


def add_bake_options(p: argparse.ArgumentParser) -> None:
    """``bake-job``'s options: every bake setting of the schema, and the light."""
    g = p.add_argument_group("bake settings (override the job's; docs/format.md section 5)")
    add_setting_options(g, schema.of_scope("job") + schema.core_settings(),
                        defaults={"resolution": "default: each set's own"})
    g.add_argument("--force", action="store_true", help="bake even if the outputs are up to date")
    add_dask_option(g)
    lt = p.add_argument_group("light for bounces (overrides the job's)")
    lt.add_argument("--env", help="an .exr/.hdr file or a built-in name (forest, sunset, city, ...)")
    lt.add_argument("--env-strength", action=CheckedValue, convert=number_range(0.0, ENV_STRENGTH_MAX, above=True),
                    default=1.0, metavar="X", help="multiplies the environment (> 0; for no light use --bounces 0)")
    lt.add_argument("--env-rotation", action=CheckedValue, convert=number_range(-360.0, 360.0), default=0.0,
                    metavar="DEG", help="Z rotation of the World's Mapping node: lookups turn by it before "
                                        "reading the image (the environment appears turned the other way)")
    add_output_options(p)


def _cmd_bake_job(args) -> int:
    from .worker import (  # not at module level: importing it sets BLAS thread limits, for bake-job only
        EXIT_CANCELLED,
        finish,
        install_cancel_handlers,
        run_job,
    )
    cancel = threading.Event()
    progress = ConsoleProgress(quiet=args.quiet)
    watchdog = install_cancel_handlers(cancel, progress)
    light = None
    if args.env:
        try:
            light = environment_light(args.env, max(args.bands or 5, 5), args.env_strength, args.env_rotation)
        except (ValueError, OSError, MemoryLimitError) as exc:
            print(f"prtt: error: {exc}", file=sys.stderr)
            return finish(1, watchdog)
        if cancel.is_set():
            progress({"type": "cancelled"})
            return finish(EXIT_CANCELLED, watchdog)
    code = run_job(args.job, args.out, progress, cancel, overrides=given_settings(args, schema.core_settings()),
                   resolution=args.resolution, force=args.force, light_override=light, dask=args.dask)
    progress.end()
    return finish(code, watchdog)


def _bpy_ready(hint: str) -> bool:
    """Whether Blender's Python module is there; registers the add-on in it
    (else says what to install or run instead)."""
    try:
        import bpy  # noqa: F401
    except ImportError:
        print(f"prtt: error: this command needs Blender as a Python module (pip install bpy==5.0.1), "
              f"or run: {hint}", file=sys.stderr)
        return False
    register()
    return True


def _cmd_bake_blend(args) -> int:
    """``python -m prtt_addon bake scene.blend ...``: the add-on's own code path in bpy."""
    if not _bpy_ready("blender -c prtt bake scene.blend"):
        return 1
    from .blender.commands import bake_file  # needs bpy, which only this command and render load
    return bake_file(args.rest, prog="python -m prtt_addon bake")


def _cmd_render_blend(args) -> int:
    """``python -m prtt_addon render scene.blend --out img ...``: the viewport's draw code, offscreen."""
    if not _bpy_ready("blender -c prtt render scene.blend --out image.png"):
        return 1
    from .blender.preview.offscreen import render_file  # needs bpy, which only this command and bake load
    return render_file(args.rest, prog="python -m prtt_addon render")


def _cmd_export_blend(args) -> int:
    """``python -m prtt_addon export scene.blend --out room.glb``: glTF with PRTT's textures."""
    if not _bpy_ready("blender -c prtt export scene.blend --out room.glb"):
        return 1
    from .blender.gltf.export import export_file  # needs bpy, which only the .blend commands load
    return export_file(args.rest, prog="python -m prtt_addon export")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m prtt_addon",
                                description="PRTT: precomputed radiance transfer textures")
    sub = p.add_subparsers(dest="command", required=True)

    e = sub.add_parser("env", help="project an equirect environment to SH and report errors")
    e.add_argument("source", help="an .exr/.hdr path or a built-in name (forest, sunset, city, ...)")
    e.add_argument("--bands", action=CheckedValue, convert=int_range(1, 64), default=5, metavar="N",
                   help="SH bands (1..64; default 5)")
    choice_option(e, "--method", values=("area", "samples"), default="area",
                  help="area: exact integrals over each pixel (default); samples: quadrature at pixel centres")
    e.set_defaults(func=_cmd_env)

    b = sub.add_parser("bake-job", help="bake a job/scene file (.npz) without Blender")
    b.add_argument("job", help="job/scene file (.npz, docs/format.md)")
    b.add_argument("--out", required=True, help="output folder (relative to where you run the command)")
    add_bake_options(b)
    b.set_defaults(func=_cmd_bake_job)

    bk = sub.add_parser("bake", help="bake a .blend file through Blender as a Python module (bpy)",
                        add_help=False)
    bk.add_argument("rest", nargs=argparse.REMAINDER)
    bk.set_defaults(func=_cmd_bake_blend)

    rn = sub.add_parser("render", help="render the viewport preview of a baked .blend offscreen (bpy)",
                        add_help=False)
    rn.add_argument("rest", nargs=argparse.REMAINDER)
    rn.set_defaults(func=_cmd_render_blend)

    ex = sub.add_parser("export", help="export a baked .blend as a .glb with PRTT's textures (bpy)",
                        add_help=False)
    ex.add_argument("rest", nargs=argparse.REMAINDER)
    ex.set_defaults(func=_cmd_export_blend)
    return p


#: Commands whose options the add-on's own parser (inside bpy) reads: every
#: argument after the command goes to it unparsed, "-h" included.
_BPY_COMMANDS = {"bake": _cmd_bake_blend, "render": _cmd_render_blend, "export": _cmd_export_blend}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in _BPY_COMMANDS:
        return _BPY_COMMANDS[argv[0]](argparse.Namespace(rest=argv[1:]))
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, TypeError, OSError) as exc:
        print(f"prtt: error: {exc}", file=sys.stderr)
        return 2
