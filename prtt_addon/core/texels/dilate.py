"""Dilation and coverage-aware mip chains for baked textures.

Textures are channel-first (C, H, W) float arrays (row 0 = bottom) with a
(H, W) bool mask of texels that hold a value.

* dilate: ``iterations`` rings: every empty texel with a filled 8-neighbour
  takes the mean of its filled neighbours, then counts as filled. Bilinear
  filtering near island borders then never reads empty (zero) texels.
* mip_chain: each level averages the *covered* children of a 2x2 block
  (weighted by coverage), so empty or dilated texels never bleed into islands.
"""
from __future__ import annotations

import numpy as np

_OFFSETS = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]


def _near(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: texels with a True 8-neighbour inside the grid."""
    H, W = mask.shape
    pad = np.pad(mask, 1)
    near = np.zeros_like(mask)
    for dy, dx in _OFFSETS:
        near |= pad[1 + dy:1 + dy + H, 1 + dx:1 + dx + W]
    return near


def dilation_rings(mask: np.ndarray, iterations: int):
    """The rings a dilation fills: per iteration the empty texels (ys, xs) and,
    for each of the 8 neighbours, which of them were filled before (indices
    into the ring, and the neighbour's coordinates). Independent of the data,
    so several channel groups (threads) can share one plan."""
    if iterations < 0:
        raise ValueError(f"dilation must be >= 0 texels, got {iterations}")
    mask = mask.copy()
    H, W = mask.shape
    rings = []
    for _ in range(iterations):
        ys, xs = np.nonzero(_near(mask) & ~mask)
        if ys.size == 0:
            break
        taps, cnt = [], np.zeros(ys.size)
        for dy, dx in _OFFSETS:
            y, x = ys + dy, xs + dx
            ok = (y >= 0) & (y < H) & (x >= 0) & (x < W)
            ok[ok] = mask[y[ok], x[ok]]
            sel = np.flatnonzero(ok)
            taps.append((sel, y[sel], x[sel]))
            cnt[sel] += 1.0
        rings.append((ys, xs, taps, cnt))
        mask[ys, xs] = True
    return rings, mask


def apply_dilation(tex: np.ndarray, rings) -> None:
    """Fill ``tex`` (C, H, W) in place along a plan from :func:`dilation_rings`."""
    for ys, xs, taps, cnt in rings:
        acc = np.zeros((tex.shape[0], ys.size), np.float64)
        for sel, y, x in taps:
            acc[:, sel] += tex[:, y, x]
        tex[:, ys, xs] = (acc / cnt).astype(tex.dtype)


def dilate_rows(arrays: list, row_of: np.ndarray, width: int, rings) -> None:
    """:func:`apply_dilation` on per-texel rows instead of planes: each of
    ``arrays`` (M, ...) float holds texel t's value at row ``row_of[t]`` (t =
    y * width + x), every texel the rings read or fill having a row. The same
    sums in the same order as the planes' dilation, so the same values."""
    for ys, xs, taps, cnt in rings:
        dst = row_of[ys * width + xs]
        src = [(sel, row_of[y * width + x]) for sel, y, x in taps]
        for a in arrays:
            acc = np.zeros((ys.size,) + a.shape[1:], np.float64)
            for sel, rows in src:
                acc[sel] += a[rows]
            a[dst] = (acc / cnt.reshape((-1,) + (1,) * (a.ndim - 1))).astype(a.dtype)


def dilate(tex: np.ndarray, mask: np.ndarray, iterations: int = 3, executor=None) -> np.ndarray:
    """Grow filled regions of ``tex`` (C, H, W) by ``iterations`` texels, in place.

    With an ``executor`` (thread pool), channel groups are filled in parallel.
    Returns the grown mask (``mask`` itself is not modified).
    """
    rings, grown = dilation_rings(mask, iterations)
    if executor is None or tex.shape[0] < 2:
        apply_dilation(tex, rings)
    else:
        half = tex.shape[0] // 2
        list(executor.map(lambda sl: apply_dilation(tex[sl], rings), [slice(0, half), slice(half, None)]))
    return grown


def mip_chain(tex: np.ndarray, weight: np.ndarray, levels: int | None = None):
    """Coverage-weighted mip levels 1.. of (tex (C, H, W), weight (H, W) float, 0 = empty).

    Returns a list of (tex_k, weight_k); sizes halve (rounding up) down to 1x1
    or ``levels`` levels.
    """
    out = []
    t = tex.astype(np.float64)
    w = np.asarray(weight, dtype=np.float64)
    C = t.shape[0]
    while (levels is None or len(out) < levels) and max(w.shape) > 1:
        H, W = w.shape
        H2, W2 = (H + 1) // 2, (W + 1) // 2
        tp = np.zeros((C, 2 * H2, 2 * W2))
        wp = np.zeros((2 * H2, 2 * W2))
        tp[:, :H, :W] = t
        wp[:H, :W] = w
        num = (tp * wp).reshape(C, H2, 2, W2, 2).sum(axis=(2, 4))
        den = wp.reshape(H2, 2, W2, 2).sum(axis=(1, 3))
        t = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
        w = den / 4.0
        out.append((t.astype(tex.dtype), w))
    return out


def grown_mask(mask: np.ndarray, iterations: int) -> np.ndarray:
    """(H, W) bool: ``mask`` grown by ``iterations`` 8-neighbour rings (the
    texels a dilation fills and the covered ones), without the rings' plan."""
    grown = np.asarray(mask, bool).copy()
    for _ in range(max(0, int(iterations))):
        near = grown | _near(grown)
        if np.array_equal(near, grown):
            break
        grown = near
    return grown


class DilatedRows:
    """Channel planes (C, H, W) float32 of values known at covered texels only,
    made a band of rows at a time (exr_io.write_sh_planes' plane source) or
    one plane at a time (:meth:`at`): each level's values scattered into zero
    planes and dilated as :func:`dilate` dilates a whole stack, the levels'
    dilated planes added in order as stacks would be. The values are the
    same: dilation is per channel, and a texel ``iterations`` rings out reads
    only texels within as many rows (:meth:`band` dilates a window that
    reaches that far beyond the band and keeps the band's rows).

    levels : list of (C, N) float32, column i the value at texel ``texel[i]``;
             or one estimators.column_spill.ColumnSpill (``scatter_rows``: the
             columns are in its file; :meth:`band` only).
    texel : (N,) int64 flat texel indices (row 0 = bottom) of ``mask`` (H, W).
    """

    def __init__(self, levels: list, texel: np.ndarray, mask: np.ndarray, iterations: int):
        self.levels = levels
        self.texel = texel
        self.mask = np.asarray(mask, bool)
        self.iterations = int(iterations)
        H, W = self.mask.shape
        self.shape = (int(levels[0].shape[0]), H, W)
        self.grown = grown_mask(self.mask, self.iterations)
        self._rings = None
        self._sorted = None

    def _scatter(self, rows, y0: int, y1: int, out: np.ndarray) -> None:
        """Level ``rows``' values at texture rows y0 .. y1 - 1 into ``out`` (C, y1 - y0, W)."""
        if hasattr(rows, "scatter_rows"):
            rows.scatter_rows(y0, y1, out)
            return
        W = self.shape[2]
        if self._sorted is None:
            order = np.argsort(self.texel, kind="stable")
            self._sorted = (order, self.texel[order])
        order, st = self._sorted
        lo, hi = np.searchsorted(st, [y0 * W, y1 * W])
        cols = order[lo:hi]
        out.reshape(out.shape[0], -1)[:, st[lo:hi] - y0 * W] = rows[:, cols]

    def band(self, y0: int, y1: int) -> np.ndarray:
        """(C, y1 - y0, W) float32: rows y0 .. y1 - 1 of every channel, dilated, summed over the levels."""
        C, H, W = self.shape
        w0, w1 = max(0, y0 - self.iterations), min(H, y1 + self.iterations)
        rings, _ = dilation_rings(self.mask[w0:w1], self.iterations)
        out = None
        for rows in self.levels:
            p = np.zeros((C, w1 - w0, W), np.float32)
            self._scatter(rows, w0, w1, p)
            apply_dilation(p, rings)
            if out is None:
                out = p
            else:
                out += p
        return out[:, y0 - w0:y1 - w0]

    def channel(self, c: int, levels=None) -> np.ndarray:
        """(H, W) float32: channel ``c``, dilated, summed over ``levels`` (default all)."""
        _, H, W = self.shape
        if self._rings is None:
            self._rings = dilation_rings(self.mask, self.iterations)[0]
        out = None
        for rows in self.levels if levels is None else levels:
            p = np.zeros((1, H * W), np.float32)
            p[0, self.texel] = rows[c]
            p = p.reshape(1, H, W)
            apply_dilation(p, self._rings)
            if out is None:
                out = p
            else:
                out += p
        return out[0]

    def value_range(self) -> tuple[float, float]:
        """(min, max) of the planes: the levels' sum at the covered texels, and 0
        where texels stay empty (dilated texels average covered ones, within
        that range to rounding)."""
        if len(self.levels) == 1 and hasattr(self.levels[0], "value_range"):    # ColumnSpill
            lo, hi = self.levels[0].value_range()
        else:
            total = self.levels[0]
            for rows in self.levels[1:]:
                total = total + rows
            lo, hi = (float(np.min(total)), float(np.max(total))) if total.size else (0.0, 0.0)
        if not self.grown.all():
            lo, hi = min(lo, 0.0), max(hi, 0.0)
        return lo, hi

    def at(self, texels: np.ndarray, level: int = -1, executor=None) -> np.ndarray:
        """(C, n) float32: one level's dilated planes at flat texel indices ``texels``."""
        mapper = executor.map if executor is not None else map
        cols = mapper(lambda c: self.channel(c, [self.levels[level]]).reshape(-1)[texels], range(self.shape[0]))
        out = np.empty((self.shape[0], texels.size), np.float32)
        for c, v in enumerate(cols):
            out[c] = v
        return out
