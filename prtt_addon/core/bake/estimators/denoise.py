"""Denoising baked SH textures in texture space (measured in ``bench sweep --only denoise``).

Two filters, both optional and off by default (docs/benchmarks.md has the
curves that decided it):

* :func:`edge_aware`: a joint (cross) bilateral filter guided by the
  G-buffer: within a (2r+1)^2 window, a texel's neighbours are weighted by
  texel distance, world-space distance and normal agreement, and only texels
  of the **same UV island** (:func:`core.texels.islands.island_labels`) ever mix. Linear in the
  coefficients, so it is applied to every SH channel alike.
* :func:`oidn_sh`: Intel Open Image Denoise (``pyoidn``, CPU) with the
  RTLightmap filter, on SH normalised the way production lightmappers do:
  the DC terms (RGB) as an HDR lightmap, every higher coefficient divided by
  sqrt(2l + 1) times its colour's DC term (in [-1, 1] for a non-negative
  function) as a *directional* lightmap, then restored. OIDN sees an image:
  it can blend across the empty gutters between islands (within the
  dilation it does not matter; further it is measured, not prevented).

Textures are channel planes (C, H, W) float32, row 0 = bottom, as the bake
keeps them; ``mask`` (H, W) bool marks covered texels. Empty texels are
returned unchanged (dilation refills them).
"""
from __future__ import annotations

import math

import numpy as np

from ...settings_schema import DENOISE_FILTERS
from ...sh.basis import band_of_coeffs
from ...texels.islands import island_labels

#: The ``bounce_denoise`` setting's values (settings_schema declares their help).
FILTERS = DENOISE_FILTERS
#: "auto" filters bounce levels traced with fewer rays than this with the
#: edge-aware filter: measured on the room (docs/benchmarks.md), the filter
#: reaches 64 raw rays' error with 24 rays and is better up to ~128 rays; from
#: there on its bias (8 % of the converged bounce, contact light blurred over
#: a texel) is more than the noise it removes. It is not the default: its
#: cost (~0.5 s at 512², ~10 s at 1024²) buys less than the same time in rays.
AUTO_MAX_RAYS = 128


def resolve_filter(filt: str, bounce_rays: int) -> str:
    """The filter a bounce level gets: ``filt``, or for "auto" edge-aware below
    :data:`AUTO_MAX_RAYS` rays and none from there on."""
    if filt == "auto":
        return "edge-aware" if bounce_rays < AUTO_MAX_RAYS else "none"
    return filt


def edge_aware(planes: np.ndarray, mask: np.ndarray, position: np.ndarray, normal: np.ndarray, *,
               radius: int = 1, sigma_texels: float = 1.0, sigma_world: float | None = None,
               normal_power: float = 16.0, labels: np.ndarray | None = None) -> np.ndarray:
    """Joint bilateral filter of ``planes`` (C, H, W) within UV islands.

    position, normal : (H, W, 3) world position and unit shading normal of
        covered texels (the G-buffer, scattered to the texture).
    sigma_world : world distance scale; default 2x the median distance between
        horizontally adjacent covered texels (a texel's footprint).
    Weight of neighbour q for texel p (same island only):
        exp(-|q - p|^2 / 2 sigma_texels^2) exp(-|x_q - x_p|^2 / 2 sigma_world^2) max(0, n_p.n_q)^normal_power.
    Returns new planes (float32); empty texels are copied unchanged.
    """
    C, H, W = planes.shape
    if labels is None:
        labels = island_labels(mask)
    pos = np.asarray(position, np.float64)
    nrm = np.asarray(normal, np.float64)
    if sigma_world is None:
        both = mask[:, 1:] & mask[:, :-1]
        d = np.linalg.norm(pos[:, 1:] - pos[:, :-1], axis=-1)[both]
        sigma_world = 2.0 * float(np.median(d)) if d.size else 1.0
        sigma_world = max(sigma_world, 1e-12)
    # Only covered texels are filtered: gather them once as rows (N, C) and
    # walk the window offsets over that list (float32 sums: the weights are
    # positive and sum to at most (2r+1)^2, far from float32's limits).
    ys, xs = np.nonzero(mask)
    N = ys.size
    vals = np.ascontiguousarray(planes[:, ys, xs].T, dtype=np.float32)       # (N, C)
    index = np.full((H, W), -1, np.int64)
    index[ys, xs] = np.arange(N)
    lab, p0, n0 = labels[ys, xs], pos[ys, xs], nrm[ys, xs]
    r = int(radius)
    offsets = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
    # Each neighbour's index and weight (0 where it is outside, empty, or of
    # another island), then blocks of texels so a block's rows stay in cache
    # while all offsets add into it.
    nb = np.zeros((len(offsets), N), np.int64)
    wt = np.zeros((len(offsets), N), np.float32)
    for o, (dy, dx) in enumerate(offsets):
        y2, x2 = ys + dy, xs + dx
        inside = np.flatnonzero((y2 >= 0) & (y2 < H) & (x2 >= 0) & (x2 < W))
        j = index[y2[inside], x2[inside]]
        keep = j >= 0
        inside, j = inside[keep], j[keep]
        keep = lab[j] == lab[inside]
        ok, q = inside[keep], j[keep]
        dw = np.sum((p0[q] - p0[ok]) ** 2, axis=1)
        cos = np.clip(np.sum(n0[q] * n0[ok], axis=1), 0.0, 1.0)
        nb[o, ok] = q
        wt[o, ok] = (math.exp(-(dy * dy + dx * dx) / (2.0 * sigma_texels ** 2))
                     * np.exp(-dw / (2.0 * sigma_world ** 2)) * cos ** normal_power)
    wsum = wt.sum(axis=0, dtype=np.float64)
    acc = np.empty((N, C), np.float32)
    block = 1 << 14
    for a in range(0, N, block):
        b = min(a + block, N)
        blk = acc[a:b]
        blk.fill(0.0)
        for o in range(len(offsets)):
            tmp = np.take(vals, nb[o, a:b], axis=0)
            tmp *= wt[o, a:b, None]
            blk += tmp
    out = planes.astype(np.float32, copy=True)
    good = wsum > 0
    out[:, ys[good], xs[good]] = (acc[good] / wsum[good, None].astype(np.float32)).T
    return out


