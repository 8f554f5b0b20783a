"""numba-compiled UV island labels (imported through core/base/jit.py).

islands.island_labels' numpy rounds of min-label propagation were most of the
bounce's exit stage on the room's 1024² atlas (its critical path;
docs/benchmarks.md); a union-find pass over the texels gives the same labels
in milliseconds.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(nogil=True, cache=True)
def _find(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]           # path halving
        i = parent[i]
    return i


@numba.njit(nogil=True, cache=True)
def island_labels(mask):
    """(H, W) int64 from a (H, W) bool mask: each covered texel's 8-connected
    island labelled by its smallest flat index, -1 for empty texels (the
    numpy path's result exactly: every union keeps the smaller root)."""
    H, W = mask.shape
    parent = np.full(H * W, -1, np.int64)
    for y in range(H):
        for x in range(W):
            if not mask[y, x]:
                continue
            i = y * W + x
            parent[i] = i
            # The neighbours already visited: left, and the three above.
            for dy, dx in ((0, -1), (-1, -1), (-1, 0), (-1, 1)):
                yy, xx = y + dy, x + dx
                if yy >= 0 and 0 <= xx < W and mask[yy, xx]:
                    a, b = _find(parent, i), _find(parent, yy * W + xx)
                    if a < b:
                        parent[b] = a
                    elif b < a:
                        parent[a] = b
    out = np.full((H, W), -1, np.int64)
    for y in range(H):
        for x in range(W):
            i = y * W + x
            if parent[i] >= 0:
                out[y, x] = _find(parent, i)
    return out
