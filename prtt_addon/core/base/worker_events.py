"""The bake worker's stdout lines as the Blender side reads them
(docs/worker-protocol.md): one JSON object per line.

A line comes from a child process that may be another PRTT version, may be
killed mid-line, or may share stdout with a library that prints: it is
untrusted text. :func:`read_event` turns a line into an event whose fields
the Blender side reads are of the documented types, or None for anything
that is not an event (the caller keeps it as output text).
"""
from __future__ import annotations

import json
import math

#: Event types of the protocol.
TYPES = ("progress", "start", "warning", "info", "error", "cancelled", "done")
#: The longest line parsed as an event (a start event with a 16-band light is ~20 KB).
MAX_LINE = 1 << 20
#: Characters kept of a message, a stage or a set name.
MAX_TEXT = 20000


def _text(v, default: str = "") -> str:
    if isinstance(v, str):
        return v[:MAX_TEXT]
    if v is None:
        return default
    try:
        return json.dumps(v)[:MAX_TEXT]
    except (ValueError, RecursionError):      # nested as deep as json.loads allowed
        return "(unprintable)"


def read_event(line: str) -> dict | None:
    """The event on ``line``, or None when the line is not one: not JSON, not
    an object, over MAX_LINE characters, or an unknown ``type``. In an event,
    ``fraction`` (progress) is a finite number in [0, 1] (0 otherwise);
    ``stage``, ``set``, ``message`` are text; ``done`` has ``manifest`` text
    and ``skipped`` a bool (an event without a manifest path is not a done event)."""
    if not isinstance(line, str) or len(line) > MAX_LINE:
        return None
    try:
        e = json.loads(line)
    except (ValueError, RecursionError):
        return None
    if not isinstance(e, dict) or e.get("type") not in TYPES:
        return None
    kind = e["type"]
    if kind == "progress":
        f = e.get("fraction", 0.0)
        try:
            f = float(f) if isinstance(f, (int, float)) and not isinstance(f, bool) else 0.0
        except OverflowError:                  # an integer of hundreds of digits
            f = 0.0
        e["fraction"] = min(1.0, max(0.0, f)) if math.isfinite(f) else 0.0
        e["stage"] = _text(e.get("stage"))
        e["set"] = _text(e.get("set"))
    elif kind in ("warning", "info", "error"):
        e["message"] = _text(e.get("message"), "(no message)")
    elif kind == "done":
        if not isinstance(e.get("manifest"), str) or not e["manifest"]:
            return None
        e["skipped"] = e.get("skipped") is True
    return e
