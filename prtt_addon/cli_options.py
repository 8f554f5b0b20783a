"""Command-line pieces both command lines share: ``python -m prtt_addon``
(prtt_addon/cli.py) and Blender's ``blender -c prtt`` (prtt_addon/blender/commands.py).

Checked option values (a refusal is a usage error naming the option, the
value and what it must be), options generated from the settings schema, and
:class:`ConsoleProgress`, the human-readable progress of a bake. Imports no
bpy and nothing of either command line.
"""
from __future__ import annotations

import argparse
import math
import shutil
import sys
import threading
import time

from .core.settings_schema import format_number


class ConsoleProgress:
    """Human-readable progress of a bake, for ``python -m prtt_addon bake-job``
    and Blender's ``bake`` command (the worker itself prints JSON lines).

    On a terminal (``out.isatty()``) progress is ONE line rewritten in place
    with ``\\r``: stage, set, percentage, rays per second, time left (from the
    stage's fraction and elapsed time). Elsewhere (a log, a pipe) it is plain
    lines: one when a stage (or set, or bounce level) starts and one every
    ``interval`` seconds. Warnings always get a line of their own (the progress
    line is cleared first and drawn again after). ``quiet``: warnings, errors
    and the final line only. ``final=False``: done/cancelled/error events are
    left to the caller, which prints its own final line.
    """

    def __init__(self, out=None, *, quiet=False, tty=None, interval=5.0, refresh=0.1, clock=None,
                 err=None, final=True, width=None):
        self.out = out if out is not None else sys.stdout
        self.err = err
        self.quiet = quiet
        self.final = final
        if tty is None:
            try:
                tty = self.out.isatty()
            except (AttributeError, ValueError):
                tty = False
        self.tty = tty
        self.interval = interval
        self.refresh = refresh
        self._time = clock or time.monotonic
        self.width = width or max(20, shutil.get_terminal_size((100, 24)).columns - 1)
        self._key = None            # (stage, set, level) of the last progress event
        self._t0 = 0.0              # when that stage started
        self._printed = -1e9        # when the last plain line / TTY update was written
        self._line = ""             # the progress line now on the terminal ("" = none)
        self._lock = threading.RLock()   # the watchdog may announce "cancelled" from its thread

    # --- what a progress event says ----------------------------------------------------
    @staticmethod
    def _rate(rays_per_s: float) -> str:
        return f"{rays_per_s / 1e6:.1f} Mrays/s" if rays_per_s >= 1e5 else f"{rays_per_s / 1e3:.0f} krays/s"

    @staticmethod
    def _duration(seconds: float) -> str:
        s = int(round(seconds))
        h, m = s // 3600, s // 60 % 60
        return f"{h}:{m:02d}:{s % 60:02d}" if h else f"{m}:{s % 60:02d}"

    def describe(self, e: dict, now: float) -> str:
        """``trace [floor 1/2] 45.3%  28.1 Mrays/s  0:12 left`` for a progress event."""
        where = ""
        if e.get("set"):
            n = f" {e['set_index'] + 1}/{e['sets']}" if e.get("sets", 0) > 1 and "set_index" in e else ""
            where = f" [{e['set']}{n}]"
        if e.get("level"):
            where += f" level {e['level']}"
        if e.get("file"):
            where += f" {e['file']}"
        f = float(e.get("fraction") or 0.0)
        text = f"{e.get('stage')}{where} {100 * f:5.1f}%"
        elapsed = now - self._t0
        rate = e.get("rays_per_s")
        if not rate and e.get("rays") and elapsed > 0:
            rate = e["rays"] / elapsed
        if rate:
            text += f"  {self._rate(rate)}"
        if 0.01 <= f < 1.0 and elapsed >= 0.5:
            text += f"  {self._duration(elapsed * (1.0 - f) / f)} left"
        return text

    # --- output ------------------------------------------------------------------------
    def _write(self, text: str) -> None:
        try:
            self.out.write(text)
            self.out.flush()
        except (OSError, ValueError):
            pass

    def _clear(self) -> None:
        if self._line:
            self._write("\r" + " " * len(self._line) + "\r")
            self._line = ""

    def _show(self, line: str) -> None:
        """Draw the TTY progress line (padded over what was there)."""
        line = line[:self.width]
        self._write("\r" + line.ljust(len(self._line)))
        self._line = line

    def say(self, text: str, *, stream=None) -> None:
        """A line of its own (the TTY progress line is cleared and drawn again)."""
        shown = self._line
        self._clear()
        if stream is None or stream is self.out:
            self._write(text + "\n")
        else:
            try:
                print(text, file=stream, flush=True)
            except (OSError, ValueError):
                pass
        if shown:
            self._show(shown)

    def end(self) -> None:
        """Leave the terminal on a fresh line (clears the progress line)."""
        with self._lock:
            self._clear()

    def __call__(self, e: dict) -> None:
        with self._lock:
            self._handle(e)

    def _handle(self, e: dict) -> None:
        t = e.get("type")
        if t == "progress":
            if self.quiet:
                return
            now = self._time()
            key = (e.get("stage"), e.get("set"), e.get("level"))
            new = key != self._key
            if new:
                self._key, self._t0 = key, now
            if self.tty:
                if new or now - self._printed >= self.refresh or e.get("fraction") == 1.0:
                    self._printed = now
                    self._show("prtt: " + self.describe(e, now))
            elif new or now - self._printed >= self.interval:
                self._printed = now
                self._write("prtt: " + self.describe(e, now) + "\n")
        elif t == "warning":
            self.say(f"prtt: warning: {e['message']}")
        elif t == "info":
            if not self.quiet:
                self.say(f"prtt: {e['message']}")
        elif t == "start":
            if not self.quiet:
                line = f"prtt: baking {len(e['sets'])} set(s), {e['triangles']} triangles"
                res = e.get("resolutions") or []
                if res:
                    shown = [f"{n} {w}x{h}" for n, (w, h) in zip(e["sets"], res)]
                    line += ": " + ", ".join(shown[:8]) + (f" and {len(shown) - 8} more" if len(shown) > 8 else "")
                self.say(line)
                if res and len(res) > 1 and str((e.get("settings") or {}).get("tuning", "")).lower() == "auto":
                    self.say("prtt: note: Tuning Auto sizes each object's own set from its surface area (128 "
                             "texels a metre, a power of two) up to the Resolution asked; Tuning Fixed, a Texel "
                             "Density or an object's Resolution Override choose otherwise")
        elif not self.final:
            if t in ("done", "cancelled", "error"):
                self.end()
        elif t == "error":
            self.end()
            print(f"prtt: error: {e['message']}", file=self.err or sys.stderr, flush=True)
        elif t == "cancelled":
            self.say("prtt: cancelled; previous outputs are intact")
        elif t == "done":
            self.end()
            if e.get("skipped"):
                self._write(f"prtt: up to date, nothing baked ({e['manifest']}); --force bakes anyway\n")
            else:
                self._write(f"prtt: done: {e['manifest']}\n")


