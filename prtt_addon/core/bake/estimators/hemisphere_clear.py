"""Which triangles provably see nothing: the bake's zero-ray analytic path.

A texel on triangle t (flat-shaded there) is unoccluded over its whole
hemisphere when no scene vertex lies above t's plane: all geometry is then in
the closed lower half-space, which a ray leaving the plane upwards never
re-enters. Its transfer is exactly the clamped cosine turned to its normal,
A_l y_lm(n) (zonal.zonal_to_sh), with zero rays.

The test per triangle is  max_v n_t . (v - a_t) <= PLANE_EPSILON  over all
unique scene vertices (normalised coordinates, float64):

1. only triangles that own texels are tested (occluder-only ones cannot use
   the result);
2. a cheap filter against the corners that are extreme along 64 directions
   (any vertex above the plane fails the triangle: sound);
3. the exact test for the survivors against all corners, organised in blocks
   of consecutive corners (spatially coherent in any mesh): a block whose
   bounding box lies below the plane (its support in direction n is at most
   the plane's offset) cannot hold a vertex above it and is skipped; the
   rest are checked vertex by vertex, up to ``budget`` dot products.
   Survivors beyond the budget are simply traced (counted in ``stats``),
   never assumed clear.

Texels use the path only where the shading normal equals the face normal
within 1e-3 rad and no normal map applies: a shading normal tilted from the
face would put part of its hemisphere below the surface (see transfer.py).
"""
from __future__ import annotations

import math

import numpy as np

from ...base.errors import Cancelled

#: A vertex this far above a plane (normalised units) still counts as on it.
PLANE_EPSILON = 1e-9
#: cos(1e-3 rad): shading normal close enough to the face normal for the analytic path.
FLAT_COS = math.cos(1e-3)
DEFAULT_BUDGET = 4e9


def _fibonacci(n):
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = math.pi * (1.0 + 5.0 ** 0.5) * i
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def clear_triangles(positions: np.ndarray, shaded_normals: np.ndarray, *,
                    candidates: np.ndarray | None = None,
                    budget: float = DEFAULT_BUDGET, cancel=None) -> tuple[np.ndarray, dict]:
    """(T,) bool: nothing in the scene lies above triangle t's plane on the side
    of ``shaded_normals[t]`` (unit face normals turned to the shaded side, zero
    for degenerate triangles, which are never clear). Only the triangles in
    ``candidates`` (default: all) are tested; the others are False.
    ``cancel`` (has is_set()) is checked between vertex blocks: parallel.Cancelled."""
    P = np.asarray(positions, dtype=np.float64)
    V = P.reshape(-1, 3)
    lo, hi = V.min(0), V.max(0)
    half = float(np.max(hi - lo)) * 0.5 or 1.0
    centre = 0.5 * (lo + hi)
    n = np.asarray(shaded_normals, dtype=np.float64)
    cand = np.arange(P.shape[0]) if candidates is None else np.asarray(candidates)
    live = cand[np.any(n[cand] != 0, axis=1)]
    # Plane offsets in normalised coordinates (the scale drops out of the sign).
    offset = np.einsum("tc,tc->t", n[live], (P[live, 0] - centre) / half)
    col = 1 << 18
    dirs = _fibonacci(64)
    ext = np.zeros(dirs.shape[0], np.int64)
    best = np.full(dirs.shape[0], -np.inf)
    for a in range(0, V.shape[0], col):
        d = dirs @ ((V[a:a + col] - centre) / half).T
        k = np.argmax(d, axis=1)
        v = d[np.arange(dirs.shape[0]), k]
        better = v > best
        best[better], ext[better] = v[better], k[better] + a
    E = (V[np.unique(ext)] - centre) / half
    ok = np.empty(live.size, bool)
    for a in range(0, live.size, col):          # (rows x 64) at a time, not (T x 64)
        ok[a:a + col] = (n[live[a:a + col]] @ E.T).max(axis=1) - offset[a:a + col] <= PLANE_EPSILON
    surv = np.flatnonzero(ok)
    clear_surv = np.zeros(surv.size, bool)
    unverified = 0
    if surv.size:
        B = 1024
        nb = -(-V.shape[0] // B)
        starts = np.arange(nb) * B
        blo = (np.minimum.reduceat(V, starts, axis=0) - centre) / half
        bhi = (np.maximum.reduceat(V, starts, axis=0) - centre) / half
        # Triangles on one plane (same normal and offset, exactly: a flat floor of
        # millions of triangles is one plane) share the test.
        planes, inv = np.unique(np.column_stack([n[live[surv]], offset[surv]]), axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        nn, off = planes[:, :3], planes[:, 3]
        n_pos, n_neg = np.maximum(nn, 0), np.minimum(nn, 0)
        violated = np.zeros(planes.shape[0], bool)
        work, complete = 0.0, True
        for b in range(nb):
            if cancel is not None and cancel.is_set():
                raise Cancelled()
            # Rows whose plane the block's bounding box reaches above, computed per
            # block: an (S, blocks) table was S x nb bytes (11.7 GB for a flat
            # 2M-triangle floor) and as many dot products before the budget applied.
            support = n_pos @ bhi[b] + n_neg @ blo[b]
            rows = np.flatnonzero((support - off > PLANE_EPSILON) & ~violated)
            if rows.size == 0:
                continue
            work += rows.size * B
            if work > budget:
                complete = False
                break
            block = (V[b * B:(b + 1) * B] - centre) / half
            top = (nn[rows] @ block.T).max(axis=1)
            violated[rows] |= top - off[rows] > PLANE_EPSILON
        if complete:
            clear_surv = ~violated[inv]
        else:
            unverified = int((~violated[inv]).sum())      # traced, never assumed clear
    clear = np.zeros(P.shape[0], bool)
    clear[live[surv]] = clear_surv
    stats = {"clear_triangles": int(clear.sum()), "tested_triangles": int(live.size),
             "filter_survivors": int(surv.size), "unchecked_over_budget": unverified}
    return clear, stats
