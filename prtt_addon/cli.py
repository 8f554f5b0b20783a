"""Argument parsing for ``python -m prtt_addon``. Heavy modules load per command."""
from __future__ import annotations

import argparse
import sys


def _cmd_env(args) -> int:
    from .env_report import report
    report(args.source, args.bands, method=args.method)
    return 0


def _cmd_demo(args) -> int:
    from .env_report import report
    print("PRTT demo: projecting Blender's built-in 'forest' environment to SH")
    report("forest", args.bands)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m prtt_addon",
                                description="PRTT: precomputed radiance transfer textures")
    sub = p.add_subparsers(dest="command", required=True)

    e = sub.add_parser("env", help="project an equirect environment to SH and report errors")
    e.add_argument("source", help="an .exr/.hdr path or a built-in name (forest, sunset, city, ...)")
    e.add_argument("--bands", type=int, default=5)
    e.add_argument("--method", choices=["area", "samples"], default="area")
    e.set_defaults(func=_cmd_env)

    d = sub.add_parser("demo", help="the main job (see README)")
    d.add_argument("--bands", type=int, default=5)
    d.set_defaults(func=_cmd_demo)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, TypeError, OSError) as exc:
        print(f"prtt: error: {exc}", file=sys.stderr)
        return 2
