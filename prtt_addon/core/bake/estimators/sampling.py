"""Hemisphere direction patterns for the transfer bake (deterministic).

A pattern is S unit directions in a *local* frame whose +Z is the surface
normal, with per-direction projection weights W_jk = f(d_j) y_k(d_j) / pdf(d_j)
for the cosine factor f = cos(theta): the transfer estimate from N rays is
    T_local ~= (1/N) sum_j V_j W_j.

Point sets in the unit square (``sampler``):
* "sobol" (default): the (0,2)-sequence (van der Corput x Sobol' dimension 2)
  with hash-based Owen scrambling (Burley 2020). Every power-of-two prefix is
  stratified, so adaptive rounds that take consecutive blocks stay stratified.
* "stratified": jittered grid cells (a random subset of cells when S is not
  a square).
* "random": independent uniform points (the Monte Carlo baseline).

Maps to the hemisphere (``distribution``):
* "cosine" (default): pdf = cos(theta) / pi, so W = pi y_k; no ray is wasted
  on grazing directions that carry no weight.
* "uniform": pdf = 1 / (2 pi), W = 2 pi cos(theta) y_k.

Exact weights (``exact_tables``): the plain estimate (1/N) sum V_j W_j is
unbiased, but the pattern's own quadrature error (0.007 at 256 Sobol' rays)
shows up as error even where nothing is occluded, and where everything is.
Per pattern and ray count N we therefore use positive weights w_j, as close
to uniform as exponential tilting allows, that make the pattern integrate the
unoccluded transfer exactly: sum_j w_j W_jk = A_k (the clamped cosine's
projection). Then T = A - sum_j w_j O_j W_j (O = blocked) is exact for fully
visible and for fully blocked points, and in between a control-variate
estimate. Where no such weights exist within a spread of 8 (too few rays for
the K moments: below ~256 rays at 5 bands) the pattern keeps uniform weights,
i.e. the plain control variate T = A - (1/N) sum_j O_j W_j.

Every random choice derives from integer hashes of (seed, pattern, ...), so the
same inputs give bit-identical patterns on every machine.
"""
from __future__ import annotations

import collections
import concurrent.futures as cf
import math
import os
import threading

import numpy as np

from ...base.blas import single_threaded_blas
from ...base.errors import Cancelled
from ...settings_schema import SAMPLERS
from ...sh.basis import eval_basis
from ...sh.zonal import clamped_cosine_factors

_U32 = np.uint32


def hash_u32(*keys) -> np.ndarray:
    """A well-mixed 32-bit hash of integer arrays (broadcast), as uint32."""
    h = np.asarray(0x9E3779B9, dtype=np.uint64)
    for k in keys:
        k = np.asarray(k).astype(np.uint64) & np.uint64(0xFFFFFFFF)
        h = h ^ (k + np.uint64(0x9E3779B9) + (h << np.uint64(6)) + (h >> np.uint64(2)))
        h &= np.uint64(0xFFFFFFFF)
        # murmur3 finaliser
        h ^= h >> np.uint64(16)
        h = (h * np.uint64(0x85EBCA6B)) & np.uint64(0xFFFFFFFF)
        h ^= h >> np.uint64(13)
        h = (h * np.uint64(0xC2B2AE35)) & np.uint64(0xFFFFFFFF)
        h ^= h >> np.uint64(16)
    return h.astype(_U32)


def hash_unit(*keys) -> np.ndarray:
    """Hash to float64 in [0, 1)."""
    return hash_u32(*keys).astype(np.float64) / 4294967296.0


def _reverse_bits(x: np.ndarray) -> np.ndarray:
    x = x.astype(_U32)
    x = ((x >> _U32(1)) & _U32(0x55555555)) | ((x & _U32(0x55555555)) << _U32(1))
    x = ((x >> _U32(2)) & _U32(0x33333333)) | ((x & _U32(0x33333333)) << _U32(2))
    x = ((x >> _U32(4)) & _U32(0x0F0F0F0F)) | ((x & _U32(0x0F0F0F0F)) << _U32(4))
    x = ((x >> _U32(8)) & _U32(0x00FF00FF)) | ((x & _U32(0x00FF00FF)) << _U32(8))
    return (x >> _U32(16)) | (x << _U32(16))


