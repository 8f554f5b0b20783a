"""Rasterising a UV layout into texels (the G-buffer's coverage step).

Texel (i, j) of a W x H texture covers u in [i/W, (i+1)/W], v in [j/H, (j+1)/H];
j counts rows from the *bottom* (v up, as UVs and Blender's Image.pixels), its
centre is at pixel coordinates (i + 0.5, j + 0.5) = (u W, v H).

Every texel touched by a triangle gets exactly one sample point:

1. Centre sampling with a fill rule: a texel whose centre lies inside a
   triangle samples there. Edge functions are evaluated so that the two
   triangles sharing an edge get exactly negated values, and a top-left rule
   gives a centre on a shared edge to exactly one of them, so a centre claimed
   twice means the UV layout really overlaps. Overlapping texels are counted and
   reported (the lowest triangle index keeps the texel).
2. Conservative coverage: a texel not claimed in step 1 but overlapped by a
   triangle (separating-axis test of the texel square against the triangle)
   samples at the point of that triangle closest to its centre, choosing the
   closest triangle. Thin islands, sub-texel islands and island borders have no
   holes.

Zero-area UV triangles (|2A| <= ZERO_AREA px^2) are not rasterised; they are
counted so the caller can report them.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..base.errors import Cancelled
from ..base.memory import check_fits

#: Twice the signed area (in texel units) below which a UV triangle is degenerate.
ZERO_AREA = 1e-10
#: Candidate (triangle, texel) pairs processed at once (bounds temporary memory).
CHUNK_PAIRS = 1 << 20


@dataclasses.dataclass
class Raster:
    """Texels of one texture covered by a set of UV triangles.

    texel : (N,) int64 flat index j * W + i (row j from the bottom), sorted.
    tri   : (N,) int64 index into the triangles given to :func:`rasterize`.
    bary  : (N, 3) float64 barycentrics of the sample point (sum to 1).
    coverage : (N,) float32, 1 for centre samples, the fraction of a 4x4
            sub-grid inside the triangle for conservative (border) samples.
    """

    width: int
    height: int
    texel: np.ndarray
    tri: np.ndarray
    bary: np.ndarray
    coverage: np.ndarray
    centre_texels: int
    conservative_texels: int
    overlap_texels: int
    overlap_triangles: np.ndarray     # triangle indices involved in overlaps
    zero_area_triangles: np.ndarray   # triangle indices not rasterised

    @property
    def n(self) -> int:
        return int(self.texel.shape[0])

    def mask(self) -> np.ndarray:
        """(H, W) bool, row 0 = bottom."""
        m = np.zeros(self.width * self.height, bool)
        m[self.texel] = True
        return m.reshape(self.height, self.width)


_EDGES = ((1, 2), (2, 0), (0, 1))     # edge k runs from vertex s to d, opposite vertex k


def _canonical_edges(P):
    """Per triangle and edge: origin, direction and sign of the edge function.

    E_k(p) = sgn * cross(e, p - o) with (o, e) taken from the lexicographically
    smaller endpoint, so two triangles sharing an edge compute bit-identical
    magnitudes with opposite signs (the fill rule then decides exactly).
    """
    out = []
    for s, d in _EDGES:
        a, b = P[:, s], P[:, d]
        swap = (a[:, 0] > b[:, 0]) | ((a[:, 0] == b[:, 0]) & (a[:, 1] > b[:, 1]))
        o = np.where(swap[:, None], b, a)
        e = np.where(swap[:, None], a, b) - o
        sgn = np.where(swap, -1.0, 1.0)
        dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
        top_left = (dy > 0) | ((dy == 0) & (dx < 0))
        out.append((o, e, sgn, top_left))
    return out


def _row_spans(P, tri, j):
    """x-range [lo, hi] of each triangle within the strip v in [j, j + 1]."""
    lo = np.full(tri.shape, np.inf)
    hi = np.full(tri.shape, -np.inf)
    y0s, y1s = j.astype(np.float64), j + 1.0
    for s, d in _EDGES:
        ax, ay = P[tri, s, 0], P[tri, s, 1]
        bx, by = P[tri, d, 0], P[tri, d, 1]
        ylo, yhi = np.minimum(ay, by), np.maximum(ay, by)
        c0, c1 = np.maximum(ylo, y0s), np.minimum(yhi, y1s)
        ok = c0 <= c1
        dy = by - ay
        flat = dy == 0
        slope = np.where(flat, 0.0, (bx - ax) / np.where(flat, 1.0, dy))
        xa = np.where(flat, ax, ax + (c0 - ay) * slope)
        xb = np.where(flat, bx, ax + (c1 - ay) * slope)
        lo = np.where(ok, np.minimum(lo, np.minimum(xa, xb)), lo)
        hi = np.where(ok, np.maximum(hi, np.maximum(xa, xb)), hi)
    return lo, hi


def _prepared(uvs, width: int, height: int):
    """(P, area2, zero, cw): corners in texel units (T, 3, 2) float64, made
    counter-clockwise; twice their areas; the degenerate ones; the ones
    swapped (to map barycentrics back)."""
    uvs = np.asarray(uvs, dtype=np.float64)
    P = uvs * np.array([width, height], dtype=np.float64)
    area2 = ((P[:, 1, 0] - P[:, 0, 0]) * (P[:, 2, 1] - P[:, 0, 1])
             - (P[:, 1, 1] - P[:, 0, 1]) * (P[:, 2, 0] - P[:, 0, 0]))
    zero = np.abs(area2) <= ZERO_AREA
    cw = area2 < 0
    order = np.where(cw[:, None], [0, 2, 1], [0, 1, 2])
    P = np.take_along_axis(P, order[:, :, None], axis=1)
    return P, np.abs(area2), zero, cw


def _claims(P, edges, live, width: int, height: int, y0: int, y1: int, cancel=None, border: bool = True):
    """(centre_parts, border_parts): lists of (flat texel, triangle) arrays of
    the texel centres inside triangles ``live`` (CCW corners ``P`` in texel
    units, ``edges`` from _canonical_edges) in rows y0 <= j < y1, and (with
    ``border``) the texels their squares touch otherwise (separating axes)."""

    # Row items: (triangle, row j) for every texel row the triangle's bbox spans,
    # trimmed to the triangle's own x-extent within that row.
    ylo = np.clip(np.floor(P[live, :, 1].min(axis=1)).astype(np.int64), 0, height - 1)
    yhi = np.clip(np.ceil(P[live, :, 1].max(axis=1)).astype(np.int64) - 1, 0, height - 1)
    yhi = np.maximum(yhi, ylo)
    ylo, yhi = np.maximum(ylo, y0), np.minimum(yhi, y1 - 1)
    nrow = np.maximum(yhi - ylo + 1, 0)
    r_tri = np.repeat(live, nrow)
    r_j = np.repeat(ylo, nrow) + (np.arange(int(nrow.sum())) - np.repeat(np.cumsum(nrow) - nrow, nrow))
    xl, xh = _row_spans(P, r_tri, r_j)
    keep = xl <= xh
    r_tri, r_j = r_tri[keep], r_j[keep]
    r_i0 = np.clip(np.floor(xl[keep]).astype(np.int64), 0, width - 1)
    r_i1 = np.clip(np.ceil(xh[keep]).astype(np.int64) - 1, 0, width - 1)
    r_i1 = np.maximum(r_i1, r_i0)
    r_cnt = r_i1 - r_i0 + 1
    # Within a row each edge function is linear in x: E_k = alpha_k x + beta_k,
    # computed from the canonical edge so shared edges stay exactly negated.
    cy = r_j + 0.5
    alpha, beta = [], []
    for (o, e, sgn, _) in edges:
        ox, oy, ex, ey, sg = o[r_tri, 0], o[r_tri, 1], e[r_tri, 0], e[r_tri, 1], sgn[r_tri]
        alpha.append(-sg * ey)
        beta.append(sg * (ex * (cy - oy) + ey * ox))
    chunk_of = (np.cumsum(r_cnt) - r_cnt) // CHUNK_PAIRS
    cuts = [0, *(np.flatnonzero(np.diff(chunk_of)) + 1).tolist(), int(r_tri.size)]

    centre_parts, border_parts = [], []
    for a, b in zip(cuts[:-1], cuts[1:]):
        if a == b:
            continue
        if cancel is not None and cancel.is_set():
            raise Cancelled()
        cnt = r_cnt[a:b]
        k = np.repeat(np.arange(a, b), cnt)
        i = np.repeat(r_i0[a:b], cnt) + (np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt))
        t = r_tri[k]
        cx = i + 0.5
        E = [alpha[q][k] * cx + beta[q][k] for q in range(3)]
        inside = np.ones(t.shape, bool)
        for q in range(3):
            inside &= (E[q] > 0) | ((E[q] == 0) & edges[q][3][t])
        flat = r_j[k] * width + i
        centre_parts.append((flat[inside], t[inside]))
        out = ~inside
        if border and out.any():
            # Separating-axis test of the texel square against each edge.
            tt = t[out]
            ok = np.ones(tt.shape, bool)
            for q in range(3):
                e = edges[q][1]
                ok &= E[q][out] + 0.5 * (np.abs(e[tt, 0]) + np.abs(e[tt, 1])) > 0
            border_parts.append((flat[out][ok], tt[ok]))

    return centre_parts, border_parts


def rasterize(uvs: np.ndarray, width: int, height: int, rows: tuple[int, int] | None = None,
              cancel=None) -> Raster:
    """Rasterise UV triangles (T, 3, 2) in [0, 1] onto a width x height texture.

    ``rows`` = (y0, y1) restricts the work to texel rows y0 <= j < y1 (bands
    can run on different threads; texel indices stay global). ``cancel`` (an
    object with is_set(), e.g. a threading.Event) is checked between chunks:
    parallel.Cancelled.
    """
    y0, y1 = (0, height) if rows is None else (int(rows[0]), int(rows[1]))
    P, area2, zero, cw = _prepared(uvs, width, height)
    edges = _canonical_edges(P)
    centre_parts, border_parts = _claims(P, edges, np.flatnonzero(~zero), width, height, y0, y1, cancel)

    # Dense arrays cover the band only; flat indices are offset by its first texel.
    base = y0 * width
    n_tex = (y1 - y0) * width
    c_flat = np.concatenate([p[0] for p in centre_parts]) - base if centre_parts else np.zeros(0, np.int64)
    c_tri = np.concatenate([p[1] for p in centre_parts]) if centre_parts else np.zeros(0, np.int64)
    # Dense owner array: texels come out sorted without sorting the claims.
    count = np.bincount(c_flat, minlength=n_tex)
    owner = np.full(n_tex, -1, np.int64)
    dup = count[c_flat] > 1
    owner[c_flat[~dup]] = c_tri[~dup]
    overlap_texels = int(np.count_nonzero(count > 1))
    overlap_tris = np.zeros(0, np.int64)
    if dup.any():
        # A centre claimed twice: the UV layout overlaps. Lowest triangle keeps it.
        d_flat, d_tri = c_flat[dup], c_tri[dup]
        o = np.lexsort((d_tri, d_flat))
        d_flat, d_tri = d_flat[o], d_tri[o]
        first = np.ones(d_flat.shape, bool)
        first[1:] = d_flat[1:] != d_flat[:-1]
        owner[d_flat[first]] = d_tri[first]
        overlap_tris = np.unique(d_tri)
    centre = owner >= 0

    # Conservative texels: not centre-claimed, closest overlapping triangle wins.
    b_flat = np.concatenate([p[0] for p in border_parts]) - base if border_parts else np.zeros(0, np.int64)
    b_tri = np.concatenate([p[1] for p in border_parts]) if border_parts else np.zeros(0, np.int64)
    keep = ~centre[b_flat]
    b_flat, b_tri = b_flat[keep], b_tri[keep]
    b_bary = np.zeros((0, 3))
    if b_flat.size:
        cx = (b_flat % width) + 0.5
        cy = (b_flat // width) + y0 + 0.5
        dist, bary_all = _closest_point(P[b_tri], cx, cy)
        o = np.lexsort((b_tri, dist, b_flat))
        b_flat, b_tri, bary_all = b_flat[o], b_tri[o], bary_all[o]
        firstb = np.ones(b_flat.shape, bool)
        firstb[1:] = b_flat[1:] != b_flat[:-1]
        b_flat, b_tri, b_bary = b_flat[firstb], b_tri[firstb], bary_all[firstb]
        owner[b_flat] = b_tri

    local = np.flatnonzero(owner >= 0)
    tri = owner[local]
    is_centre = centre[local]
    texel = local + base
    b_flat = b_flat + base
    # Barycentrics of the texel centres in the CCW corner order (1D gathers keep
    # memory small at 4096^2); border texels are overwritten below.
    px, py = (texel % width) + 0.5, (texel // width) + 0.5
    x0, y0 = P[tri, 0, 0], P[tri, 0, 1]
    x1, y1 = P[tri, 1, 0], P[tri, 1, 1]
    x2, y2 = P[tri, 2, 0], P[tri, 2, 1]
    inv_a = 1.0 / area2[tri]
    bary = np.empty((texel.size, 3))
    bary[:, 0] = ((x2 - x1) * (py - y1) - (y2 - y1) * (px - x1)) * inv_a
    bary[:, 1] = ((x0 - x2) * (py - y2) - (y0 - y2) * (px - x2)) * inv_a
    bary[:, 2] = 1.0 - bary[:, 0] - bary[:, 1]
    del x0, y0, x1, y1, x2, y2, px, py, inv_a
    cov = np.ones(texel.size, np.float32)
    if b_flat.size:
        pos = np.searchsorted(texel, b_flat)
        bary[pos] = b_bary
        cov[pos] = _subsample_coverage(P[b_tri], b_flat, width)
    # Undo the counter-clockwise reordering: barycentrics follow the input corners.
    swapped = cw[tri]
    bary[swapped] = bary[swapped][:, [0, 2, 1]]
    return Raster(width, height, texel, tri, bary, cov, int(np.count_nonzero(is_centre)), int(b_flat.size),
                  overlap_texels, overlap_tris, np.flatnonzero(zero))


#: Texels of one band of :func:`overlap_count`, and the texel claims
#: (bounding-box texels) of one group of its triangles: its memory, whatever
#: the resolution (a whole 16384² raster holds ~40 GiB) and however many
#: triangles cover a texel (UV maps stacked on one square claim each texel once
#: per triangle).
OVERLAP_BAND_TEXELS = 1 << 20
OVERLAP_GROUP_CLAIMS = 1 << 21
#: Bytes per band texel and per group claim the check holds at most: its
#: dense count, and the claim loop's arrays (row items, indices, edge values).
OVERLAP_BYTES = (8, 120)


def overlap_count(uvs: np.ndarray, width: int, height: int, cancel=None) -> int:
    """``rasterize(uvs, width, height).overlap_texels``, the texel centres
    claimed by more than one triangle, with bounded memory: a band of rows at
    a time and, within a band, a group of triangles at a time (claims counted
    into the band's dense counts), checked before the first band."""
    width, height = int(width), int(height)
    rows = max(1, OVERLAP_BAND_TEXELS // max(width, 1))
    check_fits(OVERLAP_BYTES[0] * rows * width + OVERLAP_BYTES[1] * OVERLAP_GROUP_CLAIMS,
               f"the UV overlap check at {width}x{height}")
    P, _, zero, _ = _prepared(uvs, width, height)
    live = np.flatnonzero(~zero)
    edges = _canonical_edges(P)
    lo, hi = P[live].min(axis=1), P[live].max(axis=1)          # (n, 2) bounding boxes, texel units
    ylo = np.clip(np.floor(lo[:, 1]).astype(np.int64), 0, height - 1)
    yhi = np.maximum(np.clip(np.ceil(hi[:, 1]).astype(np.int64) - 1, 0, height - 1), ylo)
    span = np.clip(np.ceil(hi[:, 0]) - np.floor(lo[:, 0]) + 1, 1, width).astype(np.int64)
    total = 0
    for y0 in range(0, height, rows):
        y1 = min(y0 + rows, height)
        inb = (yhi >= y0) & (ylo < y1)
        tri = live[inb]
        claims = span[inb] * (np.minimum(yhi[inb], y1 - 1) - np.maximum(ylo[inb], y0) + 1)
        group = np.cumsum(claims) // OVERLAP_GROUP_CLAIMS
        cuts = [0, *(np.flatnonzero(np.diff(group)) + 1).tolist(), tri.size]
        count = np.zeros((y1 - y0) * width, np.int64)
        for a, b in zip(cuts[:-1], cuts[1:]):
            if a == b:
                continue
            centre, _ = _claims(P, edges, tri[a:b], width, height, y0, y1, cancel, border=False)
            for flat, _t in centre:
                count += np.bincount(flat - y0 * width, minlength=count.size)
        total += int(np.count_nonzero(count > 1))
    return total


def _closest_point(V, px, py):
    """Distance from points to triangles V (n, 3, 2) outside them, and the
    barycentrics of the closest point (on the nearest edge)."""
    best = np.full(px.shape, np.inf)
    bary = np.zeros((px.shape[0], 3))
    for s, d in ((0, 1), (1, 2), (2, 0)):
        ax, ay = V[:, s, 0], V[:, s, 1]
        ex, ey = V[:, d, 0] - ax, V[:, d, 1] - ay
        ll = ex * ex + ey * ey
        t = np.clip(((px - ax) * ex + (py - ay) * ey) / np.where(ll > 0, ll, 1.0), 0.0, 1.0)
        qx, qy = ax + t * ex, ay + t * ey
        dist = np.hypot(px - qx, py - qy)
        better = dist < best
        best = np.where(better, dist, best)
        bary[better] = 0.0
        bary[better, s] = 1.0 - t[better]
        bary[better, d] = t[better]
    return best, bary


def _subsample_coverage(V, flat, width):
    """Fraction of a 4x4 sub-grid of each texel inside its triangle (>= 1/32)."""
    ox = (flat % width).astype(np.float64)
    oy = (flat // width).astype(np.float64)
    offs = (np.arange(4) + 0.5) / 4.0
    inside = np.zeros(flat.shape, np.float32)
    for sx in offs:
        for sy in offs:
            px, py = ox + sx, oy + sy
            ok = np.ones(flat.shape, bool)
            for s, d in _EDGES:
                ex, ey = V[:, d, 0] - V[:, s, 0], V[:, d, 1] - V[:, s, 1]
                ok &= ex * (py - V[:, s, 1]) - ey * (px - V[:, s, 0]) >= 0
            inside += ok
    return np.maximum(inside / 16.0, 1.0 / 32.0).astype(np.float32)
