"""Rays guided toward the openings a point sees the sky through (issue 53, item 1).

Why: inside a room lit through a window, nearly all of a texel's cosine-
distributed rays end on the walls. Its transfer is the few that leave
through the window, and at 256 rays how many do is a matter of chance: the
walls come out blotchy (bench window-room: 32 % mean error over the lit
texels). Rays aimed at the opening see it every time. This is path guiding
(Vorba et al. 2014, Mueller et al. 2017) in its simplest form, one level
deep and learned before the bake:

1. Pilot: one traced point in :data:`PILOT_EVERY` sends :data:`PILOT_RAYS`
   cosine-distributed rays about its shading normal. The directions that
   escape are counted per cell (a voxel of the scene holding about
   :data:`CELL_POINTS` points, split by the normal's nearest axis) in an
   equal-area histogram of world directions (:data:`BINS_Z` bands of z times
   :data:`BINS_PHI` of azimuth, each 4 pi / 512 sr), pooled with the
   neighbouring cells (:data:`POOL`) and widened by one bin each way so that
   an opening a few pilot rays found is covered whole.
2. Selection: the points of a cell whose pilot rays escaped at a rate in
   (0, :data:`OPEN_MAX`] are guided. The rest keep the transfer's estimator,
   which is exact where nothing or everything is blocked.
3. Estimate: of a guided point's N rays, n_c = N (1 - :data:`GUIDED_SHARE`)
   are cosine-distributed and n_g are drawn from its cell's histogram; they
   are combined by the balance heuristic (Veach's multi-sample MIS):

       T_k = sum_i V_i max(0, n.w_i) y_k(w_i) / (n_c p_c(w_i) + n_g p_g(w_i)),

   p_c = max(0, n.w) / pi, p_g the histogram's density per steradian. It is
   unbiased whatever the histogram holds, and each ray adds at most
   pi |y_k| / n_c (the cosine rays keep every direction covered).

Rays below the geometric horizon (smooth or normal-mapped shading) count as
blocked and are not traced, as in the transfer bake.

Determinism: every random number is a hash of (seed, point id, ray) or an
Owen-scrambled Sobol' point with a per-point shift; the pilot's counts are
integers (their sums do not depend on order); guided points are split into
chunks by their order alone and every chunk writes its own rows. Results are
the same for any thread count.

Memory: at most :data:`MAX_CELLS` cells (the cell size grows until the scene
fits), so the histograms and their tables stay under ~42 MB whatever the
resolution, beside 4 B a point for its cell (:func:`guide_bytes`).
"""
from __future__ import annotations

import dataclasses
import functools
import math
import threading

import numpy as np

from ...base.errors import Cancelled
from ...base.threads import run_chunks
from ...sh.basis import basis_unchecked
from .raytrace import SAME_NORMAL, RayScene
from .sampling import hash_u32, hash_unit, sobol2, tangent_frames, to_hemisphere

#: Pilot rays a point (cosine-distributed).
PILOT_RAYS = 16
#: One point in this many sends pilot rays (1.6 % of the default 256 rays a texel on average;
#: the window room's error 6.7 % with every point, 6.95 % with one in four, at a quarter of the cost).
PILOT_EVERY = 4
#: Direction bins: z in BINS_Z equal steps of [-1, 1], azimuth in BINS_PHI (equal areas).
BINS_Z, BINS_PHI = 16, 32
BINS = BINS_Z * BINS_PHI
#: Points a cell holds on average (the cell's edge follows from the surface area a point covers).
CELL_POINTS = 64
#: Cells at most: the edge doubles until the scene fits (bounds the tables' memory).
MAX_CELLS = 2048
#: Cells whose pilot rays escape more often than this keep the transfer's estimator: their cosine
#: rays find the openings often enough (the demo room: 0.5 guided 74 % of its texels at 3.1x the
#: bake time, 0.1 guides 6 %; the window room's inner cells are all below 0.1).
OPEN_MAX = 0.1
#: Guided-ray patterns a cell has (a point takes one by a hash of its id).
PATTERNS = 16
#: Share of a guided point's rays drawn from its cell's histogram (the rest cosine-distributed;
#: the window room 6.7 % at 3/4, 6.05 % at 7/8, 7.9 % at 1/2, the same time).
GUIDED_SHARE = 0.875

