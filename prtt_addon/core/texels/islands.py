"""UV islands on a texel grid: which covered texels belong together, and
whether a coarser grid over the same layout keeps them apart.

A bounce texture baked at 1/f of the transfer resolution is read by the
renderer's bilinear filter and filled into its gutters by dilation. Neither
mixes two islands if no texel of the coarse grid has covered texels of two
islands within one texel of it (its 3 x 3 neighbourhood): the four taps of a
lookup inside an island, and the first dilation ring they may reach, then
come from that island alone (:func:`coarse_grid_conflicts`).
"""
from __future__ import annotations

import numpy as np

from ..base import jit

_OFFSETS8 = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]


def island_labels(mask: np.ndarray) -> np.ndarray:
    """(H, W) int64: the label of each covered texel's 8-connected island (the
    smallest flat index in it), -1 for empty texels.

    Min-label propagation with pointer jumping: each round every texel takes
    the smallest label among its covered neighbours, then follows labels to
    their own label; rounds repeat until nothing changes (a few dozen for
    islands hundreds of texels long). With numba (core/base/jit.py) a compiled
    union-find gives the same labels (islands_jit)."""
    name = "prtt_addon.core.texels.islands_jit"       # by name: numba is optional (core/base/jit.py)
    fast = jit.load(name)
    if fast is not None:
        try:
            return fast.island_labels(np.ascontiguousarray(mask, dtype=bool))
        except Exception as exc:          # noqa: BLE001 - a numba that imports but cannot compile it
            jit.broken(name, exc)
    return island_labels_numpy(mask)


def island_labels_numpy(mask: np.ndarray) -> np.ndarray:
    """:func:`island_labels` without numba."""
    H, W = mask.shape
    flat = np.where(mask.reshape(-1), np.arange(H * W), -1).reshape(H, W)
    big = np.int64(H * W)
    lab = np.where(flat >= 0, flat, big)
    while True:
        pad = np.pad(lab, 1, constant_values=big)
        new = lab.copy()
        for dy, dx in _OFFSETS8:
            np.minimum(new, pad[1 + dy:1 + dy + H, 1 + dx:1 + dx + W], out=new)
        new = np.where(mask, new, big)
        # Pointer jumping: a label is a texel index; follow it to that texel's label.
        nf = new.reshape(-1)
        covered = nf < big
        while True:
            nxt = nf.copy()
            nxt[covered] = nf[nf[covered]]
            if np.array_equal(nxt, nf):
                break
            nf = nxt
        new = nf.reshape(H, W)
        if np.array_equal(new, lab):
            break
        lab = new
    return np.where(mask, lab, -1)


def block_labels(labels: np.ndarray, f: int) -> tuple[np.ndarray, np.ndarray]:
    """Island labels (H, W) (-1 empty) seen by a grid f times coarser per side:
    (lo, hi) (H/f, W/f) int64, the smallest and largest island label among the
    covered texels of each f x f block (lo = big, hi = -1 for an empty block).
    H and W must be multiples of f."""
    H, W = labels.shape
    if H % f or W % f:
        raise ValueError(f"a {W}x{H} grid is not a multiple of {f} per side")
    big = np.int64(H * W)
    blocks = labels.reshape(H // f, f, W // f, f)
    lo = np.where(blocks >= 0, blocks, big).min(axis=(1, 3))
    hi = blocks.max(axis=(1, 3))
    return lo, hi


def coarse_grid_conflicts(mask: np.ndarray, f: int, labels: np.ndarray | None = None) -> int:
    """Texels of the grid f times coarser than ``mask`` (H, W) bool whose 3 x 3
    neighbourhood holds covered texels of two different islands (8-connected
    islands of ``mask``; ``labels`` = island_labels(mask) if already known).
    0 means a texture on the coarse grid, dilated and read bilinearly, never
    mixes islands. H and W must be multiples of f."""
    if labels is None:
        labels = island_labels(mask)
    lo, hi = block_labels(labels, f)
    big = np.int64(labels.size)
    h, w = lo.shape
    lo_p = np.pad(lo, 1, constant_values=big)
    hi_p = np.pad(hi, 1, constant_values=-1)
    nlo = lo.copy()
    nhi = hi.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            np.minimum(nlo, lo_p[1 + dy:1 + dy + h, 1 + dx:1 + dx + w], out=nlo)
            np.maximum(nhi, hi_p[1 + dy:1 + dy + h, 1 + dx:1 + dx + w], out=nhi)
    return int(np.count_nonzero((nhi >= 0) & (nlo != nhi)))
