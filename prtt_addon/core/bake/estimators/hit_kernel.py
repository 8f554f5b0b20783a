"""Compiled per-hit exit radiance for the bounce bake (optional: numba).

A bounce ray that hits a surface reads the radiance leaving the hit point
towards the ray's origin from the hit set's exit textures
(bounce.ExitTextures): the diffuse term D_c of the nearest texel, plus, on
triangles with a specular lobe, sum_k G_c,k y_k(r) with r the view reflected
about the texel's shading normal (docs/shading.md). bounce.ExitShader.radiance
does this with numpy: a dozen gathers, scatters and temporaries per hit, most
of the bounce's trace + shade time in the profile. :func:`shade_set_hits`
runs the same arithmetic in compiled loops (hit_jit.py: texel indices in
strict float32, then one shading loop per band count that prefetches the rows
later hits read), several times faster (docs/benchmarks.md has the profiles).

Same results as the numpy path to float32 rounding: the same texel per hit
(identical float32 texture coordinates), the 25-term sums in another order.
tests/test_bounce_exit.py checks both paths against a float64 per-hit
reference and against each other.

numba is optional (core/base/jit.py): without it :func:`usable` is False and the
bake shades with numpy, the arithmetic of the bakes before the kernel
(their bytes exactly, under the same settings and storage). The first call in a process
loads the kernel from numba's cache (~0.45 s with numba's import, on a
helper thread at the bake's start: :func:`warm_up`) or compiles it (1.5 s,
once per install; ``cache=True`` writes beside hit_jit.py, or to the user's
cache directory when that is read-only).
"""

from __future__ import annotations

import inspect
import math
import os
import sys
import threading

import numpy as np

from ...base import jit
from ...sh.basis import sectoral_constants


