"""The sun's mask of one set (issue 48): traced from the set's G-buffer, after
texel validity has moved its points, dilated like the transfer, written as
``<set>.sun.exr`` (exr_io.write_mask_exr).

A bake has a sun when its job names one (BakeContext.sun: a
core.light.sun.Sun); the mask depends on the sun's direction and disc only,
so its key (plan.sun_key) holds those and the rays, and a sun turned since
the last bake bakes again. Texels inside geometry (validity.inside_texels)
are emptied and filled from their neighbours, as the transfer's are.
"""
from __future__ import annotations

import hashlib
import time

import numpy as np

from ...io import exr_io
from ...light.sun import SUN_RAYS, Sun
from ...texels.dilate import dilate
from ..estimators.raytrace import RayScene
from ..estimators.sun_mask import FIRST_RAYS, REFINE_RING, sun_mask
from .context import BakeContext


def sun_key(sun: Sun | None, input_hash: str, detail: int = 1, refine: bool = True) -> str | None:
    """sha256 hex of what a set's mask depends on beyond the transfer's inputs:
    the sun's direction and disc, the rays, the mask's detail (settings.sun_detail,
    when not 1: the keys of the bakes before it) and its refinement
    (settings.sun_refine; off: the keys before it); None without a sun."""
    if sun is None:
        return None
    extra = f"|detail={detail}" if detail != 1 else ""
    if refine:
        extra += f"|refine={FIRST_RAYS},{REFINE_RING}"
    return hashlib.sha256(f"{input_hash}|{sun.mask_hash()}|{SUN_RAYS}{extra}".encode()).hexdigest()


def sun_set(ctx: BakeContext, rays: RayScene | None, gb, inside: np.ndarray | None, key: str,
            rings: int | None = None) -> tuple[str, dict]:
    """Trace, dilate and stage set ``gb``'s mask (``gb`` the set's G-buffer,
    or one settings.sun_detail times finer over its layout, dilated by
    ``rings``: as many of its texels as the set's dilation covers); with
    settings.sun_refine all its rays only in penumbrae (sun_mask's ``grid``);
    returns (file name, the set report's sun entries). ``rays`` the scene's
    BVH (None under Dask: the mask is traced here, on a BVH of its own)."""
    st, sun = ctx.settings, ctx.sun
    name = ctx.scene.set_names[gb.set_index]
    ctx.check_cancel()
    ctx.emit(type="progress", stage="sun", set=name, fraction=0.0)
    t = time.perf_counter()
    if rays is None:
        rays = ctx.validity_scene[0] if ctx.validity_scene is not None else RayScene(ctx.scene.positions)
    if sun.shadow:
        m = sun_mask(rays, gb.position, gb.geo_normal, gb.texel.astype(np.int64), sun.direction, sun.angle,
                     rays=SUN_RAYS, seed=st.seed, set_index=gb.set_index, threads=st.n_threads,
                     chunk_rays=st.chunk_rays, cancel=ctx.cancel,
                     grid=(gb.width, gb.height) if st.sun_refine else None)
    else:                              # Shadow off: nothing blocks it (n.l is the shading's)
        m = np.ones(gb.texel.size, np.float32)
    H, W = gb.height, gb.width
    plane = np.zeros((1, H * W), np.float32)
    plane[0, gb.texel] = m
    cov = np.zeros(H * W, bool)
    cov[gb.texel] = True
    if inside is not None and inside.any():
        drop = gb.texel[inside]
        plane[0, drop] = 0.0
        cov[drop] = False
    dilate(plane.reshape(1, H, W), cov.reshape(H, W), st.dilate if rings is None else rings)
    fname = f"{name}.sun.exr"
    ctx.emit(type="progress", stage="write", file=fname, fraction=0.0)
    exr_io.write_mask_exr(ctx.staging.path(fname), plane.reshape(H, W), atomic=False,
                          attrs={"sun_rays": SUN_RAYS, "seed": st.seed, "sun_key": key,
                                 "sun_direction": " ".join(f"{v:.9f}" for v in sun.direction),
                                 "sun_angle": float(sun.angle), **({} if sun.shadow else {"sun_shadow": 0})})
    seconds = time.perf_counter() - t
    lit = float(np.count_nonzero(m > 0.0)) / max(1, m.size)
    return fname, {"sun_file": fname, "sun_seconds": round(seconds, 3), "sun_lit_fraction": round(lit, 4)}
