"""The transfer bake: SH projection of V(w) max(0, n.w) at surface points.

For each point (a texel's G-buffer sample or a mesh vertex) with shading normal
n and geometric normal g, the transfer vector is

    T_k = integral V(w) max(0, n.w) y_k(w) dw        (k < bands**2),

V = 1 where a ray from the point escapes the scene. How it is computed:

* Local frame: R = Rz(alpha) Ry(beta) Rz(gamma) maps +Z to n (alpha, beta from
  n; gamma a hashed random turn about n that decorrelates neighbours). Ray
  directions are a shared hemisphere pattern (sampling.py) turned by R, and
  the local coefficients are turned to world ones by the SH rotation D(R)
  (rotation.rotate_zyz), so the per-ray cost is one Embree query plus a
  share of a (rays x K) matrix product; no SH evaluation per ray.
* Estimators (``estimator``), all of the form T = base - sum_j O_j W'_j with
  O_j = 1 for blocked rays and A the exact unoccluded projection (the clamped
  cosine, known in closed form):
  - "balanced" (default): W' = w_j W_j with weights balanced so that the
    pattern integrates A exactly (sampling.exact_tables); exact for fully
    visible *and* fully blocked points, a control variate in between;
  - "control-variate": W' = W / N, base = A; exact for fully visible points;
  - "plain": the textbook (1/N) sum_j V_j W_j (base = mean W).
* Shared frames: points on one flat surface (same normal, flat shading, the
  caller's ``frame_group``) that also share a pattern are traced together in
  one frame with one azimuth per chunk: every pattern direction is then one
  Embree call over all the chunk's origins (embreex broadcasts a single
  direction), so there is no per-ray numpy work at all, and the estimator
  table is turned to world once per chunk instead of every point's result.
  Neighbouring texels still get different patterns, so their noise stays
  independent. (Fewer patterns would mean bigger Embree calls and less
  Python between them, ~8 % faster with 16 instead of 64, but texels that
  share a pattern share their noise: the error of 4x4-texel averages rose
  11 % at 256 rays, more than the same time buys as extra rays.)
* Skipping: points whose hemisphere provably holds no geometry (see
  hemisphere_clear.py) get A turned to n with zero rays; rays below the
  geometric horizon (possible when n != g: smooth or normal-mapped shading)
  would enter the surface, so they count as blocked and are never traced.
* Adaptive (``adaptive_tol > 0``): rays come in rounds whose totals are
  min_rays, 2 min_rays, 4 min_rays, ... (stratified prefixes of the scrambled
  Sobol' sequence); a point stops when the RMS standard error of its K
  coefficients (i.i.d. formula, conservative for stratified sampling) is
  below the tolerance.
* Determinism: every random choice is a hash of (seed, point id); chunks are
  independent and write disjoint rows, so results are bit-identical for any
  thread count and scheduling.
* Threads: chunks run on a thread pool (default: all cores); embreex, BLAS
  and the large numpy operations release the GIL.
"""
from __future__ import annotations

import dataclasses
import math
import os
import threading
import time

import numpy as np

from ... import settings_schema as _schema
from ...base.blas import single_threaded_blas
from ...base.errors import Cancelled
from ...base.threads import run_chunks
from ...sh.rotation import rotate_zyz, rotation_zyz
from ...sh.zonal import clamped_cosine_factors, zonal_to_sh
from . import guided
from .raytrace import SAME_NORMAL, RayScene
from .sampling import exact_tables, hash_u32, hash_unit, pattern_bank, unoccluded_local

#: Integer settings: (lowest, highest, why the bound), derived from the one
#: declaration of every setting (settings_schema.SETTINGS); validate() checks
#: them, the command lines and the add-on's properties use the same ranges.
INT_LIMITS = _schema.int_limits("transfer")
#: adaptive_tol: (lowest, highest); above ~2 every texel stops after its first
#: round anyway (transfer coefficients are below sqrt(pi)).
ADAPTIVE_TOL_LIMITS = (_schema.get("adaptive_tol").lo, _schema.get("adaptive_tol").hi)
_d = _schema.default


