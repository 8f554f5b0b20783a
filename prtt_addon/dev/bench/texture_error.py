"""Error measures the sweeps share: transfer textures of a bake folder and
their relative error against a reference."""
from __future__ import annotations

import os

import numpy as np

from ...core.io.exr_io import read_sh_exr


def load_set_textures(out_dir: str, sc) -> dict:
    """Set name -> (H, W, K) transfer texture of the bake in ``out_dir``."""
    return {n: read_sh_exr(os.path.join(out_dir, f"{n}.transfer.exr"))[0] for n in sc.set_names}


def texel_error(tex: dict, ref: dict) -> float:
    """Relative RMSE over covered texels: ||T - T_ref|| / ||T_ref|| (first K coefficients)."""
    num = den = 0.0
    for n, t in tex.items():
        r = ref[n][..., :t.shape[-1]].astype(np.float64)
        covered = np.any(r != 0, axis=-1)
        num += float(((t[covered] - r[covered]) ** 2).sum())
        den += float((r[covered] ** 2).sum())
    return float(np.sqrt(num / den))


def image_error(img: np.ndarray, ref: np.ndarray) -> float:
    """Relative RMSE over pixels covered in both: RMSE of RGB over the mean of
    ``ref`` (H, W, 4) renders, alpha > 0.5 as covered."""
    m = (img[..., 3] > 0.5) & (ref[..., 3] > 0.5)
    a, b = img[..., :3][m].astype(np.float64), ref[..., :3][m].astype(np.float64)
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.mean(b))