#: Pilot parts a thread at least (a set's pilot points fit one chunk of rays: 22K at 512²).
PILOT_PARTS = 4

#: Cells pool their pilot counts with their neighbours this many voxels each
#: way (same normal side): more escapes to learn from where openings are
#: seen in few pilot rays.
POOL = 1
_SALT_PILOT, _SALT_COS, _SALT_GUIDE = 0x9170, 0xC057, 0x6E1D


#: Bytes of SH coefficients a guided chunk projects at a time (whole points; a
#: point with more visible rays than that is summed in pieces).
PROJECT_BYTES = 4 << 20
#: Bytes a traced point costs while the cells are found (its row, voxel key,
#: np.unique's sort and inverse, the int32 cell ids), before the transfer's rows exist.
BUILD_POINT_BYTES = 64

#: Bytes a cell's bins take at most while the guide is built: the pilot's
#: counts (int32) and a chunk's count of them (int64), the pooled counts and
#: a copy of them, the CDFs and the density.
CELL_BIN_BYTES = 32
#: Cells whose tables are made at a time, and the bytes of their temporaries.
TABLE_BLOCK = 256
TABLE_BLOCK_BYTES = TABLE_BLOCK * BINS * 64


def guide_build_bytes(points: int) -> int:
    """Upper bound of what building the guide holds (bytes) for ``points``
    traced points, before the transfer's rows exist: the cells' search and
    the tables (:func:`guide_bytes`)."""
    return BUILD_POINT_BYTES * points + guide_bytes(points)


def guide_bytes(points: int) -> int:
    """Upper bound of the guide's memory (bytes) for ``points`` traced points:
    the tables of min(MAX_CELLS, points) cells and 12 B a point (its cell
    id and the guided order); the cell ids' own temporaries (~32 B a point)
    are freed before the transfer's rows exist."""
    return min(MAX_CELLS, max(points, 1)) * BINS * CELL_BIN_BYTES + TABLE_BLOCK_BYTES + 12 * points


@dataclasses.dataclass
class Guide:
    """Which points are guided and the histograms they sample.

    cell : (N,) int32 the point's cell, -1 where the point is not guided.
    row_cdf : (C, BINS_Z) float32 cumulative distribution of each cell's z bands (last = 1).
    col_cdf : (C, BINS_Z, BINS_PHI) float32 cumulative distribution of the
        azimuth bins within each band (last = 1).
    density : (C, BINS) float32 p_g per steradian of each cell's bins.
    escape_rate : (C,) float64 share of each cell's pilot rays that escaped.
    pilot_rays : rays the pilot traced.
    """

    cell: np.ndarray
    row_cdf: np.ndarray
    col_cdf: np.ndarray
    density: np.ndarray
    escape_rate: np.ndarray
    pilot_rays: int

    @property
    def points(self) -> np.ndarray:
        """(M,) indices of the guided points, ordered by cell then index."""
        sel = np.flatnonzero(self.cell >= 0)
        return sel[np.argsort(self.cell[sel], kind="stable")]


def direction_bins(d: np.ndarray) -> np.ndarray:
    """(n,) int64 equal-area bin of world unit directions (n, 3) (float32 or float64)."""
    iz = np.clip(((d[:, 2] + 1.0) * (0.5 * BINS_Z)).astype(np.int64), 0, BINS_Z - 1)
    phi = np.arctan2(d[:, 1], d[:, 0])                               # [-pi, pi]
    ip = ((phi + math.pi) * (BINS_PHI / (2.0 * math.pi))).astype(np.int64) % BINS_PHI
    return iz * BINS_PHI + ip


