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
from ...light.lamp import LAMP_RAYS, lamps_hash
from ...light.sun import SUN_RAYS, Sun
from ...texels.dilate import dilate
from ..estimators.lamp_mask import lamp_mask
from ..estimators.raytrace import RayScene
from ..estimators.sun_edge import REACH, STEPS, TOLERANCE, WIDE, sun_edges
from ..estimators.sun_mask import FIRST_RAYS, REFINE_RING, sun_mask
from .context import BakeContext

#: What the edges' texels hold, in the sun's key (a change bakes the masks again).
EDGE_VERSION = f"1,{REACH},{STEPS},{TOLERANCE},{WIDE}"
#: A set's mask and edge files end so (commit and the readers tell them by it).
MASK_SUFFIX = ".sun.exr"
EDGE_SUFFIX = ".sun_edge.exr"
LAMP_SUFFIX = ".lamps.exr"
SUN_SUFFIXES = (MASK_SUFFIX, EDGE_SUFFIX, LAMP_SUFFIX)


def sun_key(sun: Sun | None, input_hash: str, detail: int = 1, refine: bool = True,
            edges: bool = False, lamps=()) -> str | None:
    """sha256 hex of what a set's mask depends on beyond the transfer's inputs:
    the sun's direction and disc, the rays, the mask's detail (settings.sun_detail,
    when not 1: the keys of the bakes before it), its refinement
    (settings.sun_refine; off: the keys before it) and its edges
    (settings.sun_edges; off: the keys before them); with ``lamps`` (point
    and spot lamps, core.light.lamp.Lamp, in channel order) their positions,
    sizes and rays too (none: the keys before lamps); None without a sun or lamps."""
    if sun is None and not lamps:
        return None
    extra = f"|detail={detail}" if detail != 1 else ""
    if refine:
        extra += f"|refine={FIRST_RAYS},{REFINE_RING}"
    if edges and sun is not None:
        extra += f"|edges={EDGE_VERSION}"
    if lamps:
        extra += f"|lamps={lamps_hash(lamps)},{LAMP_RAYS}"
    head = f"{sun.mask_hash()}|{SUN_RAYS}" if sun is not None else "no-sun"
    return hashlib.sha256(f"{input_hash}|{head}{extra}".encode()).hexdigest()


def sun_set(ctx: BakeContext, rays: RayScene | None, gb, inside: np.ndarray | None, key: str,
            rings: int | None = None) -> tuple[list[str], dict]:
    """Trace, dilate and stage set ``gb``'s masks: the sun's (with
    ctx.sun) and its lamps' (with ctx.lamps: ``<set>.lamps.exr``, channel i
    lamp i); ``gb`` the set's G-buffer, or one settings.sun_detail times
    finer over its layout, dilated by ``rings`` (as many of its texels as the
    set's dilation covers); returns (the file names, the set report's
    entries). ``rays`` the scene's BVH (None under Dask: the masks are
    traced here, on a BVH of its own)."""
    if rays is None:
        rays = ctx.validity_scene[0] if ctx.validity_scene is not None else RayScene(ctx.scene.positions)
    files, rep = _sun_mask_set(ctx, rays, gb, inside, key, rings) if ctx.sun is not None else ([], {})
    if ctx.lamps:
        f, r = _lamp_set(ctx, rays, gb, inside, key, rings)
        files, rep = files + f, {**rep, **r}
    return files, rep


def _coverage(gb, inside):
    """(H W,) bool: the texels the masks were traced at (not those inside geometry)."""
    cov = np.zeros(gb.height * gb.width, bool)
    cov[gb.texel] = True
    if inside is not None and inside.any():
        cov[gb.texel[inside]] = False
    return cov


