"""Argument parsing for ``python -m prtt_addon``. Heavy modules load per command."""
from __future__ import annotations

import argparse
import sys


def _cmd_env(args) -> int:
    from .env_report import report
    report(args.source, args.bands, method=args.method)
    return 0


def _cmd_demo(args) -> int:
    from .demo import run_args
    return run_args(args)


class ConsoleProgress:
    """Human-readable progress for terminals and logs (the worker prints JSON)."""

    def __init__(self, out=None, interval=2.0):
        import time
        self.out = out or sys.stdout
        self.interval = interval
        self._last = 0.0
        self._stage = None
        self._time = time.monotonic

    def __call__(self, e: dict) -> None:
        t = e.get("type")
        if t == "progress":
            key = (e.get("stage"), e.get("set"))
            now = self._time()
            if key != self._stage or now - self._last >= self.interval or e.get("fraction") == 1.0:
                self._stage, self._last = key, now
                where = f" [{e['set']}]" if e.get("set") else ""
                where += f" level {e['level']}" if e.get("level") else ""
                rate = f"  {e['rays_per_s'] / 1e6:.1f} Mrays/s" if e.get("rays_per_s") else ""
                print(f"  {e.get('stage')}{where}: {100 * e.get('fraction', 0):5.1f}%{rate}",
                      file=self.out, flush=True)
        elif t == "warning":
            print(f"  warning: {e['message']}", file=self.out, flush=True)
        elif t == "error":
            print(f"prtt: error: {e['message']}", file=sys.stderr, flush=True)
        elif t == "start":
            print(f"baking {len(e['sets'])} set(s), {e['triangles']} triangles", file=self.out)
        elif t == "cancelled":
            print("cancelled; previous outputs are intact", file=self.out)
        elif t == "done":
            if e.get("skipped"):
                print(f"up to date, nothing baked ({e['manifest']}); --force bakes anyway", file=self.out)
            else:
                print(f"done: {e['manifest']}", file=self.out)


def _settings_overrides(args) -> dict:
    o = {}
    for name in ("rays", "bands", "dilate", "seed", "threads", "sampler", "estimator",
                 "distribution", "min_rays", "bounces", "bounce_rays"):
        v = getattr(args, name, None)
        if v is not None:
            o[name] = v
    if args.adaptive is not None:
        o["adaptive_tol"] = args.adaptive
    if args.half is not None:
        o["half"] = args.half
    for flag, key in (("vertex", "vertex_mode"), ("mips", "mips")):
        if getattr(args, flag):
            o[key] = True
    if args.no_analytic:
        o["analytic"] = False
    if args.no_normal_maps:
        o["normal_maps"] = False
    if args.overlap:
        o["overlap"] = args.overlap
    return o


def int_in(lo: int, hi: int):
    """argparse type: an integer lo..hi (argparse then names the option: exit 2)."""
    def integer(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer {lo}..{hi}, got {text!r}") from None
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"must be an integer {lo}..{hi}, got {v}")
        return v
    return integer


