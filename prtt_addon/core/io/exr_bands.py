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
import subprocess
import tempfile
import threading
import time

import numpy as np

from ..base.child import child_env, python_executable
from ..base.memory import MemoryLimitError, check_fits

#: Seconds the child may go without delivering a byte before it is given up.
BAND_TIMEOUT = 120
#: The longest first line the child may write (types of MAX_FILE_CHANNELS names).
MAX_PREAMBLE = 4 << 20

_DTYPES = {"HALF": np.dtype(np.float16), "FLOAT": np.dtype(np.float32), "UINT": np.dtype(np.uint32)}

_CHILD = r"""
import json, os, sys
# The stream goes to a copy of stdout; whatever else writes to fd 1 (a library's
# warning, a site hook) lands on stderr and cannot shift the stream's bytes.
out = os.fdopen(os.dup(1), "wb", buffering=1 << 20)
os.dup2(2, 1)
import Imath, OpenEXR
req = json.loads(sys.stdin.read())
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
    out.close()
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
out.close()
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
        self._err = None
        self._reading_since = None
        self._timed_out = False

    def start(self) -> "ChannelBands":
        request = memoryview(json.dumps({"path": os.path.abspath(self.path), "names": self.names,
                                         "rows": self.rows}).encode())
        try:
            # stderr to a file: a decoder that writes much there must not block on a full pipe.
            self._err = tempfile.TemporaryFile()
            self._proc = subprocess.Popen([python_executable(), "-c", _CHILD], stdin=subprocess.PIPE,
                                          stdout=subprocess.PIPE, stderr=self._err, env=child_env(),
                                          bufsize=0)
        except OSError as exc:
            raise self._error(f"{self.path}: unreadable EXR (its decoder could not start: {exc})") from exc
        threading.Thread(target=self._watch, args=(self._proc,), daemon=True).start()
        try:
            while request:          # a raw pipe may take part of it
                request = request[self._proc.stdin.write(request):]
            self._proc.stdin.close()
        except OSError:
            self._fail("its decoder could not start", ended=True)
        parsed = self._preamble(self._line())
        if parsed is None:
            self._fail("its decoder answered nonsense")
        if isinstance(parsed, str):
            raise self._error(f"{self.path}: unreadable EXR ({parsed})")
        self.dtypes = parsed
        try:        # a header may declare many channels of a wide image: one band is held here and in the child
            check_fits(2 * self.band_bytes(), f"reading {self.path} ({self.rows} rows of {len(self.names)} channels)",
                       advice="free memory, or bake the texture again at a lower resolution")
        except MemoryLimitError as exc:
            raise self._error(str(exc)) from None
        return self

    def _preamble(self, line: bytes):
        """The child's first line as {name: dtype}, its error text (str), or None for nonsense."""
        try:
            first = json.loads(line)
            if "error" in first:
                return str(first["error"])
            types, window = first["types"], first["window"]
            x0, y0, x1, y1 = (int(v) for v in window)
            if (x1 - x0 + 1, y1 - y0 + 1) != (self.width, self.height):
                return f"its decoder saw a data window {window}, the header {self.width}x{self.height}"
            if len(types) != len(self.names):
                return None
            return {n: _DTYPES[t] for n, t in zip(self.names, types)}
        except Exception:       # noqa: BLE001 - whatever the bytes were, they are not our protocol
            return None

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
        # The stream must end here, and the child exit cleanly: extra bytes mean it was not our protocol.
        if self._rest or self._read_some(bytearray(1)):
            self._fail("its decoder sent more than the texture holds")
        if self._proc.wait() != 0:
            self._fail("its decoder failed", ended=True)

    def close(self) -> None:
        p, self._proc = self._proc, None
        if p is not None:
            if p.poll() is None:
                p.kill()
            p.wait()
            p.stdout.close()
            if not p.stdin.closed:
                p.stdin.close()
        if self._err is not None:
            self._err.close()
            self._err = None

    # --- the pipe -------------------------------------------------------------------------
    # Blocking reads watched by a thread (select does not take pipes on Windows): a
    # read that waits BAND_TIMEOUT seconds gets its child killed.
    def _watch(self, proc) -> None:
        while proc.poll() is None:
            since = self._reading_since
            if since is not None and time.monotonic() - since > BAND_TIMEOUT:
                self._timed_out = True
                proc.kill()
                return
            time.sleep(0.25)

    def _read_some(self, view) -> int:
        self._reading_since = time.monotonic()
        try:
            return self._proc.stdout.readinto(view) or 0
        finally:
            self._reading_since = None

    def _line(self) -> bytes:
        got = bytearray()
        chunk = bytearray(1 << 16)
        while b"\n" not in got:
            k = self._read_some(chunk)
            if not k:
                self._fail("its decoder stopped", ended=True)
            got += chunk[:k]
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
            k = self._read_some(view[o:])
            if not k:
                self._fail("its decoder stopped early", ended=True)
            o += k

    def _fail(self, what: str, ended: bool = False):
        """Raise the caller's error for ``what``; ``ended``: the child closed its
        output, so how it exited (a crash's signal, its last words) is told."""
        p, tail = self._proc, ""
        if self._timed_out:
            what, ended = f"its decoder sent nothing for {BAND_TIMEOUT} s", False
        if p is not None and ended:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                pass
            if p.returncode is not None and p.returncode < 0:
                what = f"its decoder crashed (signal {-p.returncode})"
            if p.returncode is not None:
                self._err.seek(max(0, self._err.seek(0, os.SEEK_END) - 4096))
                text = self._err.read().decode("utf-8", "replace").strip().splitlines()
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


#: Bytes of file rows :func:`read_layers` asks the child for at a time (what
#: this process holds of the file beside the layers it fills).
READ_BAND_BYTES = 64 << 20


def channel_groups(names: list) -> list:
    """Channel names four to a layer, the last padded with None (ktx2.sh_layers'
    layout of one row of coefficients: coefficient i in layer i // 4, channel i % 4)."""
    padded = list(names) + [None] * (-len(names) % 4)
    return [padded[i:i + 4] for i in range(0, len(padded), 4)]


def read_layers(path, groups: list, height: int, width: int, *, dtype=np.float16,
                error=ValueError) -> np.ndarray:
    """(len(groups), height, width, 4) ``dtype`` layers of a texture whose
    header the caller has checked: layer l's channel c holds the file's
    channel ``groups[l][c]`` (None: 0), rows in file order (top first), read
    a band of rows at a time (:func:`channel_bands`), so this process never
    holds the whole file besides the layers."""
    names = list(dict.fromkeys(n for g in groups for n in g if n is not None))
    out = np.zeros((len(groups), height, width, 4), dtype)
    if not names:
        return out
    rows = max(1, READ_BAND_BYTES // max(1, width * len(names) * 4))
    with channel_bands(path, names, height, width, rows, error=error) as stream:
        for top, n, chans in stream:
            for layer, group in enumerate(groups):
                for c, name in enumerate(group):
                    if name is not None:
                        out[layer, top:top + n, :, c] = chans[name]
    return out
