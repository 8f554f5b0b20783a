"""A bake level's texel columns kept in a temporary file until the texture is
written, read back a band of texture rows at a time.

A relightable bounce level's result is a (C, N) float32 table, column i the
value of every channel at covered texel ``texel[i]``: at a 4096² atlas 147
channels on its 2048² bounce grid, 1.0 GB even at half precision, held until
the file is written. The trace fills it a chunk of texels at a time, in no
order of rows; the writer takes it a band of rows at a time
(exr_io.write_sh_planes, texels.dilate.DilatedRows). :class:`ColumnSpill`
appends each chunk's columns to one temporary file as records, split by the
band of rows (``bucket_rows``) their texels lie in, and keeps only an index
of them in memory, with the few channels the bake sums at once
(``exact_channels``: the DC responses its early stop reads) and the value
range. :meth:`ColumnSpill.scatter_rows` reads back the records of the
buckets a window of rows touches. The values are the float32 ones, bit for
bit: the texture written from them is the one the in-memory table gave.

The file is made in the output folder under the bake's temporary prefix and
its name is removed at once (POSIX: only the open descriptor holds it;
Windows: opened delete-on-close), so nothing is left behind whatever ends
the process, a SIGKILL or the OOM killer included; :meth:`close` gives its
space back. Writes and reads take a lock (several trace threads store at
once; no ``pwrite``, which Windows lacks).
"""
from __future__ import annotations

import os
import secrets
import threading

import numpy as np

from ...base.atomic import temp_prefix

#: Rows of a bucket. The writer's bands are whole multiples of 32 rows (exr_io.WRITE_BAND_BLOCK)
#: and read their dilation rings beyond: buckets of 8 rows read a few rows more than the
#: window (32 would read three buckets of 32 for a band of 32 and 3 rings a side).
BUCKET_ROWS = 8


def _open_unnamed(folder: str, stem: str):
    """A new binary file in ``folder`` opened for reading and writing, unbuffered,
    whose name is gone already (POSIX) or goes when it is closed (Windows)."""
    # A fresh random name: on Windows an earlier set's spill keeps its name until it is closed.
    path = os.path.join(folder, f"{temp_prefix(stem)}{secrets.token_hex(8)}.spill")
    flags = os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0) | getattr(os, "O_TEMPORARY", 0)
    fd = os.open(path, flags, 0o600)
    if not getattr(os, "O_TEMPORARY", 0):
        os.unlink(path)
    return path, open(fd, "w+b", buffering=0)