def cosine_directions(normal: np.ndarray, ids: np.ndarray, rays: int, seed: int, salt: int) -> np.ndarray:
    """(m, rays, 3) float32 cosine-distributed directions about each unit
    normal: one Owen-scrambled Sobol' pattern turned about each normal by an
    angle hashed from the point's id, so neighbours' noise is independent."""
    t, bt = tangent_frames(normal)
    gam = 2.0 * math.pi * hash_unit(seed, ids, salt)
    c, s = np.cos(gam)[:, None], np.sin(gam)[:, None]
    basis = np.stack([c * t + s * bt, c * bt - s * t, normal], axis=1).astype(np.float32)   # (m, 3, 3) rows
    local = to_hemisphere(sobol2(rays, int(hash_u32(seed, salt))), "cosine")[0].astype(np.float32)
    return np.matmul(local[None], basis)


def cell_ids(position: np.ndarray, normal: np.ndarray, rows: np.ndarray, area: float) -> tuple:
    """(len(rows),) int32 compact cell id of the points ``rows``, and the
    cells' sorted keys: voxels whose edge makes a cell hold about CELL_POINTS
    points of a surface of ``area`` covered by all the points (doubled until
    there are at most MAX_CELLS cells), split by the normal's nearest axis (+-x, +-y, +-z): the two faces
    of a wall share a voxel but not what they see. Read in blocks: no copy of
    the positions."""
    if rows.size == 0:
        return np.zeros(0, np.int32), np.zeros(0, np.int64)
    block = 1 << 20
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for a in range(0, rows.size, block):
        p = position[rows[a:a + block]]
        lo, hi = np.minimum(lo, p.min(axis=0)), np.maximum(hi, p.max(axis=0))
    span = float(np.max(hi - lo))
    edge = math.sqrt(CELL_POINTS * max(area, 0.0) / position.shape[0])
    edge = max(edge, span / 2 ** 18, 1e-30)             # voxel coordinates fit 19 bits each
    key = np.empty(rows.size, np.int64)
    while True:
        for a in range(0, rows.size, block):
            r = rows[a:a + block]
            v = np.floor((position[r] - lo) / edge).astype(np.int64)
            n = normal[r]
            ax = np.argmax(np.abs(n), axis=1)
            side = 2 * ax + (n[np.arange(r.size), ax] < 0)
            key[a:a + block] = (v[:, 0] << 41) | (v[:, 1] << 22) | (v[:, 2] << 3) | side
        uniq, inv = np.unique(key, return_inverse=True)
        if uniq.size <= MAX_CELLS:
            return inv.astype(np.int32).ravel(), uniq
        edge *= 2.0


def neighbour_sums(keys: np.ndarray, values: np.ndarray, radius: int) -> np.ndarray:
    """Sum over each cell's voxel neighbourhood ((2 radius + 1)³ voxels, the
    same normal side) of ``values`` (C, ...) of the cells with sorted ``keys``
    (cell_ids' encoding)."""
    mask = (1 << 19) - 1
    x, y, z, side = keys >> 41, (keys >> 22) & mask, (keys >> 3) & mask, keys & 7
    out = np.zeros_like(values)
    r = range(-radius, radius + 1)
    for dx in r:
        for dy in r:
            for dz in r:
                nx, ny, nz = x + dx, y + dy, z + dz
                ok = (nx >= 0) & (ny >= 0) & (nz >= 0) & (nx <= mask) & (ny <= mask) & (nz <= mask)
                nk = (nx << 41) | (ny << 22) | (nz << 3) | side
                pos = np.minimum(np.searchsorted(keys, nk), keys.size - 1)
                hit = ok & (keys[pos] == nk)
                out[hit] += values[pos[hit]]
    return out


