"""A texture file's channels a band of rows at a time (the preview's uploads).

OpenEXR's current API (``OpenEXR.File``) decodes every channel of a file at
once: a 4096² relightable texture's 147 half channels are 1.2 GB held beside
what the GPU gets. Its legacy scanline reader decodes a range of rows
(``InputFile.channels(names, type, y0, y1)``) but trusts damaged files
(crafted ones crashed it: tests/fuzz_corpus/exr), so it runs in a child
process that streams the bands through a pipe. The child's crash, garbage or
silence is a :class:`~prtt_addon.core.io.exr_io.TextureError` naming the
file, and the caller (Blender's process) holds one band at a time.

Protocol: the child reads a JSON request on stdin ({"path", "names",
"rows"}); it answers one JSON line ({"types": HALF/FLOAT/UINT per name,
"window": [x0, y0, x1, y1]} or {"error": text}), then per band of ``rows``
file rows (top first; the last band may be shorter) each name's rows as its
type's native bytes, in the order asked.
"""
from __future__ import annotations

import contextlib
import json
import os
import select
import subprocess
import time

import numpy as np

from ..base.child import child_env, python_executable

#: Seconds the child may go without delivering a byte before it is given up.
BAND_TIMEOUT = 120
#: The longest first line the child may write (types of MAX_FILE_CHANNELS names).
MAX_PREAMBLE = 4 << 20

_DTYPES = {"HALF": np.dtype(np.float16), "FLOAT": np.dtype(np.float32), "UINT": np.dtype(np.uint32)}

_CHILD = r"""
import json, sys
import Imath, OpenEXR
req = json.loads(sys.stdin.read())
out = sys.stdout.buffer
try:
    f = OpenEXR.InputFile(req["path"])
    h = f.header()
    dw, chans = h["dataWindow"], h["channels"]
    missing = [n for n in req["names"] if n not in chans]
    if missing:
        raise ValueError(f"missing channels {missing[:4]}")
    types = [str(chans[n].type) for n in req["names"]]
except Exception as exc:
    out.write((json.dumps({"error": str(exc) or type(exc).__name__}) + "\n").encode())
    sys.exit(0)
out.write((json.dumps({"types": types, "window": [dw.min.x, dw.min.y, dw.max.x, dw.max.y]}) + "\n").encode())
runs = []
for n, t in zip(req["names"], types):
    if runs and runs[-1][0] == t:
        runs[-1][1].append(n)
    else:
        runs.append((t, [n]))
rows = int(req["rows"])
for top in range(dw.min.y, dw.max.y + 1, rows):
    bottom = min(top + rows - 1, dw.max.y)
    for t, names in runs:
        for data in f.channels(names, Imath.PixelType(getattr(Imath.PixelType, t)), top, bottom):
            out.write(data)
out.flush()
"""