def denoise_bounce(planes: np.ndarray, gb, filt: str, bands: int) -> np.ndarray:
    """One bounce level's RGB SH planes (3K, H, W), covered texels from the
    G-buffer ``gb`` (texel, position, normal), through filter ``filt`` (already
    resolved: not "auto")."""
    if filt == "none":
        return planes
    H, W = gb.height, gb.width
    mask = gb.mask()
    if filt == "oidn":
        return oidn_sh(planes, mask, bands)
    if filt != "edge-aware":
        raise ValueError(f"unknown denoiser {filt!r}; use one of {', '.join(FILTERS)}")
    pos = np.zeros((H * W, 3))
    nrm = np.zeros((H * W, 3))
    pos[gb.texel], nrm[gb.texel] = gb.position, gb.normal
    return edge_aware(planes, mask, pos.reshape(H, W, 3), nrm.reshape(H, W, 3))


def oidn_available() -> bool:
    try:
        import pyoidn  # noqa: F401
    except ImportError:
        return False
    return True


def _oidn_run(img: np.ndarray, directional: bool) -> np.ndarray:
    import pyoidn
    dev = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU)
    dev.commit()
    flt = pyoidn.Filter(dev, pyoidn.OIDN_FILTER_TYPE_RT_LIGHTMAP)
    src = np.ascontiguousarray(img, np.float32)
    out = np.empty_like(src)
    H, W, _ = src.shape
    flt.set_image(pyoidn.OIDN_IMAGE_COLOR, src, pyoidn.OIDN_FORMAT_FLOAT3, W, H)
    flt.set_image(pyoidn.OIDN_IMAGE_OUTPUT, out, pyoidn.OIDN_FORMAT_FLOAT3, W, H)
    if directional:
        flt.set_bool("directional", True)
    flt.commit()
    flt.execute()
    flt.release()
    dev.release()
    return out


def oidn_sh(planes: np.ndarray, mask: np.ndarray, bands: int) -> np.ndarray:
    """OIDN RTLightmap on SH planes: (3K, H, W) RGB (R coefficients, then G,
    then B) or (K, H, W) scalar (a transfer texture).

    Raises ImportError with a clear message when pyoidn is not installed."""
    try:
        import pyoidn  # noqa: F401
    except ImportError as e:
        raise ImportError("OIDN denoising needs the optional package pyoidn (pip install pyoidn)") from e
    K = bands * bands
    C, H, W = planes.shape
    if C not in (K, 3 * K):
        raise ValueError(f"expected {K} or {3 * K} SH planes for {bands} bands, got {C}")
    rgb = C == 3 * K
    sh = planes.reshape(C // K, K, H, W).astype(np.float32)               # (colours, K, H, W)
    dc = np.maximum(sh[:, 0], 0.0)
    dc3 = dc if rgb else np.repeat(dc, 3, axis=0)
    dc_d = np.maximum(_oidn_run(dc3.transpose(1, 2, 0), False).transpose(2, 0, 1), 0.0)
    if not rgb:
        dc_d = dc_d.mean(axis=0, keepdims=True)
    out = np.empty_like(sh)
    out[:, 0] = dc_d
    scale = np.sqrt(2.0 * band_of_coeffs(bands) + 1.0)
    safe = np.where(dc > 1e-12, dc, 1.0)
    ratio = np.where(dc[:, None] > 1e-12, sh[:, 1:] / (scale[1:, None, None] * safe[:, None]), 0.0)
    ratio = np.clip(ratio, -1.0, 1.0)                                     # (colours, K - 1, H, W)
    if rgb:
        for k in range(K - 1):
            den = _oidn_run(ratio[:, k].transpose(1, 2, 0), True).transpose(2, 0, 1)
            out[:, k + 1] = den * scale[k + 1] * dc_d
    else:
        # A scalar texture: three coefficients per directional lightmap image.
        r = ratio[0]
        for a in range(0, K - 1, 3):
            grp = np.zeros((3, H, W), np.float32)
            n = min(3, K - 1 - a)
            grp[:n] = r[a:a + n]
            den = _oidn_run(grp.transpose(1, 2, 0), True).transpose(2, 0, 1)
            out[0, a + 1:a + 1 + n] = den[:n] * scale[a + 1:a + 1 + n, None, None] * dc_d[0]
    res = out.reshape(C, H, W)
    return np.where(mask[None], res, planes).astype(np.float32)
