"""Texel columns held at the precision of the half-float file they become.

A bake level's result is a (C, N) table, column i the value of every channel
at covered texel ``texel[i]``, later scattered into planes, dilated
(:mod:`.dilate`) and written as float16. Held as float32 until the write it
costs 4 C N bytes; :class:`HalfColumns` holds it in 2 C N and still writes
the same bytes:

* a covered texel's value reaches the file as float16(v) either way
  (float16(float32(float16(v))) = float16(v), and the mantissa rounding of
  exr_io.quantize_half starts from that float16);
* dilated texels average their filled neighbours in float64 (dilate.apply_dilation):
  the covered texels that some empty 8-neighbour reads (the islands' borders)
  are kept exactly, in float32 beside the float16 table, so the rings come out
  as they did from the float32 table;
* ``exact_channels`` (the DC responses a bake sums for its early stop) are
  kept whole in float32;
* a value beyond the float16 range (|v| > 65504, which would make the file
  float32) sets :attr:`overflow`: the caller then bakes the level again
  into a float32 table.

Only one level's table can be held so: levels summed, or read by a next
level, need their float32 values (relightable_stage keeps float32 there).
"""
from __future__ import annotations

import numpy as np

HALF_MAX = float(np.finfo(np.float16).max)


def border_texels(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: covered texels (``mask``) with an empty 8-neighbour inside
    the grid: those the first dilation ring reads."""
    H, W = mask.shape
    empty = np.pad(~mask, 1, constant_values=False)
    near = np.zeros_like(mask)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                near |= empty[1 + dy:1 + dy + H, 1 + dx:1 + dx + W]
    return near & mask


class HalfColumns:
    """A (C, N) float32 table stored as float16, with exact float32 columns at
    the islands' border texels and exact float32 rows for ``exact_channels``.

    texel : (N,) int64 flat texel index of column i in ``mask`` (H, W), row 0 at the bottom.
    dilate : the dilation rings the table will get (0: no border is kept).
    """

    def __init__(self, channels: int, texel: np.ndarray, mask: np.ndarray, dilate: int,
                 exact_channels=()):
        n = int(texel.size)
        self.shape = (int(channels), n)
        self.half = np.zeros(self.shape, np.float16)
        border = border_texels(mask).reshape(-1)[texel] if dilate > 0 else np.zeros(n, bool)
        self.border_cols = np.flatnonzero(border)
        self.slot = np.full(n, -1, np.int64)
        self.slot[self.border_cols] = np.arange(self.border_cols.size)
        self.border = np.zeros((self.shape[0], self.border_cols.size), np.float32)
        self.exact_channels = [int(c) for c in exact_channels]
        self.exact = np.zeros((len(self.exact_channels), n), np.float32)
        self.overflow = False

    @property
    def nbytes(self) -> int:
        return self.half.nbytes + self.border.nbytes + self.exact.nbytes + self.slot.nbytes

    def store(self, cols: np.ndarray, src: np.ndarray, first: int = 0) -> None:
        """Channels first .. first + c - 1 of columns ``cols`` (n,) int64 from
        ``src`` (c, n) float32 (threads may store disjoint columns)."""
        src = np.asarray(src, np.float32)
        if src.size and not self.overflow and float(np.abs(src).max(initial=0.0)) > HALF_MAX:
            self.overflow = True
        last = first + src.shape[0]
        with np.errstate(over="ignore"):        # flagged above: the caller re-traces into float32
            self.half[first:last, cols] = src
        at = self.slot[cols]
        on = at >= 0
        if on.any():
            self.border[first:last, at[on]] = src[:, on]
        for r, c in enumerate(self.exact_channels):
            if first <= c < last:
                self.exact[r, cols] = src[c - first]

    def __getitem__(self, c: int) -> np.ndarray:
        """(N,) float32: channel ``c`` as the file will hold it, exact at the border columns."""
        if c in self.exact_channels:
            return self.exact[self.exact_channels.index(c)].copy()
        row = self.half[c].astype(np.float32)
        row[self.border_cols] = self.border[c]
        return row

    def value_range(self) -> tuple[float, float]:
        """(min, max) of the stored values (NaN when any is NaN)."""
        if not self.half.size:
            return 0.0, 0.0
        parts = [self.half, self.border, self.exact]
        lo = np.min(np.array([np.min(a) for a in parts if a.size], np.float64))
        hi = np.max(np.array([np.max(a) for a in parts if a.size], np.float64))
        return float(lo), float(hi)