def _escaped(rs: RayScene, org: np.ndarray, d: np.ndarray, trace: np.ndarray) -> np.ndarray:
    """(m, r) bool: which rays (origins (m, 3) float32, directions (m, r, 3)
    float32) escape; rays not ``trace``d count as blocked and go to Embree
    with an empty interval (tfar < tnear = 0), which it rejects without
    traversal (no packing of the traced ones: one broadcast copy)."""
    m, r = trace.shape
    o = np.empty((m, r, 3), np.float32)
    o[...] = org[:, None, :]
    tfar = np.where(trace, np.float32(np.inf), np.float32(-1.0)).ravel()
    occ = rs.occluded(o.reshape(-1, 3), np.ascontiguousarray(d, np.float32).reshape(-1, 3), tfar=tfar)
    return ~occ.reshape(m, r) & trace


def build_guide(rs: RayScene, position, normal, geo_normal, ids, traced: np.ndarray, area: float,
                seed: int, threads: int, chunk_rays: int, cancel=None) -> Guide:
    """The pilot pass and the guide it gives (module docstring, steps 1 and 2).

    position, normal, geo_normal : (N, 3) float64 world points, unit shading
    and geometric normals; ids (N,) int64 stable ids; traced (N,) bool the
    points the transfer traces (others take no part); area: the scene's
    surface area (world units²).
    """
    N = position.shape[0]
    tr = np.flatnonzero(traced)
    cell = np.full(N, -1, np.int32)
    cell[tr], keys = cell_ids(position, normal, tr, area)
    C = int(cell[tr].max()) + 1 if tr.size else 0
    # One point in PILOT_EVERY (by a hash of its id) sends the pilot rays: a cell learns from its
    # share of them, and every point of a cell is guided or not by what the cell learned.
    sent_by = tr if PILOT_EVERY == 1 else tr[hash_u32(seed, ids[tr], _SALT_PILOT) % np.uint32(PILOT_EVERY) == 0]
    # At least PILOT_PARTS parts a thread, so both cores send them (the counts are integers:
    # their sums do not depend on the parts).
    per = max(1, min(chunk_rays // PILOT_RAYS, -(-sent_by.size // (PILOT_PARTS * max(1, threads)))))
    parts = [sent_by[a:a + per] for a in range(0, sent_by.size, per)]

    def pilot(idx):
        if cancel is not None and cancel.is_set():
            raise Cancelled()
        n, g = normal[idx], geo_normal[idx]
        d = cosine_directions(n, ids[idx], PILOT_RAYS, seed, _SALT_PILOT)
        above = np.einsum("mrc,mc->mr", d, g) > 0.0
        esc = _escaped(rs, rs.origins(position[idx], g), d, above)
        i, j = np.nonzero(esc)
        return cell[idx][i].astype(np.int64) * BINS + direction_bins(d[i, j]), np.bincount(cell[idx], minlength=C)

    seen = np.zeros(C * BINS, np.int32)       # escapes a (cell, bin)
    sent = np.zeros(C, np.int64)              # pilot points a cell

    def add(res):
        # Counted here, one chunk at a time: a chunk returns its escapes, not a table.
        seen[:] += np.bincount(res[0], minlength=C * BINS)
        sent[:] += res[1]

    run_chunks(pilot, parts, threads, add, cancel)
    counts, points = seen, sent
    if POOL:
        counts = neighbour_sums(keys, counts.reshape(C, BINS), POOL)
        points = neighbour_sums(keys, points, POOL)
    counts = counts.reshape(C, BINS_Z, BINS_PHI)
    rate = counts.sum(axis=(1, 2)) / np.maximum(points * PILOT_RAYS, 1)
    row_cdf = np.empty((C, BINS_Z), np.float32)
    col_cdf = np.empty((C, BINS_Z, BINS_PHI), np.float32)
    density = np.empty((C, BINS), np.float32)
    for a in range(0, C, TABLE_BLOCK):
        b = min(a + TABLE_BLOCK, C)
        row_cdf[a:b], col_cdf[a:b], density[a:b] = _tables(counts[a:b])
    guided_cell = (rate > 0.0) & (rate <= OPEN_MAX)
    sel = cell >= 0
    sel[sel] = guided_cell[cell[sel]]
    return Guide(np.where(sel, cell, -1).astype(np.int32), row_cdf, col_cdf, density, rate,
                 int(sent_by.size) * PILOT_RAYS)


def _tables(counts: np.ndarray):
    """Sampling tables of cells' escape counts (c, BINS_Z, BINS_PHI): the
    counts widened by one bin each way (azimuth wraps, z does not: an
    opening the pilot saw in a few rays is covered to its edges), as (row
    CDF (c, BINS_Z), CDF of the azimuth in each row (c, BINS_Z, BINS_PHI),
    density per steradian (c, BINS)), float32."""
    c = counts.shape[0]
    pad = np.pad(counts.astype(np.float32), ((0, 0), (1, 1), (0, 0)))
    rows = pad[:, :-2] + pad[:, 1:-1] + pad[:, 2:]
    wide = rows + np.roll(rows, 1, axis=2)
    wide += np.roll(rows, -1, axis=2)
    total = wide.sum(axis=(1, 2), dtype=np.float64)[:, None, None]
    p = np.divide(wide, total, out=np.zeros_like(wide), where=total > 0)
    mass = p.sum(axis=2, dtype=np.float64)
    row_cdf = np.cumsum(mass, axis=1).astype(np.float32)
    row_cdf[:, -1] = 1.0
    col = np.cumsum(p, axis=2, dtype=np.float64)
    col = np.divide(col, mass[:, :, None], out=np.zeros_like(col), where=mass[:, :, None] > 0).astype(np.float32)
    col[:, :, -1] = 1.0
    return row_cdf, col, p.reshape(c, BINS) * np.float32(BINS / (4.0 * math.pi))


@functools.lru_cache(maxsize=8)
def _sobol_u32(rays: int, seed: int) -> np.ndarray:
    """(rays, 2) uint32: sobol2(rays, seed) times 2^32 (its points are
    multiples of 2^-32), read-only; one per (rays, seed), made once."""
    u = (sobol2(rays, seed) * 4294967296.0).astype(np.uint32)
    u.flags.writeable = False
    return u


def _invert(cdf: np.ndarray, group: np.ndarray, u: np.ndarray):
    """Continuous inversion of piecewise-constant distributions: ``cdf`` (G, B)
    (last column 1), ``group`` (n,) which row each sample uses, ``u`` (n,) in
    [0, 1), float, or uint32 numerators of u * 2^32 (the same samples).
    Returns (bin (n,) int64, position in the bin (n,) in [0, 1)).

    A branchless binary search of every sample in its own row at once (B a
    power of 2: log2 B gathers and compares), in integers (the CDF in 2^-32
    steps, rounded, against the sample's numerator): exact, so a sample's
    bin does not depend on which rows share the search (a chunk's cells), as
    a float sum row + cdf would through its rounding; the bin is
    min(#{cdf <= u}, B - 1), what one search over the rows laid end to end
    gave, at a fifth of its time."""
    G, B = cdf.shape
    if B & (B - 1):
        raise ValueError(f"the rows' width must be a power of 2, got {B}")
    c = cdf.astype(np.float64).ravel()
    ci = np.round(c * 2.0 ** 32).astype(np.int64)
    if u.dtype == np.uint32:
        key = u.astype(np.int64)
        u = key * 2.0 ** -32                   # exact: at most 32 significant bits
    else:
        key = (u * 2.0 ** 32).astype(np.int64)  # u >= 0: truncation is the floor
    base = group.astype(np.int64) * B
    b = np.zeros(key.size, np.int64)
    step = B // 2
    while step:
        # b + step - 1 < B: the probe stays in the row; the steps sum to B - 1.
        b += step * (ci[base + b + (step - 1)] <= key)
        step //= 2
    pos = base + b
    lower = c[np.maximum(pos - 1, 0)]
    lower[b == 0] = 0.0
    width = c[pos] - lower
    frac = u - lower
    np.divide(frac, width, out=frac, where=width > 0)
    frac[~(width > 0)] = 0.0
    return b, np.clip(frac, 0.0, np.nextafter(1.0, 0.0), out=frac)


def guide_directions(guide: Guide, cell: np.ndarray, ids: np.ndarray, rays: int, seed: int, out=None):
    """(m, rays, 3) float32 directions drawn from the points' cells'
    histograms (written into ``out`` (m, rays, 3) float32 when given, and
    returned), and their bins (m, rays) int32.

    A cell has :data:`PATTERNS` patterns; a point takes the one its id
    hashes to (neighbours' noise stays independent but for one in PATTERNS).
    A pattern is an Owen-scrambled Sobol' set shifted per (cell, pattern)
    (Cranley-Patterson), its first coordinate choosing the z band (and the
    place in it), its second the azimuth bin in that band (and the place in
    it): stratified in both. Only the (cell, pattern) pairs the points use are
    drawn (a chunk's points share few cells: far fewer than its rays)."""
    pat = (hash_u32(seed, ids, _SALT_GUIDE) % np.uint32(PATTERNS)).astype(np.int64)
    pairs, which = np.unique(cell * PATTERNS + pat, return_inverse=True)
    which = which.ravel()
    pc, pp = pairs // PATTERNS, pairs % PATTERNS
    cells, local = np.unique(pc, return_inverse=True)
    local = local.ravel()
    u = _sobol_u32(rays, int(hash_u32(seed, _SALT_GUIDE)))
    shift = np.stack([hash_u32(seed, pc, pp, _SALT_GUIDE, 1), hash_u32(seed, pc, pp, _SALT_GUIDE, 2)], axis=-1)
    # (u + shift) mod 1 for both in [0, 1), both multiples of 2^-32: the sum of
    # their 32-bit numerators wraps exactly where the float sum less 1 would.
    w = (u[None, :, :] + shift[:, None, :]).reshape(-1, 2)
    grp = local.repeat(rays)
    iz, fz = _invert(guide.row_cdf[cells], grp, w[:, 0])
    ip, fp = _invert(guide.col_cdf[cells].reshape(-1, BINS_PHI), grp * BINS_Z + iz, w[:, 1])
    z = -1.0 + (iz + fz) * (2.0 / BINS_Z)
    phi = -math.pi + (ip + fp) * (2.0 * math.pi / BINS_PHI)
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    # Each product rounded once to float32, as a float64 array's astype would.
    d = np.empty((z.size, 3), np.float32)
    np.multiply(r, np.cos(phi), out=d[:, 0], casting="same_kind")
    np.multiply(r, np.sin(phi), out=d[:, 1], casting="same_kind")
    d[:, 2] = z
    b = (iz * BINS_PHI + ip).astype(np.int32)
    d = d.reshape(pairs.size, rays, 3)
    if out is None:
        out = d[which]
    else:
        np.take(d, which, axis=0, out=out, mode="clip")     # which < pairs.size: clip is the identity
    return out, b.reshape(pairs.size, rays)[which]


def guided_transfer(rs: RayScene, position, normal, geo_normal, ids, idx: np.ndarray, guide: Guide,
                    rays: int, bands: int, seed: int):
    """World transfer (m, K) float32 of the points ``idx`` (all guided) by the
    mixture of module docstring step 3, and the rays traced. Sums in float32
    (the transfer's type; a texel sums at most ``rays`` terms, each bounded)."""
    K = bands * bands
    m = idx.size
    n_c = max(1, int(round(rays * (1.0 - GUIDED_SHARE))))
    n_g = rays - n_c
    n, g = normal[idx], geo_normal[idx]
    pid = ids[idx]
    cell = guide.cell[idx].astype(np.int64)
    d = np.empty((m, rays, 3), np.float32)
    d[:, :n_c] = cosine_directions(n, pid, n_c, seed, _SALT_COS)
    bins_g = None
    if n_g:
        _, bins_g = guide_directions(guide, cell, pid, n_g, seed, out=d[:, n_c:])
    n32, g32 = n.astype(np.float32), g.astype(np.float32)
    cos_n = np.matmul(d, n32[:, :, None])[..., 0]
    trace = cos_n > 0.0
    horizon = np.einsum("mc,mc->m", n, g) < 1.0 - SAME_NORMAL
    if horizon.any():
        trace &= (np.matmul(d, g32[:, :, None])[..., 0] > 0.0) | ~horizon[:, None]
    traced = int(np.count_nonzero(trace))
    vis = _escaped(rs, rs.origins(position[idx], g), d, trace)
    del trace
    i, j = np.nonzero(vis)
    del vis
    out = np.zeros((m, K), np.float32)
    if i.size == 0:
        return out, traced
    dv = d[i, j]
    del d
    cv = cos_n[i, j]
    del cos_n
    b = np.empty(i.size, np.int32)
    from_cos = j < n_c
    b[from_cos] = direction_bins(dv[from_cos])
    if n_g:
        b[~from_cos] = bins_g[i[~from_cos], j[~from_cos] - n_c]
    del j, from_cos, bins_g
    p_g = guide.density[cell[i], b]
    del b
    weight = cv / (np.float32(n_c / math.pi) * cv + np.float32(n_g) * p_g)
    del cv, p_g
    # The rays' coefficients (8 K bytes a ray with the basis's transposed copy)
    # a group of whole points at a time, at most ~PROJECT_BYTES: a chunk's
    # other arrays are counted per ray, these would grow with the bands. A
    # point's sum is one reduceat over its own rays whatever the grouping.
    starts = np.flatnonzero(np.r_[True, i[1:] != i[:-1]])
    ends = np.r_[starts[1:], i.size]
    step = max(1, PROJECT_BYTES // (8 * K))
    a = 0
    while a < starts.size:
        lo = starts[a]
        b = int(np.searchsorted(ends, lo + step, side="right"))
        if b <= a:
            # One point with more visible rays than a group holds (many rays at many
            # bands): its sum in pieces of ``step`` rays from its own first ray, in order.
            row = i[lo]
            for c in range(lo, ends[a], step):
                e = min(c + step, ends[a])
                contrib = basis_unchecked(dv[c:e], bands, np.float32)
                contrib *= weight[c:e, None]
                out[row] += contrib.sum(axis=0)
            a += 1
            continue
        hi = ends[b - 1]
        # Coefficient-major (K, rays): no transposed copy; reduceat along a point's own
        # rays sums them as reduceat over rows did (the same bits: tests/test_guided.py, numpy 1.26).
        contrib = basis_unchecked(dv[lo:hi], bands, np.float32, coeff_major=True)
        contrib *= weight[None, lo:hi]
        out[i[starts[a:b]]] = np.add.reduceat(contrib, starts[a:b] - lo, axis=1).T
        a = b
    return out, traced


def bake_guided(rs: RayScene, position, normal, geo_normal, ids, guide: Guide, rays: int, bands: int,
                seed: int, threads: int, chunk_rays: int, sink, cancel=None) -> None:
    """Run :func:`guided_transfer` over every guided point in chunks of
    ``chunk_rays`` rays on ``threads`` threads; ``sink(idx, rows, rays_traced,
    thread)`` receives each chunk's rows and the ident of the thread that
    traced them (called on the calling thread)."""
    order = guide.points
    per = max(1, chunk_rays // max(rays, 1))
    parts = [order[a:a + per] for a in range(0, order.size, per)]

    def one(idx):
        if cancel is not None and cancel.is_set():
            raise Cancelled()
        rows, traced = guided_transfer(rs, position, normal, geo_normal, ids, idx, guide, rays, bands, seed)
        return idx, rows, traced, threading.get_ident()

    run_chunks(one, parts, threads, lambda r: sink(*r), cancel)
