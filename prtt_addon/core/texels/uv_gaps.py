"""How far apart a UV map's islands are, in texels: the padding bilinear
lookups, dilation and the coarse bounce grid rely on (issue 53).

An island is a set of triangles connected through shared UV corners (the
same UV coordinate on a shared vertex, as Blender's UV editor joins them).
The gap between two islands is the smallest Euclidean distance between a
point of one and a point of the other, in texels of a ``resolution``²
texture: exact for triangles (edge-to-edge distances; touching or
overlapping triangles are 0 apart).

Only pairs closer than ``within`` texels are measured: triangles are put in
the cells of a grid ``within`` texels wide that their bounding box, grown by
within / 2, touches; two triangles of different islands that share a cell
are a candidate pair. numpy only (it runs beside bpy in the tests and benchmarks).
"""
from __future__ import annotations

import numpy as np

#: Candidate pairs measured at a time (9 edge pairs of float64 temporaries each: ~100 MB).
PAIR_CHUNK = 200_000


def uv_islands(tri_uv: np.ndarray) -> np.ndarray:
    """(T,) int64 island label per triangle of tri_uv (T, 3, 2): triangles
    sharing a corner UV (equal to 1e-7 of the UV square) are one island."""
    t = tri_uv.shape[0]
    if t == 0:
        return np.zeros(0, np.int64)
    keys = np.round(np.asarray(tri_uv, np.float64).reshape(-1, 2) * 1e7).astype(np.int64)
    _, corner = np.unique(keys, axis=0, return_inverse=True)
    corner = corner.reshape(t, 3)
    # Label propagation over the corner-triangle graph: every corner takes the
    # smallest triangle label touching it, every triangle the smallest of its
    # corners', until nothing changes (pointer jumping keeps the rounds few).
    label = np.arange(t)
    while True:
        at_corner = np.full(corner.max() + 1, t, np.int64)
        np.minimum.at(at_corner, corner.ravel(), np.repeat(label, 3))
        new = at_corner[corner].min(axis=1)
        new = new[new]                                   # jump: a label's own label
        if np.array_equal(new, label):
            return np.unique(label, return_inverse=True)[1].astype(np.int64)
        label = new