def _laine_karras(x: np.ndarray, seed: int) -> np.ndarray:
    with np.errstate(over="ignore"):
        x = x + _U32(seed)
        x ^= x * _U32(0x6C50B47C)
        x ^= x * _U32(0xB82F1E52)
        x ^= x * _U32(0xC7AFE638)
        x ^= x * _U32(0x8D22F6E6)
    return x


def _owen(x: np.ndarray, seed: int) -> np.ndarray:
    return _reverse_bits(_laine_karras(_reverse_bits(x), seed))


def sobol2(n: int, seed: int) -> np.ndarray:
    """(n, 2) Owen-scrambled (0,2)-sequence points in [0, 1)."""
    i = np.arange(n, dtype=np.uint64).astype(_U32)
    x = _reverse_bits(i)                      # van der Corput
    y = np.zeros(n, _U32)
    v = _U32(1 << 31)
    for bit in range(32):
        if (n - 1) >> bit == 0:
            break
        y ^= np.where((i >> _U32(bit)) & _U32(1), v, _U32(0)).astype(_U32)
        v = _U32(v ^ (v >> _U32(1)))
    s = hash_u32(seed, 0x50B01)
    x = _owen(x, int(hash_u32(s, 1)))
    y = _owen(y, int(hash_u32(s, 2)))
    return np.stack([x, y], axis=-1).astype(np.float64) / 4294967296.0