def number_in(lo: float, hi: float, *, above: bool = False):
    """argparse type: a finite number lo..hi (``above``: strictly greater than lo)."""
    import math
    where = f"> {lo:g} and <= {hi:g}" if above else f"{lo:g}..{hi:g}"

    def number(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number {where}, got {text!r}") from None
        if not (math.isfinite(v) and (v > lo if above else v >= lo) and v <= hi):
            raise argparse.ArgumentTypeError(f"must be a finite number {where}, got {text}")
        return v
    return number


#: --env-strength: 0 or less would bake no light (or negative light), silently.
ENV_STRENGTH_MAX = 1e6


def add_bake_options(p: argparse.ArgumentParser) -> None:
    from .core.bake import BAKE_INT_LIMITS
    from .core.scene import MAX_RESOLUTION
    from .core.transfer import ADAPTIVE_TOL_LIMITS, INT_LIMITS
    lim = {**INT_LIMITS, **BAKE_INT_LIMITS}
    rng = lambda name: int_in(*lim[name][:2])  # noqa: E731
    g = p.add_argument_group("bake settings (default: the job's, else PRTT's defaults)")
    g.add_argument("--resolution", type=int_in(1, MAX_RESOLUTION), help="texels per side for every set")
    g.add_argument("--rays", type=rng("rays"), help="rays per texel (maximum when adaptive), default 256")
    g.add_argument("--bands", type=rng("bands"), help="SH bands, default 5 (25 coefficients)")
    g.add_argument("--dilate", type=rng("dilate"), help="dilation in texels, default 3")
    g.add_argument("--half", dest="half", action="store_true", default=None, help="float16 EXR (default)")
    g.add_argument("--float", dest="half", action="store_false", help="float32 EXR")
    g.add_argument("--adaptive", type=number_in(*ADAPTIVE_TOL_LIMITS), metavar="TOL",
                   help="stop per texel when the RMS standard error is below TOL")
    g.add_argument("--min-rays", dest="min_rays", type=rng("min_rays"), help="first adaptive round, default 64")
    g.add_argument("--sampler", choices=["sobol", "stratified", "random"])
    g.add_argument("--distribution", choices=["cosine", "uniform"])
    g.add_argument("--estimator", choices=["balanced", "control-variate", "plain"])
    g.add_argument("--seed", type=rng("seed"))
    g.add_argument("--threads", type=rng("threads"), help="0 = all cores")
    g.add_argument("--vertex", action="store_true", help="also bake per-vertex transfer")
    g.add_argument("--mips", action="store_true", help="also write coverage-weighted mip levels")
    g.add_argument("--no-analytic", action="store_true", help="trace provably unoccluded texels too")
    g.add_argument("--no-normal-maps", action="store_true")
    g.add_argument("--overlap", choices=["warn", "error"], help="overlapping UVs: warn (default) or fail")
    g.add_argument("--force", action="store_true", help="bake even if the outputs are up to date")
    g.add_argument("--bounces", type=rng("bounces"),
                   help="inter-reflection levels, default 1 (0 = off; needs a light)")
    g.add_argument("--bounce-rays", dest="bounce_rays", type=rng("bounce_rays"),
                   help="rays per texel per bounce, default 64")
    g.add_argument("--env", help="light for bounces: .exr/.hdr or built-in name (overrides the job's light)")
    g.add_argument("--env-strength", type=number_in(0.0, ENV_STRENGTH_MAX, above=True), default=1.0,
                   help="multiplies the environment (> 0; for no light use --bounces 0)")
    g.add_argument("--env-rotation", type=number_in(-360.0, 360.0), default=0.0, metavar="DEG",
                   help="Z rotation of the World's Mapping node: lookups turn by it before "
                        "reading the image (the environment appears turned the other way)")


def env_light(source: str, bands: int, strength: float = 1.0, rotation_z_deg: float = 0.0):
    """(K, 3) SH light from an environment image, strength and a Mapping-node Z rotation."""
    import math

    import numpy as np

    from .core import envmap, sh
    L = envmap.project_equirect(source, bands) * strength
    if rotation_z_deg:
        # Mapping (Point) turns the lookup direction: L(w) = img(R w) = img((R^T)^-1 w),
        # i.e. the image's SH rotated by R^T.
        a = math.radians(rotation_z_deg)
        R = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
        L = sh.rotate(L, R.T)
    return L


def _cmd_bake_job(args) -> int:
    import threading

    from .core.memory import MemoryLimitError
    from .worker import EXIT_CANCELLED, finish, install_cancel_handlers, run_job
    cancel = threading.Event()
    progress = ConsoleProgress()
    watchdog = install_cancel_handlers(cancel, progress)
    light = None
    if args.env:
        try:
            light = env_light(args.env, max(args.bands or 5, 5), args.env_strength, args.env_rotation)
        except (ValueError, OSError, MemoryLimitError) as exc:
            print(f"prtt: error: {exc}", file=sys.stderr)
            return finish(1, watchdog)
        if cancel.is_set():
            progress({"type": "cancelled"})
            return finish(EXIT_CANCELLED, watchdog)
    return finish(run_job(args.job, args.out, progress, cancel, overrides=_settings_overrides(args),
                          resolution=args.resolution, force=args.force, light_override=light), watchdog)


def _in_bpy(entry: str, argv, prog: str, hint: str) -> int:
    """Run ``prtt_addon.blender.<entry>`` (a function taking argv and prog) inside
    Blender as a Python module, with the add-on registered."""
    try:
        import bpy  # noqa: F401
    except ImportError:
        print(f"prtt: error: this command needs Blender as a Python module (pip install bpy==5.0.1), "
              f"or run: {hint}", file=sys.stderr)
        return 1
    import importlib

    from . import register
    module, func = entry.rsplit(".", 1)
    register()
    return getattr(importlib.import_module(f"prtt_addon.blender.{module}"), func)(argv, prog=prog)


def _cmd_bake_blend(args) -> int:
    """``python -m prtt_addon bake scene.blend ...``: the add-on's own code path in bpy."""
    return _in_bpy("cli.bake_file", args.rest, "python -m prtt_addon bake", "blender -c prtt bake scene.blend")


def _cmd_render_blend(args) -> int:
    """``python -m prtt_addon render scene.blend --out img ...``: the viewport's draw code, offscreen."""
    return _in_bpy("preview_render.render_file", args.rest, "python -m prtt_addon render",
                   "blender -c prtt render scene.blend --out image.png")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m prtt_addon",
                                description="PRTT: precomputed radiance transfer textures")
    sub = p.add_subparsers(dest="command", required=True)

    e = sub.add_parser("env", help="project an equirect environment to SH and report errors")
    e.add_argument("source", help="an .exr/.hdr path or a built-in name (forest, sunset, city, ...)")
    e.add_argument("--bands", type=int_in(1, 64), default=5)
    e.add_argument("--method", choices=["area", "samples"], default="area")
    e.set_defaults(func=_cmd_env)

    b = sub.add_parser("bake-job", help="bake a job/scene file (.npz) without Blender")
    b.add_argument("job", help="job/scene file (.npz, docs/format.md)")
    b.add_argument("--out", required=True, help="output folder")
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

    try:
        from .demo import add_arguments as demo_arguments
    except ImportError:             # the extension zip leaves the development-only demo out
        return p
    d = sub.add_parser("demo", help="the main job: demo scene, unwrap, bake, TPFL vs vertex-TPFL (see README)")
    demo_arguments(d)
    d.set_defaults(func=_cmd_demo)
    return p


#: Commands whose options the add-on's own parser (inside bpy) reads: every
#: argument after the command goes to it unparsed, "-h" included.
_BPY_COMMANDS = {"bake": _cmd_bake_blend, "render": _cmd_render_blend}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in _BPY_COMMANDS:
        import argparse as _ap
        return _BPY_COMMANDS[argv[0]](_ap.Namespace(rest=argv[1:]))
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, TypeError, OSError) as exc:
        print(f"prtt: error: {exc}", file=sys.stderr)
        return 2
