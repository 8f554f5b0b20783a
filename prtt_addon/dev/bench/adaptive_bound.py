"""The ``adaptive_bounce`` part of ``bench sweep``: what an adaptive bounce ray count
could save at most, measured before building one (#15 item 3).

An adaptive count spends rays where a texel's estimate is noisy. Its best
case is the oracle (Neyman) allocation: rays per texel proportional to the
standard deviation s_i of one ray's contribution, known exactly and for free.
For T texels and N rays in all, the summed squared error (what the bounce
curve's relative RMSE squares) is

    uniform   sum_i s_i^2 / (N / T)        oracle   (sum_i s_i)^2 / N

so at equal error the oracle needs ``gain = T sum s_i^2 / (sum s_i)^2`` times
fewer rays. A real scheme pays a pilot pass and estimates s_i from a few
rays, so it saves less; when the oracle's gain is under the rule the
denoisers were held to (the same error with at most half the rays), no
adaptive count can pass it.

s_i is measured from two bakes of the default settings (tuning auto, so the
bounce grid and ray count a user gets) that differ only in their seed:
Var(one bake's texel) ~= |a_i - b_i|^2 / 2, summed over the 75 RGB SH
coefficients. The difference also holds the transfer's own noise as the
bounce reads it (~3 % per coefficient at 256 rays, averaged over a texel's
hits), which makes the s_i slightly more even; the per-texel estimate's own
noise makes them less even, by more at these ray counts, so the gain reads
high rather than low: a bound in that sense, not a guarantee.
"""
from __future__ import annotations

import os
import shutil

import numpy as np

from ...core.bake.pipeline.context import BakeSettings
from ...core.bake.pipeline.runner import bake_scene
from ...core.texels.gbuffer import build_gbuffer
from . import scene_library
from .denoise_sweep import bounce_planes

SEEDS = (11, 29)


def oracle_gain(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> dict:
    """The oracle allocation's ray saving from two independent estimates
    ``a``, ``b`` (C, H, W) planes of the same texels, over the texels of
    ``mask`` (H, W) where they differ (equal ones traced no rays). Returns
    gain, the share of the summed variance in the noisiest 10 % of texels,
    and the texel count."""
    diff = a[:, mask].astype(np.float64) - b[:, mask]
    var = (diff ** 2).sum(axis=0) / 2.0                               # one bake's variance per texel
    # Texels the bake skips (provably open, or seeing nothing) give both bakes
    # the same value: no rays to move, so they are not in T.
    var = var[var > 0]
    s = np.sqrt(var)
    T = var.size
    gain = float(T * var.sum() / s.sum() ** 2) if s.sum() > 0 else 1.0
    top = np.sort(var)[::-1][: max(1, T // 10)].sum() / max(var.sum(), 1e-300)
    return dict(gain=gain, top10_share=float(top), texels=int(T))


def sweep_adaptive_bound(cfg, light, tmp: str) -> list:
    """Rows: per bounce ray count, the oracle gain (fewer rays at equal error)."""
    res = 64 if cfg.quick else cfg.sweep_res
    rays_list = (16,) if cfg.quick else (32, 64, 128)
    sc = scene_library.room_scene(res, atlas=True, materials=True)
    name = sc.set_names[0]
    rows = []
    for rays in rays_list:
        est = []
        for seed in SEEDS:
            d = os.path.join(tmp, f"adaptive-{rays}-{seed}")
            m = bake_scene(sc, d, BakeSettings(rays=256, bounces=1, bounce_rays=rays, half=False, seed=seed,
                                               bounce_mode="baked", bounce_denoise="none", tuning="auto"), light=light,
                           skip_if_unchanged=False)
            est.append(bounce_planes(os.path.join(d, f"{name}.bounce1.exr")))
            shutil.rmtree(d, ignore_errors=True)
        H, W = est[0].shape[1:]
        mask = build_gbuffer(sc, 0, resolution=(W, H)).mask()
        grid = m["bounce"]["sets"][0].get("grid", {})
        r = dict(bounce_rays=rays, texel_rays=grid.get("rays", rays), grid=f"{W}x{H}", **oracle_gain(*est, mask))
        print(f"  {rays:4d} bounce rays ({r['texel_rays']} per texel on the {r['grid']} grid): oracle allocation "
              f"needs {r['gain']:.2f}x fewer rays at equal error; the noisiest 10 % of texels hold "
              f"{100 * r['top10_share']:.0f} % of the variance", flush=True)
        rows.append(r)
    return rows