@dataclasses.dataclass
class TransferSettings:
    """Settings of the transfer bake. Defaults, types and ranges are declared in
    settings_schema.SETTINGS (scope "transfer"), field names here must match
    (tests/test_settings_schema.py)."""

    bands: int = _d("bands")
    rays: int = _d("rays")                  # rays per point (maximum when adaptive)
    sampler: str = _d("sampler")
    distribution: str = _d("distribution")
    estimator: str = _d("estimator")
    adaptive_tol: float = _d("adaptive_tol")    # 0 = fixed ray count
    min_rays: int = _d("min_rays")          # first adaptive round
    analytic: bool = _d("analytic")         # zero-ray path for provably clear points
    guiding: bool = _d("guiding")           # rays aimed at openings where most rays are blocked (guided.py)
    seed: int = _d("seed")
    threads: int = _d("threads")            # 0 = all cores
    n_patterns: int = _d("n_patterns")
    chunk_rays: int = _d("chunk_rays")      # rays per Embree call (bounds memory)

    def validate(self) -> "TransferSettings":
        """Check every field's type and range (ValueError "name must be ..., got ...")."""
        _schema.validate(self, "transfer")
        return self

    @property
    def n_threads(self) -> int:
        return self.threads or os.cpu_count() or 1

    def round_sizes(self) -> list[int]:
        """Rays added per round: [rays], or min_rays, min_rays, 2 min_rays, ... up to rays."""
        if self.adaptive_tol <= 0 or self.min_rays >= self.rays:
            return [self.rays]
        sizes, total = [self.min_rays], self.min_rays
        while total < self.rays:
            step = min(total, self.rays - total)
            sizes.append(step)
            total += step
        return sizes


@dataclasses.dataclass
class Points:
    """Surface points to bake. ids are stable integers (e.g. texel indices)."""

    position: np.ndarray     # (N, 3) float64 world
    normal: np.ndarray       # (N, 3) float64 shading normal
    geo_normal: np.ndarray   # (N, 3) float64 geometric normal
    ids: np.ndarray          # (N,) int64
    analytic: np.ndarray     # (N,) bool: provably unoccluded
    frame_group: np.ndarray | None = None   # (N,) int64, >= 0: may share a frame
    area: float | None = None   # world units²: the surface the points cover (guided.py's cells); None: the scene's

    @property
    def n(self) -> int:
        return int(self.position.shape[0])


def unoccluded_transfer(normals: np.ndarray, bands: int) -> np.ndarray:
    """Exact transfer of fully visible points: the clamped cosine turned to n. (N, K)."""
    return zonal_to_sh(clamped_cosine_factors(bands), normals)


def _frame_angles(n: np.ndarray, ids: np.ndarray, seed: int):
    alpha = np.arctan2(n[:, 1], n[:, 0])
    beta = np.arccos(np.clip(n[:, 2], -1.0, 1.0))
    gamma = 2.0 * math.pi * hash_unit(seed, ids, 0x6A33)
    return alpha, beta, gamma


@dataclasses.dataclass
class ChunkFrames:
    """Per-point ray set-up of one chunk (all arrays indexed like ``idx``)."""

    alpha: np.ndarray
    beta: np.ndarray
    gamma: np.ndarray
    R: np.ndarray            # (n, 3, 3) float32 local -> world
    origins: np.ndarray      # (n, 3) float32 normalised, offset along the geometric normal
    geo_normal: np.ndarray   # (n, 3) float32
    horizon: np.ndarray      # (n,) bool: shading != geometric normal (test the horizon)
    shared: bool = False     # one frame for the whole chunk (rows of R identical)


