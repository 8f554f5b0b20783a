"""Bilinear texture lookups with the GPU's conventions.

A W x H texture's texel (i, j) (j from the bottom, like UVs) has its centre at
uv = ((i + 0.5) / W, (j + 0.5) / H); lookups between centres blend the four
nearest texels; outside the centres' range the edge texels extend (clamp to
edge). This is what the viewport shader's sampler does, so the bounce bake and
the shader tests read baked textures exactly as the renderer will.

Also the two layouts a texture has in the bake: pixel-major rows (one texel's
channels contiguous, what the kernels produce and gather) and channel planes
(C, H, W) (what dilation and the EXR writer take).
"""
from __future__ import annotations

import numpy as np

from ..base.memory import discard_pages


def pixel_major(tex_chw: np.ndarray) -> np.ndarray:
    """(C, H, W) -> (H * W, C) float32, rows contiguous: one gather per texel."""
    C, H, W = tex_chw.shape
    return np.ascontiguousarray(tex_chw.reshape(C, H * W).T, dtype=np.float32)


def planes_from_rows(texel: np.ndarray, rows: np.ndarray, n_texels: int, *,
                     executor=None, block: int = 4096, visit=None, consume: bool = False) -> np.ndarray:
    """Channel planes (C, n_texels) float32 holding ``rows`` (N, C) at ``texel``
    (N,) (strictly ascending), zero elsewhere.

    Each run of ``block`` listed texels is assembled in a small cache-resident
    buffer over the span it covers and copied out whole (a direct
    ``planes[:, texel] = rows.T`` strides across C rows megabytes apart and is
    ~4x slower). Texels between spans are never written, so the empty parts of
    a sparse atlas stay untouched zero pages. With an ``executor`` two threads
    share the spans.

    visit : called as visit(a, b) for each run of rows a..b - 1 once it is in
            the planes (from the thread that placed it): what else the caller
            reads of those rows, before ``consume`` lets them go.
    consume : ``rows`` (C-contiguous, done with) give each run's pages back to
            the OS once it is placed (base/memory.discard_pages): the rows
            and the planes are never both whole in memory. The rows read as
            zeros afterwards.
    """
    consume = consume and rows.flags.c_contiguous
    n, C = rows.shape
    if texel.shape != (n,):
        raise ValueError(f"texel must have shape ({n},), got {texel.shape}")
    planes = np.zeros((C, n_texels), np.float32)
    starts = list(range(0, n, block))

    def fill(ks):
        for a in ks:
            b = min(a + block, n)
            lo, hi = int(texel[a]), int(texel[b - 1]) + 1
            span = np.zeros((C, hi - lo), np.float32)
            span[:, texel[a:b] - lo] = rows[a:b].T
            planes[:, lo:hi] = span
            if visit is not None:
                visit(a, b)
            if consume:
                discard_pages(rows[a:b])

    if executor is not None and len(starts) > 1:
        mid = len(starts) // 2
        list(executor.map(fill, [starts[:mid], starts[mid:]]))
    else:
        fill(starts)
    return planes


def bilinear(tex_pm: np.ndarray, width: int, height: int, uv: np.ndarray) -> np.ndarray:
    """Sample a pixel-major texture (H * W, C) at uv (n, 2); returns (n, C) float32."""
    x = np.asarray(uv[:, 0], dtype=np.float64) * width - 0.5
    y = np.asarray(uv[:, 1], dtype=np.float64) * height - 0.5
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0).astype(np.float32)[:, None]
    fy = (y - y0).astype(np.float32)[:, None]
    x0 = x0.astype(np.int64)
    y0 = y0.astype(np.int64)
    xa, xb = np.clip(x0, 0, width - 1), np.clip(x0 + 1, 0, width - 1)
    ya, yb = np.clip(y0, 0, height - 1) * width, np.clip(y0 + 1, 0, height - 1) * width
    # np.take copies whole rows (several times faster than fancy indexing here);
    # the blend runs in place to keep temporaries down.
    top = np.take(tex_pm, ya + xa, axis=0)
    top *= 1 - fx
    top += np.take(tex_pm, ya + xb, axis=0) * fx
    bottom = np.take(tex_pm, yb + xa, axis=0)
    bottom *= 1 - fx
    bottom += np.take(tex_pm, yb + xb, axis=0) * fx
    top *= 1 - fy
    bottom *= fy
    top += bottom
    return top


def bilinear_repeat(img_top_first: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup with repeat wrapping, as material image textures are sampled.

    img (H, W, C) in file order (row 0 at the top); uv (N, 2), v up; returns
    (N, C). Unlike :func:`bilinear` (clamp to edge, rows bottom first), UVs
    outside 0..1 wrap around."""
    H, W = img_top_first.shape[:2]
    img = img_top_first[::-1]                  # row 0 = bottom, like v
    x = uv[:, 0] * W - 0.5
    y = uv[:, 1] * H - 0.5
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    x0w, x1w = x0 % W, (x0 + 1) % W
    y0w, y1w = y0 % H, (y0 + 1) % H
    return ((img[y0w, x0w] * (1 - fx) + img[y0w, x1w] * fx) * (1 - fy)
            + (img[y1w, x0w] * (1 - fx) + img[y1w, x1w] * fx) * fy)