def _lamp_set(ctx: BakeContext, rays: RayScene, gb, inside, key: str, rings) -> tuple[list[str], dict]:
    """Set ``gb``'s lamp masks (lamp_mask.py), dilated like the sun's, staged as one file."""
    st = ctx.settings
    name = ctx.scene.set_names[gb.set_index]
    ctx.check_cancel()
    ctx.emit(type="progress", stage="lamps", set=name, fraction=0.0)
    t = time.perf_counter()
    H, W = gb.height, gb.width
    planes = np.zeros((len(ctx.lamps), H * W), np.float32)
    for i, lamp in enumerate(ctx.lamps):
        if lamp.shadow:
            m = lamp_mask(rays, gb.position, gb.geo_normal, gb.texel.astype(np.int64), lamp, rays=LAMP_RAYS,
                          seed=st.seed, set_index=gb.set_index, lamp_index=i, threads=st.n_threads,
                          chunk_rays=st.chunk_rays, cancel=ctx.cancel,
                          grid=(W, H) if st.sun_refine else None)
        else:                          # Shadow off: nothing blocks it
            m = np.ones(gb.texel.size, np.float32)
        planes[i, gb.texel] = m
    cov = _coverage(gb, inside)
    planes[:, ~cov] = 0.0
    dilate(planes.reshape(-1, H, W), cov.reshape(H, W), st.dilate if rings is None else rings)
    fname = f"{name}{LAMP_SUFFIX}"
    ctx.emit(type="progress", stage="write", file=fname, fraction=0.0)
    exr_io.write_lamp_exr(ctx.staging.path(fname), planes.reshape(-1, H, W), atomic=False,
                          attrs={"lamp_rays": LAMP_RAYS, "seed": st.seed, "sun_key": key,
                                 "lamps": " ".join(lp.name.replace(" ", "_")[:40] for lp in ctx.lamps)})
    return [fname], {"lamp_file": fname, "lamp_seconds": round(time.perf_counter() - t, 3)}


def _sun_mask_set(ctx: BakeContext, rays: RayScene, gb, inside, key: str, rings) -> tuple[list[str], dict]:
    """Set ``gb``'s sun mask, with settings.sun_refine all its rays only in
    penumbrae (sun_mask's ``grid``), with settings.sun_edges its sub-texel
    edges beside it (sun_edge.py)."""
    st, sun = ctx.settings, ctx.sun
    name = ctx.scene.set_names[gb.set_index]
    ctx.check_cancel()
    ctx.emit(type="progress", stage="sun", set=name, fraction=0.0)
    t = time.perf_counter()
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
    cov = _coverage(gb, inside)
    plane[0, ~cov] = 0.0
    edges = None
    if st.sun_edges and sun.shadow:
        # Before the mask's dilation: the edges are found from the traced texels alone.
        edges, edge_counts = sun_edges(rays, gb.position, gb.geo_normal, gb.texel.astype(np.int64), W, H, m,
                                       sun.direction, sun.angle, use=None if inside is None else ~inside)
    dilate(plane.reshape(1, H, W), cov.reshape(H, W), st.dilate if rings is None else rings)
    fname = f"{name}{MASK_SUFFIX}"
    ctx.emit(type="progress", stage="write", file=fname, fraction=0.0)
    attrs = {"sun_rays": SUN_RAYS, "seed": st.seed, "sun_key": key,
             "sun_direction": " ".join(f"{v:.9f}" for v in sun.direction),
             "sun_angle": float(sun.angle), **({} if sun.shadow else {"sun_shadow": 0})}
    exr_io.write_mask_exr(ctx.staging.path(fname), plane.reshape(H, W), atomic=False, attrs=attrs)
    files = [fname]
    rep = {}
    if edges is not None:
        planes = np.zeros((3, H * W), np.float32)
        planes[:, gb.texel] = edges.T
        if inside is not None and inside.any():
            planes[:, gb.texel[inside]] = 0.0
        # The same rings as the mask's: a gutter texel is valid where all it is filled from are.
        dilate(planes.reshape(3, H, W), cov.reshape(H, W), st.dilate if rings is None else rings)
        ename = f"{name}{EDGE_SUFFIX}"
        exr_io.write_edge_exr(ctx.staging.path(ename), planes.reshape(3, H, W), atomic=False,
                              attrs={**attrs, "sun_edges": EDGE_VERSION})
        files.append(ename)
        rep = {"sun_edge_file": ename, "sun_edge_texels": edge_counts["edge_texels"],
               "sun_mask_texels": edge_counts["mask_texels"], "sun_crossings": edge_counts["crossings"]}
    seconds = time.perf_counter() - t
    lit = float(np.count_nonzero(m > 0.0)) / max(1, m.size)
    return files, {"sun_file": fname, "sun_seconds": round(seconds, 3), "sun_lit_fraction": round(lit, 4), **rep}