def chunk_frames(rs: RayScene, pts: Points, idx: np.ndarray, seed: int,
                 shared: bool = False, anchor: tuple | None = None) -> ChunkFrames:
    if shared:
        # One frame: the first point's normal, an azimuth hashed from the
        # chunk's smallest id (deterministic whatever the traversal order);
        # ``anchor``: (first point, smallest id) of the chunk before guided points left it.
        # The points share their geometric normal too (one flat face group).
        first, low = (int(idx[0]), int(pts.ids[idx].min())) if anchor is None else anchor
        ng0 = pts.geo_normal[first]
        org = rs.origins(pts.position[idx], ng0)
        a, b, _ = _frame_angles(pts.normal[first:first + 1], pts.ids[first:first + 1], seed)
        gam = 2.0 * math.pi * hash_unit(seed, low, 0x5A4D)
        n = idx.size
        alpha, beta, gamma = np.full(n, a[0]), np.full(n, b[0]), np.full(n, float(gam))
        R = np.broadcast_to(rotation_zyz(a[0], b[0], gam).astype(np.float32), (n, 3, 3))
        return ChunkFrames(alpha, beta, gamma, R, org, np.broadcast_to(ng0.astype(np.float32), (n, 3)),
                           np.zeros(n, bool), shared=True)
    ng = pts.geo_normal[idx]
    org = rs.origins(pts.position[idx], ng)
    alpha, beta, gamma = _frame_angles(pts.normal[idx], pts.ids[idx], seed)
    R = rotation_zyz(alpha, beta, gamma).astype(np.float32)
    hz = np.einsum("nc,nc->n", pts.normal[idx], ng) < 1.0 - SAME_NORMAL
    return ChunkFrames(alpha, beta, gamma, R, org, ng.astype(np.float32), hz)


def shared_rotation(fr: ChunkFrames, K: int) -> np.ndarray:
    """D^T (K, K) float64 of a shared-frame chunk: world coefficients = local @ D^T."""
    # Rows of rotate_zyz(I) are D(R) e_i, i.e. it returns D^T.
    ang = lambda v: np.full(K, v)  # noqa: E731
    return rotate_zyz(np.eye(K), ang(fr.alpha[0]), ang(fr.beta[0]), ang(fr.gamma[0]))


