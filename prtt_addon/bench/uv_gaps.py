"""How far apart a UV map's islands are, in texels: the padding that
bilinear lookups and dilation need (issue 53, "padding that holds").

An island is a set of triangles connected through shared UV corners (the
same UV coordinate on a shared edge's vertex, as Blender's UV editor joins
them). The gap between two islands is the smallest Euclidean distance
between any point of one and any point of the other, measured in texels of
a ``resolution``² texture. Exact for triangles (edge-to-edge distances; an
overlap is a gap of 0), computed for candidate pairs whose bounding boxes
come within ``search`` texels, so it costs O(T · neighbours), for the test
scenes' few thousand triangles.
"""
from __future__ import annotations

import numpy as np


def uv_islands(tri_uv: np.ndarray) -> np.ndarray:
    """(T,) int island label per triangle: triangles sharing a corner UV
    (equal to 1e-7 of the UV square) are one island. tri_uv (T, 3, 2)."""
    t = tri_uv.shape[0]
    keys = np.round(tri_uv.reshape(-1, 2) * 1e7).astype(np.int64)
    _, corner = np.unique(keys, axis=0, return_inverse=True)
    corner = corner.reshape(t, 3)
    parent = np.arange(corner.max() + 1)

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for c0, c1, c2 in corner:
        r0 = find(c0)
        for c in (c1, c2):
            r = find(c)
            if r != r0:
                parent[r] = r0
    roots = np.array([find(c) for c in corner[:, 0]])
    return np.unique(roots, return_inverse=True)[1]


def _point_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from points p (..., 2) to segments a-b (..., 2)."""
    ab = b - a
    t = np.clip(np.einsum("...i,...i", p - a, ab) / np.maximum(np.einsum("...i,...i", ab, ab), 1e-300), 0, 1)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def _cross(o, a, b):
    return (a[..., 0] - o[..., 0]) * (b[..., 1] - o[..., 1]) - (a[..., 1] - o[..., 1]) * (b[..., 0] - o[..., 0])


def triangle_distances(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(P,) distances between triangle pairs A[i], B[i] (P, 3, 2); 0 where they touch or overlap."""
    best = np.full(A.shape[0], np.inf)
    for i in range(3):
        a0, a1 = A[:, i], A[:, (i + 1) % 3]
        for j in range(3):
            b0, b1 = B[:, j], B[:, (j + 1) % 3]
            d = np.minimum(np.minimum(_point_segment(a0, b0, b1), _point_segment(a1, b0, b1)),
                           np.minimum(_point_segment(b0, a0, a1), _point_segment(b1, a0, a1)))
            d1, d2 = _cross(a0, a1, b0), _cross(a0, a1, b1)
            d3, d4 = _cross(b0, b1, a0), _cross(b0, b1, a1)
            d = np.where((d1 * d2 < 0) & (d3 * d4 < 0), 0.0, d)       # the edges cross
            best = np.minimum(best, d)

    def inside(p, T):
        s = [_cross(T[:, k], T[:, (k + 1) % 3], p) for k in range(3)]
        return ((s[0] >= 0) & (s[1] >= 0) & (s[2] >= 0)) | ((s[0] <= 0) & (s[1] <= 0) & (s[2] <= 0))
    contained = inside(A[:, 0], B) | inside(B[:, 0], A)
    return np.where(contained, 0.0, best)


def island_gaps(tri_uv: np.ndarray, resolution: int, *, search: float = 16.0) -> np.ndarray:
    """(T,) per triangle the distance in texels to the nearest triangle of
    another island (inf when none is within ``search`` texels)."""
    from scipy.spatial import cKDTree  # test and bench dependency (requirements.txt)

    uv = np.asarray(tri_uv, np.float64) * resolution
    label = uv_islands(tri_uv)
    centre = uv.mean(axis=1)
    radius = np.linalg.norm(uv - centre[:, None], axis=2).max(axis=1)
    tree = cKDTree(centre)
    reach = 2 * radius.max() + search
    pairs = tree.query_pairs(reach, output_type="ndarray")
    gap = np.full(len(uv), np.inf)
    if len(pairs) == 0:
        return gap
    i, j = pairs[:, 0], pairs[:, 1]
    keep = (label[i] != label[j]) & (np.linalg.norm(centre[i] - centre[j], axis=1) <= radius[i] + radius[j] + search)
    i, j = i[keep], j[keep]
    for s in range(0, len(i), 200_000):
        d = triangle_distances(uv[i[s:s + 200_000]], uv[j[s:s + 200_000]])
        np.minimum.at(gap, i[s:s + 200_000], d)
        np.minimum.at(gap, j[s:s + 200_000], d)
    return gap