class ChannelBands:
    """Bands of a scanline EXR's channels, decoded by a child process.

    ``names``: the channels wanted; ``height`` x ``width``: the data window
    the caller has checked (exr_io.checked_header); ``rows``: file rows per
    band. :meth:`start` reads the child's first answer (``dtypes``: name ->
    numpy dtype of the stored channel); iterating yields (top, n, {name: (n,
    width) array}) top first, the arrays views of one buffer reused by the
    next band. Use through :func:`channel_bands` (the child is killed when
    the block ends)."""

    def __init__(self, path: str, names: list, height: int, width: int, rows: int, error):
        self.path, self.names = os.fspath(path), list(names)
        self.height, self.width, self.rows = int(height), int(width), max(1, min(int(rows), int(height)))
        self._error = error
        self.dtypes: dict = {}
        self._proc = None
        self._rest = bytearray()

    def start(self) -> "ChannelBands":
        request = json.dumps({"path": os.path.abspath(self.path), "names": self.names, "rows": self.rows})
        try:
            self._proc = subprocess.Popen([python_executable(), "-c", _CHILD], stdin=subprocess.PIPE,
                                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=child_env(),
                                          bufsize=0)
            self._proc.stdin.write(request.encode())
            self._proc.stdin.close()
        except OSError as exc:
            raise self._error(f"{self.path}: unreadable EXR (its decoder could not start: {exc})") from exc
        line = self._line()
        try:
            first = json.loads(line)
        except ValueError:
            first = None
        if not isinstance(first, dict):
            self._fail("its decoder answered nonsense")
        if "error" in first:
            raise self._error(f"{self.path}: unreadable EXR ({first['error']})")
        types, window = first.get("types"), first.get("window")
        try:
            x0, y0, x1, y1 = (int(v) for v in window)
        except (TypeError, ValueError):
            x0 = y0 = x1 = y1 = None
        if x0 is None or (x1 - x0 + 1, y1 - y0 + 1) != (self.width, self.height):
            self._fail(f"its decoder saw a data window {window}, the header {self.width}x{self.height}")
        if not isinstance(types, list) or len(types) != len(self.names) or any(t not in _DTYPES for t in types):
            self._fail("its decoder answered unknown channel types")
        self.dtypes = {n: _DTYPES[t] for n, t in zip(self.names, types)}
        return self

    def band_bytes(self, n: int | None = None) -> int:
        """Bytes of one band of ``n`` rows (default: a full band) of every name."""
        return (self.rows if n is None else n) * self.width * sum(d.itemsize for d in self.dtypes.values())

    def __iter__(self):
        buf = bytearray(self.band_bytes())
        for top in range(0, self.height, self.rows):
            n = min(self.rows, self.height - top)
            view = memoryview(buf)[:self.band_bytes(n)]
            self._read_into(view)
            chans, o = {}, 0
            for name in self.names:
                dt = self.dtypes[name]
                size = n * self.width * dt.itemsize
                chans[name] = np.frombuffer(buf, dt, n * self.width, o).reshape(n, self.width)
                o += size
            yield top, n, chans

    def close(self) -> None:
        p, self._proc = self._proc, None
        if p is None:
            return
        if p.poll() is None:
            p.kill()
        p.wait()
        for s in (p.stdout, p.stderr):
            s.close()

    # --- the pipe -------------------------------------------------------------------------
    def _wait(self) -> None:
        fd = self._proc.stdout.fileno()
        deadline = time.monotonic() + BAND_TIMEOUT
        while not select.select([fd], [], [], 1.0)[0]:
            if time.monotonic() > deadline:
                self._fail(f"its decoder sent nothing for {BAND_TIMEOUT} s")

    def _line(self) -> bytes:
        got = bytearray()
        while b"\n" not in got:
            self._wait()
            chunk = os.read(self._proc.stdout.fileno(), 1 << 16)
            if not chunk:
                self._fail("its decoder stopped", ended=True)
            got += chunk
            if len(got) > MAX_PREAMBLE:
                self._fail("its decoder answered nonsense")
        line, _, rest = bytes(got).partition(b"\n")
        self._rest = bytearray(rest)
        return line

    def _read_into(self, view: memoryview) -> None:
        o = 0
        if self._rest:
            k = min(len(self._rest), len(view))
            view[:k] = self._rest[:k]
            del self._rest[:k]
            o = k
        while o < len(view):
            self._wait()
            k = self._proc.stdout.readinto(view[o:])
            if not k:
                self._fail("its decoder stopped early", ended=True)
            o += k

    def _fail(self, what: str, ended: bool = False):
        """Raise the caller's error for ``what``; ``ended``: the child closed its
        output, so how it exited (a crash's signal, its last words) is told."""
        p, tail = self._proc, ""
        if p is not None and ended:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                pass
            if p.returncode is not None and p.returncode < 0:
                what = f"its decoder crashed (signal {-p.returncode})"
            if p.returncode is not None:
                text = p.stderr.read(4096).decode("utf-8", "replace").strip().splitlines()
                tail = f": {text[-1]}" if text else ""
        self.close()
        raise self._error(f"{self.path}: unreadable EXR ({what}{tail})")


@contextlib.contextmanager
def channel_bands(path, names: list, height: int, width: int, rows: int, error=ValueError):
    """A started :class:`ChannelBands`, its child killed when the block ends;
    failures raise ``error`` (a message naming the file)."""
    bands = ChannelBands(path, names, height, width, rows, error)
    try:
        yield bands.start()
    finally:
        bands.close()