def pattern_count(st: TransferSettings) -> int:
    """Patterns in the bank: n_patterns, capped so the bank stays <= 64 MB."""
    return max(1, min(st.n_patterns, int(2 ** 24 // max(st.rays * st.bands ** 2, 1))))


#: A (frame group, pattern) bucket needs this many points to be traced with a
#: shared frame; a shared chunk holds up to SHARED_FACTOR x the points of a
#: per-point chunk (its rays need no per-ray arrays, so it can be bigger).
SHARED_MIN = 128
SHARED_FACTOR = 2


@dataclasses.dataclass
class Chunk:
    g: int                   # pattern
    idx: np.ndarray          # point indices
    shared: bool             # one frame for all points
    # A shared chunk some of whose points are traced elsewhere (guided.py): the
    # (point index, smallest id) its frame is made from, those of the whole
    # chunk, so the points it keeps get the rows they had with it whole.
    anchor: tuple | None = None
    # (n,) bool: the points whose rays are not traced (bake_points' ``skip``), or None.
    skip: np.ndarray | None = None


def _stable_order(major: np.ndarray, minor: np.ndarray | None = None) -> np.ndarray:
    """Stable order of non-negative integer keys, by (major, minor) when both are
    given: what np.argsort(major * (max(minor) + 1) + minor, kind="stable") gives.
    Keys below 2^16 go through uint16, which numpy sorts by radix (~15x faster),
    two passes for pairs (least significant first)."""
    keys = [k for k in (minor, major) if k is not None]
    if all(k.size == 0 or int(k.max()) < 1 << 16 for k in keys):
        o = np.argsort(keys[0].astype(np.uint16), kind="stable")
        for k in keys[1:]:
            o = o[np.argsort(k[o].astype(np.uint16), kind="stable")]
        return o
    if minor is None:
        return np.argsort(major, kind="stable")
    return np.argsort(major * (int(minor.max()) + 1) + minor, kind="stable")


def chunk_plan(pts: Points, settings: TransferSettings, exclude: np.ndarray | None = None):
    """The bake's work split: list of :class:`Chunk`, and the pattern count G.
    ``exclude`` (N,) bool: points traced elsewhere (guided.py), left out.

    Deterministic in (seed, ids, frame groups); shared by the bake and the
    benchmark (which re-traces the very same rays with bare Embree calls).
    Its temporaries are freed as it goes (~20 B a point at most beside the
    chunks' indices, #35: they had peaked at 83 B a texel beside the G-buffer).
    """
    st = settings
    analytic = pts.analytic if st.analytic else np.zeros(pts.n, bool)
    traced = np.flatnonzero(~analytic)
    G = pattern_count(st)
    # Patterns fit int32 (G is capped by the bank's size); indices of traced fit int32 below 2^31 points.
    idx_t = np.int32 if traced.size < 1 << 31 else np.int64
    pattern = (hash_u32(st.seed, pts.ids[traced], 0x9A77) % np.uint32(G)).astype(np.int32)
    per_chunk = max(1, st.chunk_rays // st.round_sizes()[0])
    chunks = []
    solo = np.ones(traced.size, bool)
    if pts.frame_group is not None:
        grp = pts.frame_group[traced]
        cand = np.flatnonzero(grp >= 0).astype(idx_t)
        if cand.size:
            grp = grp[cand]
            o = _stable_order(grp, pattern[cand])
            cand_s = cand[o]
            key_s = grp[o] * G + pattern[cand_s]
            o = None
            starts = np.flatnonzero(np.r_[True, key_s[1:] != key_s[:-1]])
            ends = np.r_[starts[1:], key_s.size]
            del key_s
            big = per_chunk * SHARED_FACTOR
            for a, b in zip(starts, ends):
                if b - a < SHARED_MIN:
                    continue
                for c in range(a, b, big):
                    sel = cand_s[c:min(c + big, b)]
                    solo[sel] = False
                    members = traced[sel]
                    if exclude is None or not exclude[members].any():
                        chunks.append(Chunk(int(pattern[sel[0]]), members, True))
                        continue
                    # Planned as without guided points (the same frames), traced without them.
                    anchor = (int(members[0]), int(pts.ids[members].min()))
                    keep = members[~exclude[members]]
                    if keep.size:
                        chunks.append(Chunk(int(pattern[sel[0]]), keep, True, anchor))
            cand_s = None
        grp = cand = None
    if exclude is not None:
        # Points with frames of their own: their rows do not depend on their chunk's company.
        solo &= ~exclude[traced]
    rest = np.flatnonzero(solo).astype(idx_t)
    del solo
    p_rest = pattern[rest]
    del pattern
    o = _stable_order(p_rest)
    p_sorted = p_rest[o]
    del p_rest
    order = traced[rest[o]]
    del rest, o, traced
    for g in range(G):
        lo, hi = np.searchsorted(p_sorted, [g, g + 1])
        for a in range(lo, hi, per_chunk):
            chunks.append(Chunk(g, order[a:min(a + per_chunk, hi)], False))
    return chunks, G


class _Stats:
    def __init__(self):
        self.lock = threading.Lock()
        self.rays_traced = 0
        self.rays_below_horizon = 0
        self.rays_planned = 0
        self.points_done = 0
        self.early_stopped = 0
        self.threads_used = set()

    def add(self, traced, below, planned, points, early, thread=None):
        """Count one chunk; ``thread``: who traced it (default: this thread)."""
        with self.lock:
            self.rays_traced += traced
            self.rays_below_horizon += below
            self.rays_planned += planned
            self.points_done += points
            self.early_stopped += early
            self.threads_used.add(threading.get_ident() if thread is None else thread)


def estimator_tables(st: TransferSettings, G: int, prefix: int, cancel=None):
    """(base (G, K) float64, table (G, prefix, K) float32): T = base - O @ table."""
    _, W, cum = pattern_bank(G, st.rays, st.bands, st.sampler, st.distribution, st.seed, cancel=cancel)
    A = unoccluded_local(st.bands)
    if st.estimator == "balanced":
        return np.tile(A, (G, 1)), exact_tables(G, st.rays, st.bands, st.sampler,
                                               st.distribution, st.seed, prefix, cancel=cancel)
    table = (W[:, :prefix].astype(np.float64) / prefix).astype(np.float32)
    if st.estimator == "control-variate":
        return np.tile(A, (G, 1)), table
    return cum[:, prefix - 1] / prefix, table


def warm_tables(settings: TransferSettings, cancel: threading.Event | None = None) -> None:
    """Compute the (cached) ray patterns and estimator tables a bake with these
    settings will use, e.g. on a helper thread while the G-buffer is built.
    ``cancel`` set -> :class:`Cancelled` (checked between patterns)."""
    st = settings
    G = pattern_count(st)
    pattern_bank(G, st.rays, st.bands, st.sampler, st.distribution, st.seed, cancel=cancel)
    for c in np.cumsum(st.round_sizes()).tolist():
        estimator_tables(st, G, c, cancel)


class ChunkKernel:
    """Everything one chunk needs: computes the world transfer of its points.

    Used by the bake's thread pool (bake_points); a chunk's result depends only
    on the chunk, never on the thread that runs it. Not thread-safe per
    instance except through :meth:`run`, which keeps its scratch buffers per
    thread.
    """

    def __init__(self, rs: RayScene, pts: Points, st: TransferSettings, G: int, cancel=None):
        self.rs, self.pts, self.st, self.G = rs, pts, st, G
        self.K = st.bands ** 2
        self.dirs_bank, self.w_bank, self.cum_w = pattern_bank(
            G, st.rays, st.bands, st.sampler, st.distribution, st.seed, cancel=cancel)
        self.rounds = st.round_sizes()
        self.adaptive = len(self.rounds) > 1
        totals = np.cumsum(self.rounds).tolist()
        self.tables = {c: estimator_tables(st, G, c, cancel) for c in totals}
        self.base32 = {c: t[0].astype(np.float32) for c, t in self.tables.items()}
        if self.adaptive:
            self.w2_bank = (self.w_bank.astype(np.float64) ** 2).astype(np.float32)
            self.cum_w2 = np.cumsum(self.w2_bank.astype(np.float64), axis=1)
        self._local = threading.local()

    def _buffers(self, n_rays):
        b = getattr(self._local, "b", None)
        if b is None or b[0].shape[0] < n_rays:
            b = (np.empty((n_rays, 3), np.float32), np.empty((n_rays, 3), np.float32),
                 np.empty(n_rays, np.float32))
            self._local.b = b
        return b

    def _trace_round_shared(self, R, org, P, cancel=None, skip=None):
        """Occlusion (m, size) float32 when all m origins share the frame R (3, 3):
        one Embree call per direction, broadcast over the origins; ``skip`` (m,)
        bool: origins not traced (their rows meaningless)."""
        m, size = org.shape[0], P.shape[0]
        Dw = np.ascontiguousarray(P @ R.T)                      # (size, 3) world directions
        # The loop holds the GIL between Embree calls, and each time a thread must
        # wait for it costs a wake-up: keep its work to one call and one append
        # (bare embreex results, 0 = occluded), and convert once at the end.
        rows = []
        tfar = np.full(m, np.inf, np.float32)                   # read-only to embreex
        if skip is not None:
            tfar[skip] = -1.0                                   # rejected without traversal
        trace = self.rs.occluded_raw
        for j in range(size):
            if j % 32 == 0 and cancel is not None and cancel.is_set():
                raise Cancelled()
            rows.append(trace(org, Dw[j:j + 1], tfar))
        hits = np.stack(rows)
        del rows
        OT = hits.view(np.float32)                              # 1.0 = occluded, in place
        np.equal(hits, 0, out=OT, casting="unsafe")
        skipped = 0 if skip is None else int(np.count_nonzero(skip)) * size
        return OT.T, m * size - skipped, 0

    def _trace_round(self, R, org, ng, hz, P, shared=False, cancel=None, skip=None):
        """Occlusion (m, size) float32 of pattern directions P turned by R;
        ``skip`` (m,) bool: points not traced (their rows meaningless)."""
        if shared:
            return self._trace_round_shared(np.asarray(R[0]), org, P, cancel, skip)
        m, size = R.shape[0], P.shape[0]
        ob, db, tb = self._buffers(m * size)
        ob[:m * size].reshape(m, size, 3)[...] = org[:, None, :]      # GIL-free broadcast copy
        D3 = np.matmul(P[None], R.transpose(0, 2, 1), out=db[:m * size].reshape(m, size, 3))
        if not hz.any() and skip is None:
            occ = self.rs.occluded(ob[:m * size], db[:m * size])
            return occ.reshape(m, size).astype(np.float32), m * size, 0
        # Rays below the geometric horizon would enter the surface: they count
        # as blocked and go to Embree with an empty interval (tfar < tnear = 0),
        # which it rejects without traversal; so do every ray of a skipped point.
        below = (np.matmul(D3, ng[:, :, None])[..., 0] <= 0.0) & hz[:, None]
        tfar = tb[:m * size]
        tfar.fill(np.inf)
        tfar[below.ravel()] = -1.0
        if skip is not None:
            tfar.reshape(m, size)[skip] = -1.0
        occ = self.rs.occluded(ob[:m * size], db[:m * size], tfar=tfar).reshape(m, size)
        occ |= below
        n_skip = 0 if skip is None else int(np.count_nonzero(skip))
        n_below = int(below.sum() if skip is None else below[~skip].sum())
        return occ.astype(np.float32), (m - n_skip) * size - n_below, n_below

    def run(self, chunk: "Chunk", cancel=None):
        """World transfer (n, K) float32 of the chunk's points, and (rays
        traced, rays below horizon, points stopped early)."""
        st, g, idx = self.st, chunk.g, chunk.idx
        fr = chunk_frames(self.rs, self.pts, idx, st.seed, shared=chunk.shared, anchor=chunk.anchor)
        n = idx.size
        if not self.adaptive:
            O, traced, below = self._trace_round(fr.R, fr.origins, fr.geo_normal, fr.horizon,
                                                 self.dirs_bank[g], fr.shared, cancel, chunk.skip)
            base, table = self.base32[st.rays][g], self.tables[st.rays][1][g]
            if fr.shared:
                # One frame: turn the estimator to world once (a (rays, K) table)
                # instead of turning every point's result.
                Dt = self._shared_rotation(fr)
                base = (base.astype(np.float64) @ Dt).astype(np.float32)
                table = (table.astype(np.float64) @ Dt).astype(np.float32)
                return base[None, :] - O @ table, (traced, below, 0)
            local = base[None, :] - O @ table
            early = 0
        else:
            local, traced, below, early = self._run_adaptive(g, fr, n, cancel)
        if fr.shared:
            return local @ self._shared_rotation(fr).astype(np.float32), (traced, below, early)
        return rotate_zyz(local, fr.alpha, fr.beta, fr.gamma), (traced, below, early)

    def _shared_rotation(self, fr: ChunkFrames) -> np.ndarray:
        return shared_rotation(fr, self.K)

    def _run_adaptive(self, g, fr, n, cancel):
        st, K = self.st, self.K
        O_all = np.zeros((n, st.rays), np.uint8)
        acc = np.zeros((n, K))
        acc2 = np.zeros((n, K))
        count = np.zeros(n, np.int64)
        active = np.arange(n)
        start = traced = below = 0
        for r_i, size in enumerate(self.rounds):
            if cancel is not None and cancel.is_set():
                raise Cancelled()
            O, t_r, b_r = self._trace_round(fr.R[active], fr.origins[active], fr.geo_normal[active],
                                            fr.horizon[active], self.dirs_bank[g, start:start + size],
                                            fr.shared, cancel)
            traced += t_r
            below += b_r
            O_all[active, start:start + size] = O
            acc[active] += O @ self.w_bank[g, start:start + size]
            acc2[active] += O @ self.w2_bank[g, start:start + size]
            count[active] += size
            start += size
            if r_i == len(self.rounds) - 1:
                break
            c = float(start)
            if st.estimator == "plain":
                s1 = self.cum_w[g, start - 1] - acc[active]
                s2 = self.cum_w2[g, start - 1] - acc2[active]
            else:
                s1, s2 = acc[active], acc2[active]
            var = np.maximum(s2 / c - (s1 / c) ** 2, 0.0)
            active = active[np.sqrt((var / c).mean(axis=1)) > st.adaptive_tol]
            if active.size == 0:
                break
        local = np.empty((n, K), np.float32)
        for c in np.unique(count):
            sel = np.flatnonzero(count == c)
            table = self.tables[int(c)][1]
            local[sel] = self.base32[int(c)][g][None, :] - O_all[sel, :c].astype(np.float32) @ table[g]
        return local, traced, below, int(np.count_nonzero(count < st.rays))


def _guide(rs, pts, st, analytic, cancel):
    """The guide of the points the transfer traces (guided.build_guide), or
    None where no point is guided (then the bake is the one without guiding,
    byte for byte)."""
    traced = ~analytic
    if not traced.any():
        return None
    area = rs.area if pts.area is None else pts.area
    g = guided.build_guide(rs, pts.position, pts.normal, pts.geo_normal, pts.ids, traced, area, st.seed,
                           st.n_threads, st.chunk_rays, cancel)
    return g if bool((g.cell >= 0).any()) else None


#: GIL switch interval while tracing: a thread leaving Embree waits at most
#: this long for the other's Python glue (default 5 ms; 0.5 ms measured ~8%
#: faster on two cores).
SWITCH_INTERVAL = 0.0005


def bake_points(rs: RayScene, pts: Points, settings: TransferSettings, *,
                progress=None, cancel: threading.Event | None = None, remote=None,
                skip: np.ndarray | None = None):
    """Transfer vectors of ``pts``: returns ((N, K) float32, stats dict).

    ``skip`` (N,) bool: points whose rows the caller drops (texels inside
    geometry, validity.inside_texels): their rays are not traced and their
    rows are meaningless (zero where guided). The other points' rows are
    theirs bit for bit: the guide's pilot still counts the skipped points,
    and they stay in their chunks (the same shapes through BLAS, whose
    rounding can depend on them), their rays handed to Embree with an empty
    interval (ChunkKernel.run; each Chunk carries its ``skip``, to a Dask
    worker too). Under adaptive sampling (its rounds' shapes follow every
    point's noise) the plain chunks' skipped points are traced; guided ones
    are left out either way.

    Chunks run on ``settings.n_threads`` threads with single-threaded BLAS and
    write their rows of the result (disjoint, whole rows: see bake.py for why
    rows, not texture planes). progress(done_points, total_points,
    rays_traced) is called from the calling thread as chunks finish.
    ``cancel`` set -> :class:`Cancelled`. ``remote`` (distributed.DaskBake):
    the same chunks run on a Dask cluster instead of local threads (the same
    results, bit for bit).
    """
    import sys

    old_interval = sys.getswitchinterval()
    sys.setswitchinterval(SWITCH_INTERVAL)
    try:
        with single_threaded_blas():
            return _bake_points(rs, pts, settings, progress, cancel, remote, skip)
    finally:
        sys.setswitchinterval(old_interval)


def _bake_points(rs, pts, settings, progress, cancel, remote=None, skip=None):
    st = settings.validate()
    K = st.bands ** 2
    N = pts.n
    stats = _Stats()
    t0 = time.perf_counter()
    analytic = pts.analytic if st.analytic else np.zeros(N, bool)
    # The guide (its pilot rays) before the rows exist: its temporaries and the rows are never held together.
    guide = _guide(rs, pts, st, analytic, cancel) if st.guiding else None
    guided_pts = None if guide is None else guide.cell >= 0
    kernel_skip = None                        # the plain chunks' points whose rays are not traced
    skipped_guided = 0
    if skip is not None:
        skip = np.asarray(skip, bool) & ~analytic
        if guide is not None:
            # Guided points run alone (their rows do not depend on their company): left out.
            skipped_guided = int(np.count_nonzero(skip & guided_pts))
            guide = dataclasses.replace(guide, cell=np.where(skip, -1, guide.cell).astype(np.int32))
        if len(st.round_sizes()) == 1:
            kernel_skip = skip & ~guided_pts if guided_pts is not None else skip
            if not kernel_skip.any():
                kernel_skip = None
    # Planned before the rows exist: the planner's temporaries and the rows are never held together.
    chunks, G = chunk_plan(pts, st, guided_pts)
    if kernel_skip is not None:
        # Each chunk carries its own (to a Dask worker too): the same rays traced either way.
        for c in chunks:
            own = kernel_skip[c.idx]
            if own.any():
                c.skip = own
    out = np.zeros((N, K), np.float32)

    ia = np.flatnonzero(analytic)
    if ia.size:
        out[ia] = unoccluded_transfer(pts.normal[ia], st.bands)
    skipped = skipped_guided + (0 if kernel_skip is None else int(np.count_nonzero(kernel_skip)))
    n_traced = N - int(ia.size) - skipped
    done = int(ia.size) + skipped_guided       # the plain chunks' skipped points count as their chunks finish
    if progress:
        progress(done, N, 0)

    def on_result(n):
        nonlocal done
        done += n
        if progress:
            progress(done, N, stats.rays_traced)

    if guide is not None:
        with stats.lock:
            stats.rays_traced += guide.pilot_rays
    if chunks:
        def sink(chunk, res, counts, thread=None):
            out[chunk.idx] = res
            n = chunk.idx.size
            stats.add(*counts[:2], n * st.rays, n, counts[2], thread)
            return n

        # Biggest chunks first, so the threads finish together.
        chunks = sorted(chunks, key=lambda c: -c.idx.size)
        if remote is not None:
            remote.trace_points(pts, st, chunks, G, sink, on_result, cancel)
        else:
            kernel = ChunkKernel(rs, pts, st, G, cancel)

            def run_chunk(chunk):
                if cancel is not None and cancel.is_set():
                    raise Cancelled()
                res, counts = kernel.run(chunk, cancel)
                return sink(chunk, res, counts)

            run_chunks(run_chunk, chunks, st.n_threads, on_result, cancel)
    n_guided = 0
    guided_threads = set()
    if guide is not None:
        # Guided points run on this machine's threads (with a Dask cluster too: the same rows either way).
        def guided_sink(idx, rows, traced, thread):
            out[idx] = rows
            stats.add(traced, 0, idx.size * st.rays, idx.size, 0, -1)
            guided_threads.add(thread)
            on_result(idx.size)

        n_guided = int(np.count_nonzero(guided_pts))       # chosen by the guide (skipped ones too)
        guided.bake_guided(rs, pts.position, pts.normal, pts.geo_normal, pts.ids, guide, st.rays, st.bands,
                           st.seed, st.n_threads, st.chunk_rays, guided_sink, cancel)
    seconds = time.perf_counter() - t0
    info = {
        "points": N,
        "analytic_points": int(ia.size),
        "skipped_points": skipped,
        "traced_points": n_traced,
        "rays_traced": stats.rays_traced,
        "rays_below_horizon_skipped": stats.rays_below_horizon,
        "rays_naive": N * st.rays,
        "adaptive_early_stops": stats.early_stopped,
        "guided_points": n_guided,
        # (G,) int64: which points were guided (ascending; empty without guiding), for guided_filter.
        "guided_index": np.flatnonzero(guided_pts) if guided_pts is not None else np.zeros(0, np.int64),
        "pilot_rays": 0 if guide is None else guide.pilot_rays,
        # Threads at work at once: the guided points run on a pool of their own.
        "threads": max(len(stats.threads_used - {-1}), len(guided_threads)),
        "seconds": seconds,
        "rays_per_second": stats.rays_traced / seconds if seconds > 0 else 0.0,
    }
    return out, info
