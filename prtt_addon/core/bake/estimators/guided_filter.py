"""Smoothing of the guided texels' transfer (issue 53, item 1).

Why: a texel lit through a window sees its light in a few hundredths of its
hemisphere. Guided rays (guided.py) find that opening every time, but at 256
rays what each texel collects of it still varies from texel to texel by ~6 %
(bench window-room: 6.3 % mean error over the lit texels), visibly blotchy
on a wall. Its neighbours on the same surface see nearly the same opening,
so a small joint bilateral filter of the guided texels' rows, guided by the
G-buffer, averages that noise away (2.98 % in the bench, with texel
validity) while the texels the guide left alone keep their rows bit for bit.

Weight of neighbour q for a guided texel p (q a covered, valid texel of the
set within ``RADIUS`` texels; the G-buffer's positions x and shading normals n):

    exp(-|q - p|^2 / 2 SIGMA_TEXELS^2) exp(-|x_q - x_p|^2 / 2 (SIGMA_STEPS s)^2) max(0, n_p.n_q)^NORMAL_POWER

with s the set's texel step (validity.texel_step). The world term keeps texels
of other UV islands (far away in the world, near in the atlas) and across
folds out, as islands would; texels inside geometry (validity.py) are never
neighbours: they bake black, and averaging them in darkens a wall's foot by
a quarter (the reason the filter is measured with texel validity on).

The filter is linear in the coefficients (every SH coefficient alike) and
reads only the unfiltered rows: the answer does not depend on the order of
texels or on how they are split (bands of texture rows, each written once
the next band is computed; two bands' outputs are held at once). The sums
are float32 einsum loops in a fixed order: the same bits on any machine and
thread count. With numba (core/base/jit.py) a compiled loop does a band
(guided_filter_jit): the same neighbours and weights, the same values to
float32 rounding (not the same bits), in a fraction of the time.
"""
from __future__ import annotations

import math
import threading

import numpy as np

from ...base import jit
from ...base.threads import map_items

#: Window half-width in texels, the texel-distance sigma, the world-distance sigma in texel
#: steps and the normals' power. The window room (512², 256 rays, the prototype of this filter on
#: the bench's texels, inside texels left out): radius 1 3.3 %, 2 3.1 %, 3 3.1 %; sigma 1.5 texels
#: 3.2 %, 2 3.3 % (wider kernels blur more than they average); the bake with these: 2.98 %.
RADIUS = 2
SIGMA_TEXELS = 1.0
SIGMA_STEPS = 2.0
NORMAL_POWER = 16
#: Texture rows a band of targets spans (at least RADIUS; ~50 MB of temporaries at 4096 texels wide).
BAND_ROWS = 16
#: Targets whose neighbours' rows are gathered at a time.
SUB = 4096
#: Bytes a target holds for the numpy path's offset in flight (filter_bytes).
OFFSET_BYTES = 320
#: Bands filtered at a time on an executor's threads (their outputs held until written).
GROUP = 4


def filter_bytes(width: int, coeffs: int, height: int | None = None) -> int:
    """Upper bound of the filter's temporaries (bytes) for a set ``width``
    texels wide with ``coeffs`` coefficients a row, the larger of its two
    layouts: one band at a time (two bands' outputs, one band's gathered
    neighbours: float32 and float64 sums, indices, weights, SUB targets'
    rows) or GROUP bands of a GROUP-th the rows (GROUP + 1 outputs, GROUP
    gathers of a GROUP-th the targets); and the numpy path's texel lookup
    (4 B a texel of the set, ``height`` rows: ``width`` unless given)."""
    per_offset = (2 * RADIUS + 1) ** 2 * (8 + 8 + 4)       # neighbour index, weight, float32 weight

    def layout(rows, group, sub):
        texels = rows * width
        return (texels * ((group + 1) * 4 * coeffs + group * (per_offset + 64))
                + group * sub * (2 * RADIUS + 1) ** 2 * 4 * coeffs)
    grouped = layout(_grouped_rows(), GROUP, _grouped_sub())
    # The numpy path's one offset in flight: its bounds, lookups and indices (~60 B a
    # target), the gathered positions and normals and their differences (~170 B);
    # with 320 B the peaks are 0.97 of the bound (tests/test_guided_filter.py).
    offset = BAND_ROWS * width * OFFSET_BYTES
    return max(layout(BAND_ROWS, 1, SUB) + offset, grouped) + 4 * width * (width if height is None else height)


