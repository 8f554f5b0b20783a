"""The ``bounce`` and ``denoise`` parts of ``bench sweep``: bounce rays against
error, raw and denoised, on the room-class scene.

One transfer bake (256 rays) is shared; bounce level 1 is baked with 16 ... 256
rays per texel and compared with a converged bounce reference (2048 rays,
cached in .cache/bench). Error: relative RMSE of the bounce texels (all 75 RGB
SH coefficients, covered texels) against the reference. Each denoiser's time
is added to the bake's: a denoiser pays when its curve reaches an error with
at most half the rays of the raw curve (the rule docs/benchmarks.md states).
"""
from __future__ import annotations

import os
import shutil
import time

import numpy as np

from ...core.bake.estimators.denoise import edge_aware, oidn_available, oidn_sh
from ...core.bake.pipeline.context import BakeSettings
from ...core.bake.pipeline.runner import bake_scene
from ...core.io.exr_io import read_sh_exr
from ...core.texels.gbuffer import build_gbuffer
from ...core.texels.islands import island_labels
from . import scene_library
from .texture_error import load_set_textures, texel_error

REF_BOUNCE_RAYS = 2048


def bounce_planes(path: str) -> np.ndarray:
    """A baked bounce texture as channel-first planes (3K, H, W) float32, row 0 at the bottom."""
    data, _ = read_sh_exr(path)                       # (H, W, 3, K), row 0 at the bottom
    H, W, _, K = data.shape
    return np.ascontiguousarray(data.transpose(2, 3, 0, 1).reshape(3 * K, H, W)).astype(np.float32)


def _guides(sc, set_index: int):
    gb = build_gbuffer(sc, set_index)
    H, W = gb.height, gb.width
    pos = np.zeros((H * W, 3))
    nrm = np.zeros((H * W, 3))
    pos[gb.texel], nrm[gb.texel] = gb.position, gb.normal
    return gb.mask(), pos.reshape(H, W, 3), nrm.reshape(H, W, 3)