def stratified2(n: int, seed: int) -> np.ndarray:
    """(n, 2) jittered-grid points; a hashed random subset of cells if n is not square."""
    m = math.isqrt(n)
    if m * m < n:
        m += 1
    cells = np.arange(m * m)
    if m * m > n:
        cells = cells[np.argsort(hash_u32(seed, 0x5713, cells), kind="stable")[:n]]
    jitter = np.stack([hash_unit(seed, 1, cells), hash_unit(seed, 2, cells)], axis=-1)
    return (np.stack([cells % m, cells // m], axis=-1) + jitter) / m


def random2(n: int, seed: int) -> np.ndarray:
    idx = np.arange(n)
    return np.stack([hash_unit(seed, 0xAA, idx), hash_unit(seed, 0xBB, idx)], axis=-1)


def square_points(sampler: str, n: int, seed: int) -> np.ndarray:
    if sampler == "sobol":
        return sobol2(n, seed)
    if sampler == "stratified":
        return stratified2(n, seed)
    if sampler == "random":
        return random2(n, seed)
    raise ValueError(f"unknown sampler {sampler!r}; choose one of {', '.join(SAMPLERS)}")


def to_hemisphere(u: np.ndarray, distribution: str) -> tuple[np.ndarray, np.ndarray]:
    """Map (n, 2) points to local unit directions (z = normal) and pdf values."""
    phi = 2.0 * math.pi * u[:, 1]
    if distribution == "cosine":
        r = np.sqrt(u[:, 0])
        z = np.sqrt(np.maximum(0.0, 1.0 - u[:, 0]))
        pdf = z / math.pi
    elif distribution == "uniform":
        z = 1.0 - u[:, 0]                      # in (0, 1]
        r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
        pdf = np.full(z.shape, 1.0 / (2.0 * math.pi))
    else:
        raise ValueError(f"unknown distribution {distribution!r}; choose cosine or uniform")
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d, pdf


def tangent_frames(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tangent and bitangent (N, 3) completing unit normals n (N, 3) to
    right-handed orthonormal frames (Frisvad 2012 in Duff et al.'s 2017
    branch-free form)."""
    s = np.where(n[:, 2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (s + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1.0 + s * n[:, 0] ** 2 * a, s * b, -s * n[:, 0]], axis=-1)
    bt = np.stack([b, s + n[:, 1] ** 2 * a, -n[:, 1]], axis=-1)
    return t, bt


def unoccluded_local(bands: int) -> np.ndarray:
    """(K,) exact projection of max(0, cos theta) about +Z (zonal)."""
    l = np.arange(bands)
    a = np.zeros(bands * bands)
    a[l * l + l] = clamped_cosine_factors(bands) * np.sqrt((2 * l + 1) / (4 * math.pi))
    return a


def balance_weights(W: np.ndarray, target: np.ndarray, iters: int = 60) -> tuple[np.ndarray, float]:
    """Positive weights close to uniform with sum_j w_j W_j = target.

    Exponential tilting (entropy balancing): w_j = exp(W_j . lam) / N, lam from
    Newton's method on the convex dual f(lam) = sum_j w_j - target . lam, with
    backtracking. Always positive; exact when the target is reachable by
    positive weights. Returns (weights (N,), max residual).

    A step is taken when it lowers the dual enough (Armijo) or, failing that,
    when it lowers the residual max|grad|: near the optimum the dual's decrease
    (about grad . step, 1e-16 and less) is below float64's resolution of f ~ 1,
    so the Armijo test alone stalled some patterns at residuals of 1e-10-1e-7
    that depend on the last bits of exp and LAPACK. Those bits differ between
    numpy lines (1.26 and 2.x), and BALANCE_TOLERANCE then chose balanced
    weights for a pattern in one Blender and uniform ones in another: bounce
    textures 17 % apart in some texels. The gradient is resolved to ~1e-15, so
    the iteration runs on to ~1e-14 in every numpy.
    """
    N, K = W.shape
    lam = np.zeros(K)
    w = np.full(N, 1.0 / N)

    def weights(l):
        return np.exp(np.minimum(W @ l, 60.0)) / N     # an infeasible target drives lam to infinity

    f = 1.0
    grad = W.T @ w - target
    for _ in range(iters):
        res = np.abs(grad).max()
        if res < 1e-13:
            break
        H = (W * w[:, None]).T @ W
        step = np.linalg.lstsq(H + 1e-14 * np.trace(H) * np.eye(K), grad, rcond=None)[0]
        decrease = grad @ step
        t = 1.0
        while t > 1e-8:
            cand = lam - t * step
            wc = weights(cand)
            fc = wc.sum() - target @ cand
            gc = W.T @ wc - target
            if np.isfinite(fc) and (fc <= f - 1e-4 * t * decrease or np.abs(gc).max() <= (1.0 - 0.5 * t) * res):
                break
            t *= 0.5
        else:
            break
        lam, f, w, grad = cand, fc, wc, gc
    return w, float(np.abs(W.T @ w - target).max())


#: Balanced weights are used only when exact to this and within this spread
#: (max/min); otherwise the pattern keeps uniform weights (plain control variate).
BALANCE_TOLERANCE = 1e-8
BALANCE_MAX_SPREAD = 8.0


class _Memo:
    """A small LRU cache of computed tables, shared by threads.

    Unlike functools.lru_cache it lets the computation take a ``cancel`` event
    that is not part of the key (a cancelled computation caches nothing), and a
    key being computed by one thread is waited for, not computed twice (the
    bake warms tables on a helper while the G-buffer builds, then the trace
    asks for the same ones).
    """

    def __init__(self, maxsize: int):
        self.maxsize = maxsize
        self.lock = threading.Lock()
        self.done: collections.OrderedDict = collections.OrderedDict()
        self.busy: dict = {}

    def get(self, key, compute, cancel=None):
        while True:
            with self.lock:
                if key in self.done:
                    self.done.move_to_end(key)
                    return self.done[key]
                ev = self.busy.get(key)
                if ev is None:
                    ev = self.busy[key] = threading.Event()
                    break
            # Another thread computes it: wait (cancellable), then look again.
            while not ev.wait(0.05):
                _check(cancel)
        try:
            value = compute(cancel)
            with self.lock:
                self.done[key] = value
                while len(self.done) > self.maxsize:
                    self.done.popitem(last=False)
            return value
        finally:
            with self.lock:
                self.busy.pop(key, None)
            ev.set()

    def clear(self):
        with self.lock:
            self.done.clear()


def _check(cancel) -> None:
    if cancel is not None and cancel.is_set():
        raise Cancelled()


_EXACT = _Memo(32)
_BANKS = _Memo(8)


def exact_tables(n_patterns: int, n_rays: int, bands: int, sampler: str,
                 distribution: str, seed: int, prefix: int, *, cancel=None) -> np.ndarray:
    """(G, prefix, K) float32 tables W'_j = N w_j W_j / N for the first ``prefix``
    rays of each pattern, with weights balanced so sum_j W'_j = A (see module doc).
    Cached; ``cancel`` (an Event) is checked between patterns (parallel.Cancelled)."""
    key = (n_patterns, n_rays, bands, sampler, distribution, seed, prefix)
    return _EXACT.get(key, lambda c: _exact_tables(*key, c), cancel)


def _exact_tables(n_patterns, n_rays, bands, sampler, distribution, seed, prefix, cancel):
    _, W, _ = pattern_bank(n_patterns, n_rays, bands, sampler, distribution, seed, cancel=cancel)
    A = unoccluded_local(bands)
    out = np.empty((n_patterns, prefix, bands * bands), np.float32)

    def one(g):
        _check(cancel)
        Wg = W[g, :prefix].astype(np.float64)
        if prefix < bands * bands:
            # Fewer rays than coefficients: K constraints on N < K weights have no
            # exact solution in general, and the Newton search costs ~10 ms a pattern.
            out[g] = (Wg / prefix).astype(np.float32)
            return
        w, res = balance_weights(Wg, A)
        if not (res <= BALANCE_TOLERANCE and w.max() <= BALANCE_MAX_SPREAD * w.min()):
            w = np.full(prefix, 1.0 / prefix)
        out[g] = (w[:, None] * Wg).astype(np.float32)

    if prefix < bands * bands or bands < 8:
        for g in range(n_patterns):
            one(g)
    else:
        # Many bands: each pattern's Newton steps are (K x K) least squares, 0.7 s
        # a pattern at 16 bands; patterns are independent and LAPACK lets go of the
        # GIL, so one thread per core (each single-threaded BLAS: the same bytes).
        with single_threaded_blas(), cf.ThreadPoolExecutor(max(1, os.cpu_count() or 1)) as ex:
            list(ex.map(one, range(n_patterns)))
    out.setflags(write=False)
    return out


def pattern_bank(n_patterns: int, n_rays: int, bands: int, sampler: str,
                 distribution: str, seed: int, *, cancel=None):
    """G patterns of S local directions with projection weights.

    Returns (dirs (G, S, 3) float32, weights (G, S, K) float32 = cos y / pdf,
    weights_sum (G, S, K) float64 = cumulative sum over the first j+1 rays,
    used for the plain estimator). Read-only, cached; ``cancel`` is checked
    between patterns.
    """
    key = (n_patterns, n_rays, bands, sampler, distribution, seed)
    return _BANKS.get(key, lambda c: _pattern_bank(*key, c), cancel)


def _pattern_bank(n_patterns, n_rays, bands, sampler, distribution, seed, cancel):
    dirs = np.empty((n_patterns, n_rays, 3))
    W = np.empty((n_patterns, n_rays, bands * bands))
    for g in range(n_patterns):
        _check(cancel)
        u = square_points(sampler, n_rays, int(hash_u32(seed, g, 0xD1)))
        d, pdf = to_hemisphere(u, distribution)
        dirs[g] = d
        W[g] = eval_basis(d, bands) * (d[:, 2] / np.maximum(pdf, 1e-300))[:, None]
    cum = np.cumsum(W, axis=1)
    out = (dirs.astype(np.float32), W.astype(np.float32), cum)
    for a in out:
        a.setflags(write=False)
    return out