def _grouped_rows() -> int:
    """Texture rows of a band when GROUP bands run at once (at least RADIUS)."""
    return max(RADIUS, BAND_ROWS // GROUP)


def _grouped_sub() -> int:
    """Targets gathered at a time by each of GROUP bands at once."""
    return max(1, SUB // GROUP)


_JIT = "prtt_addon.core.bake.estimators.guided_filter_jit"


def _compiled():
    """The compiled band loop (guided_filter_jit), or None: numba off or missing."""
    return jit.load(_JIT)


def _band(rows, texel, lookup, width, height, position, normal, valid, tg, offsets, spatial, inv_world,
          sub: int = SUB) -> np.ndarray:
    """(M, K) float32: the filtered rows of one band's targets ``tg`` (M,),
    numpy: each target's neighbours (index, weight; weight 0 where there is
    none), then the weighted sum of their rows, ``sub`` targets at a time (C
    loops of einsum: the same sums whatever the machine; ~10 MB of gathered
    rows). ``lookup`` (H W,) int32: the row of each texel, -1 where none
    (found without a search: the same neighbours, in the same order).
    Reads ``rows`` only."""
    flat = texel[tg]
    y, x = flat // width, flat % width
    p0, n0 = position[tg], normal[tg]
    nb = np.zeros((tg.size, len(offsets)), np.int64)
    wt = np.zeros((tg.size, len(offsets)), np.float64)
    for o, ((dy, dx), ws) in enumerate(zip(offsets, spatial)):
        yq, xq = y + dy, x + dx
        ok = (yq >= 0) & (yq < height) & (xq >= 0) & (xq < width)
        j = np.where(ok, lookup[np.where(ok, yq * width + xq, 0)], -1)    # the row of texel q, -1: none
        ok = j >= 0
        ok[ok] = valid[j[ok]]
        i, j = np.flatnonzero(ok), j[ok]
        # A sum of 3 in order, as np.sum over the axis adds them (the same bits).
        pj, p0i = position[j], p0[i]
        d0, d1, d2 = pj[:, 0] - p0i[:, 0], pj[:, 1] - p0i[:, 1], pj[:, 2] - p0i[:, 2]
        dw = d0 * d0 + d1 * d1 + d2 * d2
        nj, n0i = normal[j], n0[i]
        cos = np.clip(nj[:, 0] * n0i[:, 0] + nj[:, 1] * n0i[:, 1] + nj[:, 2] * n0i[:, 2], 0.0, 1.0)
        nb[i, o] = j
        wt[i, o] = ws * np.exp(-dw * inv_world) * cos ** NORMAL_POWER
    wsum = wt.sum(axis=1)
    good = wsum > 0
    wt[good] /= wsum[good, None]
    wt = wt.astype(np.float32)
    out = rows[tg]
    for a in range(0, tg.size, sub):
        b = min(a + sub, tg.size)
        g = np.flatnonzero(good[a:b]) + a
        out[g] = np.einsum("mo,mok->mk", wt[g], rows[nb[g]])
    return out


def smooth_guided(rows: np.ndarray, texel: np.ndarray, width: int, height: int, position: np.ndarray,
                  normal: np.ndarray, targets: np.ndarray, valid: np.ndarray, step: float, *,
                  compiled: bool = True, executor=None) -> int:
    """Filter ``rows`` (N, K) float32 in place at the rows ``targets`` (M,)
    int (ascending), texels of a set ``width`` x ``height``: ``texel`` (N,)
    flat indices ascending (the G-buffer's), ``position``/``normal`` (N, 3)
    world, unit; ``valid`` (N,) bool: texels that may be neighbours; ``step``
    the set's texel step (world units, > 0); ``compiled``: False takes the numpy
    path even where numba is there (the tests compare the two); ``executor``:
    a thread pool on which the compiled loop (which holds no GIL) filters
    GROUP bands at a time. Returns the texels filtered.

    Every band is filtered from the rows as traced: a band's filtered rows are
    written once the bands that read them (the next, within RADIUS <=
    BAND_ROWS rows) are filtered, so the answer does not depend on the
    threads or the grouping."""
    targets = np.asarray(targets, np.int64)
    if targets.size == 0 or step <= 0:
        return 0
    r = RADIUS
    offsets = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
    spatial = [math.exp(-(dy * dy + dx * dx) / (2.0 * SIGMA_TEXELS ** 2)) for dy, dx in offsets]
    inv_world = 1.0 / (2.0 * (SIGMA_STEPS * step) ** 2)
    state = {"fast": _compiled() if compiled else None}
    lock = threading.Lock()
    # GROUP bands at once of a GROUP-th the rows each (the memory of one band at a
    # time) where the compiled loop runs them: it holds no GIL, while the numpy path's
    # many small steps on thin bands would wait for it (0.07 s -> 0.15 s, the window room).
    group = GROUP if executor is not None and state["fast"] is not None else 1
    band_rows, sub = (_grouped_rows(), _grouped_sub()) if group > 1 else (BAND_ROWS, SUB)
    ty = texel[targets] // width
    band_of = ty // band_rows
    cuts = np.flatnonzero(np.diff(band_of)) + 1
    bands = np.split(np.arange(targets.size), cuts)
    spatial_f64 = np.asarray(spatial, np.float64)

    def band(members) -> tuple:
        """(the band's target rows, their filtered values), from ``rows`` as traced."""
        tg = targets[members]
        fast = state["fast"]
        if fast is not None:
            out = np.empty((tg.size, rows.shape[1]), np.float32)
            try:
                fast.smooth_band(rows, texel, width, height, position, normal, valid, tg, spatial_f64, r,
                                 inv_world, NORMAL_POWER, out)
                return tg, out
            except Exception as exc:    # noqa: BLE001 - a numba that imports but cannot compile it
                jit.broken(_JIT, exc)
                state["fast"] = None
        with lock:                      # made once, by the first band that needs it
            if state.get("lookup") is None:
                lookup = np.full(width * height, -1, np.int32 if texel.size < 1 << 31 else np.int64)
                lookup[texel] = np.arange(texel.size)
                state["lookup"] = lookup
        return tg, _band(rows, texel, state["lookup"], width, height, position, normal, valid, tg, offsets, spatial,
                         inv_world, sub)

    pending = None                    # the band before this group's, filtered, not yet written
    for a in range(0, len(bands), group):
        part = bands[a:a + group]
        done = map_items(executor, band, part)
        # The band before reads no row of this group's neighbours any more: write it now,
        # and every band of the group but the last (the next group's first band reads it).
        for tg, out in ([pending] if pending is not None else []) + done[:-1]:
            rows[tg] = out
        pending = done[-1]
    rows[pending[0]] = pending[1]
    return int(targets.size)
