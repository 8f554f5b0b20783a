"""numba-compiled band of the guided texels' filter (imported through
core/base/jit.py; guided_filter.py keeps the numpy path).

The numpy path gathers each target's 25 neighbours into arrays (indices,
weights, then their rows: ~100 B a neighbour) and sums them with einsum:
0.19 s of the window room's 512² bake, most of it the gathers. This loop
visits the same neighbours in the same order, with the same float64 weights
normalised and rounded to float32, and sums the rows in float32 neighbour
by neighbour (no fused multiply-add without fastmath): the same values to
float32 rounding (tests/test_guided_filter.py), though not the same bits
(einsum orders its float32 sums in its own way). Its answer, like the numpy
path's, depends neither on threads nor on how the targets are split.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(nogil=True, cache=True, error_model="numpy")
def smooth_band(rows, texel, width, height, position, normal, valid, targets, spatial, radius, inv_world,
                power, out):
    """out[m] = the filtered row of target ``targets[m]`` (rows (N, K) float32,
    read only; out (M, K) float32); spatial ((2r + 1)², float64) the texel
    distance weights in the numpy path's offset order (dy, then dx)."""
    n = texel.size
    K = rows.shape[1]
    side = 2 * radius + 1
    ws = np.empty(side * side)
    js = np.empty(side * side, np.int64)
    for m in range(targets.size):
        p = targets[m]
        f = texel[p]
        y, x = f // width, f % width
        total = 0.0
        o = 0
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                w = 0.0
                j = 0
                yq, xq = y + dy, x + dx
                if 0 <= yq < height and 0 <= xq < width:
                    q = yq * width + xq
                    j = min(np.searchsorted(texel, q), n - 1)
                    if texel[j] == q and valid[j]:
                        dw = 0.0
                        c = 0.0
                        for a in range(3):
                            d = position[j, a] - position[p, a]
                            dw += d * d
                            c += normal[j, a] * normal[p, a]
                        c = min(max(c, 0.0), 1.0)
                        w = spatial[o] * math.exp(-dw * inv_world) * c ** power
                ws[o] = w
                js[o] = j
                total += w
                o += 1
        if total > 0.0:
            for k in range(K):
                acc = np.float32(0.0)
                for o in range(side * side):
                    if ws[o] > 0.0:                # no neighbour there: its row is never read
                        acc += np.float32(ws[o] / total) * rows[js[o], k]
                out[m, k] = acc
        else:
            for k in range(K):
                out[m, k] = rows[p, k]