def recurrence_constants(bands: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """float32 constants of sh.basis.basis_unchecked's recurrence for ``bands``:
    sect (n,) Pbar_m^m; a, b (n, n) the three-term factors at [m, l] (0 where unused)."""
    n = bands
    sect = sectoral_constants(n)
    a = np.zeros((n, n))
    b = np.zeros((n, n))
    for m in range(n):
        for l in range(m + 1, n):
            if l == m + 1:
                a[m, l] = math.sqrt(2 * m + 3)
            else:
                a[m, l] = math.sqrt((4.0 * l * l - 1.0) / (l * l - m * m))
                b[m, l] = math.sqrt(((l - 1.0) ** 2 - m * m) / (4.0 * (l - 1.0) ** 2 - 1.0))
    return sect.astype(np.float32), a.astype(np.float32), b.astype(np.float32)


def available() -> bool:
    """numba is installed and not switched off (core/base/jit.py)."""
    return jit.available()


_JIT = "prtt_addon.core.bake.estimators.hit_jit"
_ISLANDS = "prtt_addon.core.texels.islands_jit"
_probe_lock = threading.Lock()
_probed: dict = {}


def _jit():
    return jit.load(_JIT)


def _probe(mod, kind: str, bands: int, transfer_bands: int = 0) -> None:
    """Call the loops of ``kind`` ("baked", "relight" or "columns") on no hits, with the
    dtypes of a real call: numba compiles (or loads from its cache) the very
    overloads a bake uses (for "relight": both loops of glossy ``bands``
    with a transfer of ``transfer_bands``)."""
    i64, f32 = np.zeros(0, np.int64), np.zeros(0, np.float32)
    rows, f2 = np.zeros(1, np.int32), np.zeros((1, 3), np.float32)
    mod.texel_indices(i64, i64, f32, f32, np.zeros((1, 6), np.float32), 1, 1, True, np.zeros(1, bool), 1, 1)
    if kind == "relight":
        K, kg = max(transfer_bands, bands) ** 2, bands * bands
        loops = {mod.relight_project, mod.relight_for(transfer_bands, bands, True)}
        for loop in loops:
            loop(i64, i64, rows, rows, i64, i64, f2, np.zeros((1, 1, K), np.float32), f2,
                 np.zeros((1, 1, kg, kg), np.float32), f2, f2, bands, *recurrence_constants(bands), 1, f32,
                 np.zeros((1, kg), np.float32), np.zeros((1, 3, K), np.float32), np.zeros((1, 1, kg, kg), np.float32))
    elif kind == "columns":
        mod.put_columns(f2, i64, np.zeros((3, 0), np.float32))
        mod.put_texel_rows(f2, i64, np.zeros((0, 3), np.float32))
    else:
        mod.for_bands(bands)(i64, i64, rows, rows, i64, i64, f2, f2, f2, bands, *recurrence_constants(bands), f2)


def usable(kind: str, bands: int, transfer_bands: int = 0) -> bool:
    """The compiled loops of ``kind`` for ``bands`` bands (for "relight" the
    glossy part's, with a transfer of ``transfer_bands``) load and run (once
    per process, cached): False when numba is off or missing, fails to
    import, or fails to compile them (then recorded in core/base/jit.failures and
    never tried again: the bake shades with numpy)."""
    key = (kind, bands, transfer_bands)
    if key in _probed:
        return _probed[key]
    with _probe_lock:
        if key not in _probed:
            mod = _jit()
            ok = mod is not None
            if ok:
                try:
                    _probe(mod, kind, bands, transfer_bands)
                except Exception as exc:      # noqa: BLE001 - a numba/llvmlite this code was not written for
                    jit.broken(_JIT, exc)
                    ok = False
            _probed[key] = ok
    return _probed[key]


def _entry_points(mod, kind: str, bands: int, transfer_bands: int = 0) -> list:
    """The dispatchers :func:`_probe` calls for ``kind`` (the loops a bake enters)."""
    if kind == "relight":
        loops = [mod.relight_project, mod.relight_for(transfer_bands, bands, True)]
    elif kind == "columns":
        loops = [mod.put_columns, mod.put_texel_rows]
    else:
        loops = [mod.for_bands(bands)]
    return [mod.texel_indices, *loops]


def _cached(dispatcher) -> bool:
    """numba's cache holds compiled code of ``dispatcher`` for its current
    source: the index file numba names ``<file>.<qualname>-<line>.pyXY.nbi``
    in the dispatcher's cache folder (``stats.cache_path``) exists and is
    newer than the source file. numba also checks the source's exact stamp
    and its own version: an edit that keeps the line, or a numba upgrade,
    reads as cached here while numba compiles (the estimate is then ~60 MB
    low, once). False when anything is unlike numba 0.5x-0.6x, so an unknown
    numba counts as compiling."""
    try:
        func = dispatcher.py_func
        source = inspect.getfile(func)
        name = (f"{os.path.splitext(os.path.basename(source))[0]}.{func.__qualname__}"
                f"-{func.__code__.co_firstlineno}.py{sys.version_info[0]}{sys.version_info[1]}"
                f"{getattr(sys, 'abiflags', '')}.nbi")
        index = os.path.join(dispatcher.stats.cache_path, name)
        return os.path.getmtime(index) >= os.path.getmtime(source)
    except (AttributeError, OSError, TypeError):
        return False


def compile_pending(bands: int, relightable: bool = False, glossy_bands: int = 3) -> bool:
    """:func:`warm_up` will compile kernels rather than load them from numba's
    cache (a first bake after an install or an update of PRTT): the compiler
    keeps ~60 MB resident for the rest of the process, which the memory
    estimate adds (pipeline/memory_plan.JIT_COMPILE). False without numba."""
    if not available():
        return False
    mod, islands = _jit(), jit.load(_ISLANDS)
    if mod is None:
        return False
    kind = ("relight", glossy_bands, bands) if relightable else ("baked", bands)
    entries = _entry_points(mod, *kind) + _entry_points(mod, "columns", 0)
    if islands is not None:
        entries.append(islands.island_labels)
    return not all(_cached(d) for d in entries)


def warm_up(bands: int, relightable: bool = False, glossy_bands: int = 3) -> threading.Thread | None:
    """Import numba and load (or compile) the kernels on a daemon thread (the
    hit shading's for the bake's mode, and the UV island labels' the bounce
    grid is chosen with), so that the bounce stage does not wait for them
    (loading from numba's cache takes a fraction of a first compile). Called
    at the start of a bake with bounces; None when numba is not there. Failures are recorded, not raised (:func:`usable`)."""
    if not available():
        return None

    def load():
        usable("relight", glossy_bands, bands) if relightable else usable("baked", bands)
        usable("columns", 0)
        islands = jit.load(_ISLANDS)
        if islands is not None:
            try:
                islands.island_labels(np.zeros((1, 1), bool))
            except Exception as exc:          # noqa: BLE001 - see usable
                jit.broken(_ISLANDS, exc)

    t = threading.Thread(target=load, name="prtt-hit-kernel", daemon=True)
    t.start()
    return t


_NO_GLOSSY = np.zeros((1, 1), np.float32)


def shade_set_hits(sel: np.ndarray, prim: np.ndarray, u: np.ndarray, v: np.ndarray, ray_of: np.ndarray,
                   D: np.ndarray, frames: np.ndarray, glossy_tri: np.ndarray, ex, bands: int, consts,
                   out: np.ndarray) -> None:
    """Write the exit radiance of one set's textures ``ex`` (bounce.ExitTextures)
    at its hits ``sel`` (indices into the chunk's hits) into ``out`` (rays, 3)
    float32, row ray_of[i] for hit i. prim (h,) int64 triangles, u, v (h,)
    float32 barycentrics, ray_of (h,) int64, D (rays, 3) float32 ray
    directions, frames (T, 6) float32 (bounce.uv_frames), glossy_tri (T,)
    bool, consts = recurrence_constants(bands). Only when
    usable("baked", bands)."""
    has = ex.glossy is not None
    tex, gtex, g = hit_texels(sel, prim, u, v, frames, glossy_tri, ex.diffuse_grid, ex.glossy_grid if has else None)
    _jit().for_bands(bands)(tex, gtex, ex.diffuse_grid.row_of, g.row_of, sel, ray_of, D, ex.diffuse,
                            ex.glossy if has else _NO_GLOSSY, bands, *consts, out)


def numba_version() -> str | None:
    """numba's version when the hit shading's compiled loops load, else None."""
    return jit.version(_JIT)


def relight_loop(bands: int, glossy_bands: int, shared_exit: bool):
    """The relightable loop (hit_jit.relight_for) for exit forms shared
    between the colours or not (only when usable("relight", glossy_bands, bands))."""
    return _jit().relight_for(bands, glossy_bands, shared_exit)


def hit_texels(sel, prim, u, v, frames, glossy_tri, diffuse_grid, glossy_grid):
    """(tex, gtex, grid): the hits ``sel``'s flat texels on ``diffuse_grid`` and,
    on triangles with a lobe, on ``glossy_grid`` (-1 elsewhere; None: the set
    has no glossy rows), and the grid gtex indexes (hit_jit.texel_indices).
    For the compiled loops of both bounce modes."""
    g = glossy_grid if glossy_grid is not None else diffuse_grid
    tex, gtex = _jit().texel_indices(sel, prim, u, v, frames, diffuse_grid.width, diffuse_grid.height,
                                     glossy_grid is not None, glossy_tri, g.width, g.height)
    return tex, gtex, g


def store_columns(dst: np.ndarray, cols: np.ndarray, src: np.ndarray) -> None:
    """dst[:, cols] = src: a chunk's result (C, n) into its texel columns of a
    texture (C, H*W), as numpy's assignment would (the same values; the
    bakes' stores call it from their threads for disjoint columns). Compiled
    (hit_jit.put_columns, put_texel_rows) for float32 into C-contiguous
    float32 rows, src either C-contiguous or the transpose of a C-contiguous
    (n, C) array (the projections' results); numpy otherwise."""
    fast = (dst.dtype == np.float32 and src.dtype == np.float32 and dst.flags.c_contiguous
            and src.shape == (dst.shape[0], cols.size) and cols.dtype == np.int64)
    if fast and available() and usable("columns", 0):
        mod = _jit()
        if src.flags.c_contiguous:
            mod.put_columns(dst, cols, src)
            return
        if src.T.flags.c_contiguous:
            mod.put_texel_rows(dst, cols, src.T)
            return
    dst[:, cols] = src