# --- options ---------------------------------------------------------------------------------

class CheckedValue(argparse.Action):
    """An option whose value ``convert`` checks; a refusal is a usage error
    (exit 2) naming the option, the value and what it must be:
    ``--rays 0 is out of range: it must be 1..65536``."""

    def __init__(self, option_strings, dest, convert=None, **kwargs):
        self.convert = convert
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        try:
            v = self.convert(values)
        except ValueError as exc:
            parser.error(f"{option_string} {values} {exc}")
        setattr(namespace, self.dest, v)


def parse_size(text: str) -> tuple[int, int]:
    """``WxH`` -> (W, H), both at least 1 (argparse reports anything else, exit 2)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 1920x1080, got {text!r}") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"width and height must be at least 1, got {text!r}")
    return w, h


def int_range(lo: int, hi: int):
    """Converter: an integer lo..hi."""
    def convert(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise ValueError(f"is not an integer: it must be {lo}..{hi}") from None
        if not lo <= v <= hi:
            raise ValueError(f"is out of range: it must be {lo}..{hi}")
        return v
    return convert


def number_range(lo: float, hi: float, *, above: bool = False):
    """Converter: a finite number lo..hi (``above``: strictly greater than lo)."""
    where = f"> {format_number(lo)} and <= {format_number(hi)}" if above else f"{format_number(lo)}..{format_number(hi)}"

    def convert(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise ValueError(f"is not a number: it must be {where}") from None
        if not math.isfinite(v):
            raise ValueError(f"is not a finite number: it must be {where}")
        if not ((v > lo if above else v >= lo) and v <= hi):
            raise ValueError(f"is out of range: it must be {where}")
        return v
    return convert


def one_of(values):
    """Converter: one of ``values``, case-insensitive, ``_`` for ``-`` too
    (``SMART`` == ``smart``, ``VERTEX_TPFL`` == ``vertex-tpfl``); returns the
    value as listed."""
    values = tuple(values)
    canon = {v.lower().replace("_", "-"): v for v in values}

    def convert(text: str) -> str:
        v = canon.get(text.lower().replace("_", "-"))
        if v is None:
            raise ValueError(f"is an invalid choice: it must be one of {', '.join(values)}")
        return v
    return convert


def choice_option(p, *names, values, help=None, default=None, dest=None):  # noqa: A002 (argparse's own name)
    """add_argument for a case-insensitive choice (see :func:`one_of`)."""
    kw = {"dest": dest} if dest else {}
    return p.add_argument(*names, action=CheckedValue, convert=one_of(values), default=default,
                          metavar="{" + ",".join(values) + "}", help=help, **kw)


def add_setting_options(group, settings, *, defaults: dict | None = None) -> None:
    """Options for schema settings (core/settings_schema.py): ``dest`` is the
    setting's name and every default is None (not given: the job's, the
    scene's or the schema's default applies). ``defaults``: {name: what
    applies when the option is not given}, where that is not the schema's."""
    defaults = defaults or {}
    for s in settings:
        default_text = defaults.get(s.name)
        if s.kind == "bool":
            on, off = s.flags
            mx = group.add_mutually_exclusive_group()
            mark = "" if default_text else " (default)"
            mx.add_argument(on, dest=s.name, action="store_const", const=True, default=None,
                            help=s.help + (mark if s.default else ""))
            mx.add_argument(off, dest=s.name, action="store_const", const=False, default=None,
                            help=s.off_help + (mark if not s.default else ""))
            continue
        if s.kind == "choice":
            choice_option(group, s.option, dest=s.name, values=s.values,
                          help=f"{s.help} ({default_text or 'default ' + s.default})")
            continue
        unit = f" {s.unit}" if s.unit else ""
        convert = int_range(s.lo, s.hi) if s.kind == "int" else number_range(s.lo, s.hi)
        group.add_argument(s.option, dest=s.name, action=CheckedValue, convert=convert, default=None,
                           metavar=s.metavar, help=f"{s.help} ({format_number(s.lo)}..{format_number(s.hi)}{unit}; "
                                                   f"{default_text or 'default ' + format_number(s.default)})")


def given_settings(args, settings) -> dict:
    """{name: value} of the schema settings given on the command line."""
    return {s.name: getattr(args, s.name) for s in settings if getattr(args, s.name, None) is not None}


def add_output_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("-q", "--quiet", action="store_true",
                   help="print only warnings, errors and the final line (no progress)")


def dask_spec(value: str) -> str:
    """``--dask``'s value, checked (argparse type: a bad one is a usage error naming it)."""
    from .core.bake.executors.dask_spec import parse_spec  # deferred: as above
    from .core.base.errors import BakeError  # deferred: the option module loads before numpy
    try:
        parse_spec(value)
    except BakeError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return value


def add_dask_option(g) -> None:
    """``--dask [ADDR]`` (bake-job, the worker, Blender's bake): docs/distributed.md."""
    g.add_argument("--dask", nargs="?", const="env", type=dask_spec, metavar="local[:N]|tcp://HOST:PORT",
                   help="trace on a Dask cluster: local[:N] starts N worker processes here, an address uses a "
                        "running scheduler, no value reads $DASK_SCHEDULER_ADDRESS (needs the optional "
                        "packages dask and distributed; the outputs are the local bake's, bit for bit)")