def _point_segment(p, a, b):
    ab = b - a
    t = np.clip(np.einsum("...i,...i", p - a, ab) / np.maximum(np.einsum("...i,...i", ab, ab), 1e-300), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def _cross(o, a, b):
    return (a[..., 0] - o[..., 0]) * (b[..., 1] - o[..., 1]) - (a[..., 1] - o[..., 1]) * (b[..., 0] - o[..., 0])


def triangle_distances(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(P,) distances between triangles A[i] and B[i] (P, 3, 2); 0 where they touch or overlap."""
    best = np.full(A.shape[0], np.inf)
    for i in range(3):
        a0, a1 = A[:, i], A[:, (i + 1) % 3]
        for j in range(3):
            b0, b1 = B[:, j], B[:, (j + 1) % 3]
            d = np.minimum(np.minimum(_point_segment(a0, b0, b1), _point_segment(a1, b0, b1)),
                           np.minimum(_point_segment(b0, a0, a1), _point_segment(b1, a0, a1)))
            crossing = (_cross(a0, a1, b0) * _cross(a0, a1, b1) < 0) & (_cross(b0, b1, a0) * _cross(b0, b1, a1) < 0)
            best = np.minimum(best, np.where(crossing, 0.0, d))

    def inside(p, T):
        s = [_cross(T[:, k], T[:, (k + 1) % 3], p) for k in range(3)]
        return ((s[0] >= 0) & (s[1] >= 0) & (s[2] >= 0)) | ((s[0] <= 0) & (s[1] <= 0) & (s[2] <= 0))
    return np.where(inside(A[:, 0], B) | inside(B[:, 0], A), 0.0, best)


class OverBudget(Exception):
    """The measure would take more cells or candidate pairs than it was allowed."""


def candidate_pairs(uv: np.ndarray, label: np.ndarray, within: float, budget: int | None = None) -> np.ndarray:
    """(P, 2) triangle index pairs of different islands whose bounding boxes,
    grown by within / 2, share a grid cell ``within`` wide (uv in texels).
    ``budget``: OverBudget before allocating more than that many cell entries
    or candidate pairs (many small triangles in few cells: a pair count that
    grows with the square of the triangles a cell holds)."""
    lo = np.floor((uv.min(axis=1) - within / 2) / within).astype(np.int64)
    hi = np.floor((uv.max(axis=1) + within / 2) / within).astype(np.int64)
    nx, ny = hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1
    count = nx * ny
    if budget is not None and int(count.sum()) > budget:
        raise OverBudget(f"{int(count.sum())} cell entries")
    tri = np.repeat(np.arange(len(uv)), count)
    k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    cx = lo[tri, 0] + k % nx[tri]
    cy = lo[tri, 1] + k // nx[tri]
    cell = (cx - cx.min()) * (cy.max() - cy.min() + 1) + (cy - cy.min())
    order = np.lexsort((label[tri], cell))
    cell, tri = cell[order], tri[order]
    # Cells holding more than one island only.
    start = np.flatnonzero(np.r_[True, cell[1:] != cell[:-1]])
    end = np.r_[start[1:], len(cell)]
    lab = label[tri]
    mixed = lab[start] != lab[end - 1]
    n = (end - start)[mixed].astype(np.int64)
    if budget is not None and int((n * (n - 1) // 2).sum()) > budget:
        raise OverBudget(f"{int((n * (n - 1) // 2).sum())} candidate pairs")
    pairs = []
    for s, e in zip(start[mixed], end[mixed]):
        t, l = tri[s:e], lab[s:e]
        i, j = np.triu_indices(e - s, 1)
        keep = l[i] != l[j]
        pairs.append(np.stack([t[i[keep]], t[j[keep]]], axis=1))
    if not pairs:
        return np.zeros((0, 2), np.int64)
    pairs = np.unique(np.sort(np.concatenate(pairs), axis=1), axis=0)
    # Bounding boxes further apart than ``within`` hold no closer points.
    lo_, hi_ = uv.min(axis=1), uv.max(axis=1)
    apart = np.maximum(lo_[pairs[:, 0]] - hi_[pairs[:, 1]], lo_[pairs[:, 1]] - hi_[pairs[:, 0]]).clip(0)
    return pairs[np.hypot(apart[:, 0], apart[:, 1]) < within]


def island_gaps(tri_uv: np.ndarray, resolution: int, *, within: float = 16.0,
                budget: int | None = None) -> np.ndarray:
    """(T,) per triangle the distance in texels to the nearest triangle of
    another island; inf where none is within ``within`` texels. ``budget``:
    OverBudget (candidate_pairs) rather than more work than that."""
    uv = np.asarray(tri_uv, np.float64) * resolution
    gap = np.full(len(uv), np.inf)
    if len(uv) == 0:
        return gap
    pairs = candidate_pairs(uv, uv_islands(tri_uv), float(within), budget)
    for s in range(0, len(pairs), PAIR_CHUNK):
        i, j = pairs[s:s + PAIR_CHUNK, 0], pairs[s:s + PAIR_CHUNK, 1]
        d = triangle_distances(uv[i], uv[j])
        np.minimum.at(gap, i, d)
        np.minimum.at(gap, j, d)
    return gap


#: Cell entries or candidate pairs a measure for the unwrap may take (~100-200 MB of temporaries).
UNWRAP_BUDGET = 2_000_000


def narrowest_gap(tri_uv: np.ndarray, resolution: int, *, within: float = 16.0,
                  budget: int | None = None) -> float | None:
    """The smallest island gap in texels (inf when no islands are within
    ``within``); None when it would take more than ``budget`` (see candidate_pairs)."""
    try:
        g = island_gaps(tri_uv, resolution, within=within, budget=budget)
    except OverBudget:
        return None
    return float(g.min()) if g.size else float("inf")