def _error(planes: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> float:
    a, b = planes[:, mask].astype(np.float64), ref[:, mask].astype(np.float64)
    return float(np.sqrt(((a - b) ** 2).sum() / (b ** 2).sum()))


def sweep_bounce_denoise(cfg, light, tmp: str, *, with_denoise: bool = True) -> list:
    res = 64 if cfg.quick else cfg.sweep_res
    rays_list = (8, 32) if cfg.quick else (16, 32, 64, 128, 256)
    ref_rays = 128 if cfg.quick else REF_BOUNCE_RAYS
    sc = scene_library.room_scene(res, atlas=True, materials=True)
    name = sc.set_names[0]
    work = os.path.join(tmp, "bounce")
    bake_scene(sc, work, BakeSettings(rays=256, bounces=0, half=False), light=light)
    cache = os.path.join(scene_library.ROOT, ".cache", "bench", f"bounce_ref_{res}_{ref_rays}.npy")
    if os.path.isfile(cache) and not cfg.quick:
        ref = np.load(cache)
    else:
        print(f"  reference bounce ({ref_rays} rays per texel) ...", flush=True)
        bake_scene(sc, work, BakeSettings(rays=256, bounces=1, bounce_mode="baked", bounce_rays=ref_rays, half=False,
                                          bounce_denoise="none", tuning="fixed"), light=light)
        ref = bounce_planes(os.path.join(work, f"{name}.bounce1.exr"))
        if not cfg.quick:
            os.makedirs(os.path.dirname(cache), exist_ok=True)
            np.save(cache, ref)
    mask, pos, nrm = _guides(sc, 0)
    labels = island_labels(mask)
    oidn = with_denoise and oidn_available()
    rows = []
    for rays in rays_list:
        t = time.perf_counter()
        # The full grid: the denoisers are measured on the transfer's texels (bench auto has the coarse grid).
        m = bake_scene(sc, work, BakeSettings(rays=256, bounces=1, bounce_mode="baked", bounce_rays=rays, half=False,
                                               bounce_denoise="none", tuning="fixed"), light=light)
        bake_s = time.perf_counter() - t
        assert m["transfer_reused"]
        raw = bounce_planes(os.path.join(work, f"{name}.bounce1.exr"))
        rows.append(dict(bounce_rays=rays, filter="none", bake_s=bake_s, denoise_s=0.0, total_s=bake_s,
                         error=_error(raw, ref, mask)))
        if with_denoise:
            t = time.perf_counter()
            den = edge_aware(raw, mask, pos, nrm, labels=labels)
            s = time.perf_counter() - t
            rows.append(dict(bounce_rays=rays, filter="edge-aware", bake_s=bake_s, denoise_s=s,
                             total_s=bake_s + s, error=_error(den, ref, mask)))
        if oidn:
            t = time.perf_counter()
            den = oidn_sh(raw, mask, 5)
            s = time.perf_counter() - t
            rows.append(dict(bounce_rays=rays, filter="oidn", bake_s=bake_s, denoise_s=s,
                             total_s=bake_s + s, error=_error(den, ref, mask)))
        for r in rows[-3:]:
            if r["bounce_rays"] == rays:
                print(f"  {rays:5d} rays {r['filter']:>10s}: {r['total_s']:7.2f} s, error {100 * r['error']:.2f} %",
                      flush=True)
    shutil.rmtree(work, ignore_errors=True)
    return rows


def rays_for_error(rows: list, filt: str, error: float, rays_key: str = "bounce_rays") -> float | None:
    """Rays the ``filt`` curve needs to reach ``error`` (log-linear
    interpolation between measured points; None when it never does)."""
    pts = sorted((r[rays_key], r["error"]) for r in rows if r["filter"] == filt)
    for (r0, e0), (r1, e1) in zip(pts, pts[1:]):
        if e0 >= error >= e1 and e0 != e1:
            f = (np.log(e0) - np.log(error)) / (np.log(e0) - np.log(e1))
            return float(np.exp(np.log(r0) + f * (np.log(r1) - np.log(r0))))
    if pts and pts[0][1] <= error:
        return float(pts[0][0])
    return None


def print_rays_needed(rows: list, rays_key: str, raw_rays: int, what: str) -> None:
    """Per denoiser: the rays it needs to reach the raw curve's error at
    ``raw_rays`` (or the largest measured count below it), against half of them."""
    base = max(r[rays_key] for r in rows if r[rays_key] <= raw_rays)
    raw = next(r["error"] for r in rows if r["filter"] == "none" and r[rays_key] == base)
    for f in sorted({r["filter"] for r in rows} - {"none"}):
        need = rays_for_error(rows, f, raw, rays_key)
        print(f"  {f}: reaches the raw {base}-ray {what} error ({100 * raw:.2f} %) with "
              f"{'never' if need is None else f'{need:.0f}'} rays (rays criterion: <= {base // 2})")

#: Rays of the transfer denoise part's reference (default sampler and estimator,
#: its own seed): its noise, ~0.5 % of the coefficients, is far below the
#: 32 ... 512-ray errors compared against it.
REF_TRANSFER_RAYS = 8192


def sweep_transfer_denoise(cfg, sc, tmp: str) -> list:
    """Transfer textures (5 bands) at 32 ... 512 rays, raw and denoised, against
    a converged transfer (texel error; contact shadows are where a filter that
    blurs shows up in it)."""
    rays_list = (16, 64) if cfg.quick else (32, 64, 128, 256, 512)
    ref_rays = 1024 if cfg.quick else REF_TRANSFER_RAYS
    ref_dir = os.path.join(scene_library.CACHE, f"denoise-ref-{cfg.sweep_res}-{ref_rays}-{scene_library.layout_code()}")
    if not os.path.isfile(os.path.join(ref_dir, "manifest.json")):
        print(f"  transfer reference ({ref_rays} rays per texel, cached) ...", flush=True)
        bake_scene(sc, ref_dir, BakeSettings(rays=ref_rays, bands=5, half=False, bounces=0, seed=777),
                   skip_if_unchanged=False)
    ref = load_set_textures(ref_dir, sc)
    guides = {}
    for s, name in enumerate(sc.set_names):
        mask, pos, nrm = _guides(sc, s)
        guides[name] = (mask, pos, nrm, island_labels(mask))
    oidn = oidn_available()
    rows = []
    for rays in rays_list:
        d = os.path.join(tmp, f"tdn{rays}")
        t = time.perf_counter()
        bake_scene(sc, d, BakeSettings(rays=rays, bands=5, half=False, bounces=0), skip_if_unchanged=False)
        bake_s = time.perf_counter() - t
        raw = load_set_textures(d, sc)                    # name -> (H, W, K)
        variants = {"none": (raw, 0.0)}
        for filt in ("edge-aware", "oidn") if oidn else ("edge-aware",):
            t = time.perf_counter()
            out = {}
            for name, tex in raw.items():
                mask, pos, nrm, labels = guides[name]
                planes = np.ascontiguousarray(tex.transpose(2, 0, 1))
                den = (edge_aware(planes, mask, pos, nrm, labels=labels) if filt == "edge-aware"
                       else oidn_sh(planes, mask, 5))
                out[name] = den.transpose(1, 2, 0)
            variants[filt] = (out, time.perf_counter() - t)
        for filt, (tex, s) in variants.items():
            err = texel_error(tex, ref)
            rows.append(dict(rays=rays, filter=filt, bake_s=bake_s, denoise_s=s, total_s=bake_s + s, error=err))
            print(f"  transfer {rays:5d} rays {filt:>10s}: {bake_s + s:7.2f} s, error {100 * err:.2f} %", flush=True)
        shutil.rmtree(d, ignore_errors=True)
    return rows
