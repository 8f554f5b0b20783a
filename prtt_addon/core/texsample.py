"""Bilinear texture lookups with the GPU's conventions.

A W x H texture's texel (i, j) (j from the bottom, like UVs) has its centre at
uv = ((i + 0.5) / W, (j + 0.5) / H); lookups between centres blend the four
nearest texels; outside the centres' range the edge texels extend (clamp to
edge). This is what the viewport shader's sampler does, so the bounce bake and
the shader tests read baked textures exactly as the renderer will.
"""
from __future__ import annotations

import numpy as np


def pixel_major(tex_chw: np.ndarray) -> np.ndarray:
    """(C, H, W) -> (H * W, C) float32, rows contiguous: one gather per texel."""
    C, H, W = tex_chw.shape
    return np.ascontiguousarray(tex_chw.reshape(C, H * W).T, dtype=np.float32)


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