class ColumnSpill:
    """A (C, N) float32 table of texel columns, kept in a temporary file.

    channels : C.
    texel : (N,) int64 flat texel index of column i (row 0 at the bottom) on a
            ``width`` x ``height`` grid.
    folder : where the temporary file goes (the bake's output folder).
    exact_channels : channels also kept in memory, whole ((N,) float32 each, ``spill[c]``).
    """

    def __init__(self, channels: int, texel: np.ndarray, width: int, height: int, folder: str,
                 exact_channels=(), bucket_rows: int = BUCKET_ROWS):
        self.shape = (int(channels), int(texel.size))
        self.texel = texel
        self.width, self.height = int(width), int(height)
        self.bucket_rows = max(1, int(bucket_rows))
        self.exact_channels = [int(c) for c in exact_channels]
        self.exact = np.zeros((len(self.exact_channels), texel.size), np.float32)
        self._lo, self._hi = np.inf, -np.inf
        self._lock = threading.Lock()
        n_buckets = -(-self.height // self.bucket_rows)
        self._index: list[list[tuple[int, int, int, int]]] = [[] for _ in range(n_buckets)]
        self._end = 0
        # Records are large: no buffer to flush (and every write and read is looped to its end).
        self.path, self._file = _open_unnamed(folder, "columns")
        self.bytes_written = 0

    def store(self, cols: np.ndarray, src: np.ndarray, first: int = 0) -> None:
        """Channels first .. first + c - 1 of columns ``cols`` (n,) from ``src``
        (c, n) float32 (threads may store disjoint columns)."""
        src = np.asarray(src, np.float32)
        c, n = src.shape
        if n == 0:
            return
        texel = self.texel[cols]
        bucket = texel // (self.width * self.bucket_rows)
        order = np.argsort(bucket, kind="stable")
        bucket, texel, vals = bucket[order], texel[order], src[:, order]
        cuts = np.flatnonzero(np.diff(bucket)) + 1
        parts = []
        for a, b in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [n]])):
            t = np.ascontiguousarray(texel[a:b], np.int64)
            v = np.ascontiguousarray(vals[:, a:b])
            parts.append((int(bucket[a]), int(b - a), t.tobytes() + v.tobytes()))
        lo, hi = (float(np.min(src)), float(np.max(src)))
        with self._lock:
            for r, ch in enumerate(self.exact_channels):
                if first <= ch < first + c:
                    self.exact[r, cols] = src[ch - first]
            # np.min / np.max propagate NaN: keep it (the writer refuses non-finite values).
            self._lo = lo if np.isnan(lo) else min(self._lo, lo)
            self._hi = hi if np.isnan(hi) else max(self._hi, hi)
            self._file.seek(self._end)
            for bk, m, payload in parts:
                view = memoryview(payload)
                while view:                             # an unbuffered write may take part of it
                    view = view[self._file.write(view):]
                self._index[bk].append((self._end, int(first), c, m))
                self._end += len(payload)
            self.bytes_written = self._end

    def __getitem__(self, c: int) -> np.ndarray:
        """(N,) float32: channel ``c``, one of ``exact_channels``."""
        if c not in self.exact_channels:
            raise KeyError(f"channel {c} is in the spill file only (kept whole: {self.exact_channels})")
        return self.exact[self.exact_channels.index(c)].copy()

    def value_range(self) -> tuple[float, float]:
        """(min, max) of the stored values (NaN when any is NaN; (0, 0) when none)."""
        if self._lo > self._hi:
            return 0.0, 0.0
        return float(self._lo), float(self._hi)

    def scatter_rows(self, y0: int, y1: int, out: np.ndarray) -> None:
        """Write the stored values of texture rows y0 .. y1 - 1 into ``out``
        (C, y1 - y0, W) float32 at their texels (others are left as they are)."""
        W = self.width
        flat = out.reshape(out.shape[0], -1)
        b0, b1 = y0 // self.bucket_rows, -(-y1 // self.bucket_rows)
        with self._lock:
            if self._file is None:
                raise ValueError(f"{self.path}: the spilled columns were closed (deleted) already")
            for bk in range(b0, min(b1, len(self._index))):
                for off, first, c, m in self._index[bk]:
                    self._file.seek(off)
                    raw = bytearray(8 * m + 4 * c * m)
                    got = 0
                    while got < len(raw):                # an unbuffered read may return part of it
                        n = self._file.readinto(memoryview(raw)[got:])
                        if not n:
                            raise OSError(f"{self.path}: the spill file ends early")
                        got += n
                    texel = np.frombuffer(raw, np.int64, m)
                    vals = np.frombuffer(raw, np.float32, c * m, 8 * m).reshape(c, m)
                    if texel.min() >= y0 * W and texel.max() < y1 * W:      # a record inside the window
                        flat[first:first + c, texel - y0 * W] = vals
                        continue
                    keep = (texel >= y0 * W) & (texel < y1 * W)
                    flat[first:first + c, texel[keep] - y0 * W] = vals[:, keep]

    @property
    def closed(self) -> bool:
        return self._file is None

    def file_bytes(self) -> int:
        """Bytes the file holds now (0 once closed)."""
        with self._lock:
            return 0 if self._file is None else os.fstat(self._file.fileno()).st_size

    def close(self) -> None:
        """Close the file, giving its space back (reading it afterwards is an error)."""
        with self._lock:
            if self._file is not None:
                self._file.close()
                self._file = None
                self._index = [[] for _ in self._index]

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
