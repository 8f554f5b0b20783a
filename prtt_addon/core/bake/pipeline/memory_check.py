"""Whether a bake fits in memory, checked before it allocates: the estimate
of each stage (memory_plan.stage_bytes) from the bake's settings, its texture
sets' sizes and coverage and what the process already holds, against the
memory available; the refusal names the estimate and what to lower.
"""
from __future__ import annotations

import numpy as np

from ...base.errors import BakeError
from ...base.memory import check_fits, resident_bytes
from ...model.scene import MAX_RESOLUTION
from ..estimators import hit_kernel
from ..estimators.relightable import GLOSSY_BANDS, relight_shared_colour
from .context import BakeContext, BakeSettings, asked_downscale
from .memory_plan import covered_texels, peak_stage, process_extra, stage_bytes, uv_areas, uv_boundaries
from .plan import BakePlan


def bake_stage_bytes(set_sizes, st: BakeSettings, *, n_triangles: int, bouncing: bool,
                     downscales: list[int] | None = None, compiling: bool = False,
                     extra: int = 0, dask: bool = False, sun: bool = False, lamps: int = 0,
                     sun_edges: bool | None = None) -> dict[str, int]:
    """Estimated peak bytes of each stage of a bake (memory_plan.stage_bytes).
    ``set_sizes``: (width, height, covered texels) per set baked, in order
    (covered: memory_plan.covered_texels of the set's UV area); ``downscales``:
    each set's bounce grid once chosen (default: the grid the settings ask for);
    ``compiling``: the bounce's kernels are compiled in this process (:func:`kernels_compile`);
    ``extra``: what the process holds beyond a bare worker (memory_plan.process_extra);
    ``dask``: the rays are traced on a Dask cluster (this process is its client);
    ``sun``: each set's masks are baked too (a sun's, with ``sun_edges``
    (default: with settings.sun_edges) its edges; ``lamps`` lamps' masks)."""
    K = st.bands ** 2
    kg = min(GLOSSY_BANDS, st.bands) ** 2
    colours = 1 if relight_shared_colour(st) else 3
    return stage_bytes([tuple(int(v) for v in s) for s in set_sizes], bands=st.bands, dilate=st.dilate,
                       n_triangles=n_triangles, threads=st.n_threads, chunk_rays=st.chunk_rays, mips=st.mips,
                       rays=st.rays, bounce_rays=st.bounce_rays,
                       bounces=st.bounces if bouncing else 0, bounce_mode=st.bounce_mode,
                       downscale=(downscales if downscales is not None
                                  else asked_downscale(st.bounces, st.tuning, st.bounce_downscale)),
                       relight_channels=3 * K + colours * (kg - 1) * kg, glossy_coeffs=kg * kg,
                       compiling=compiling, extra=extra, dask=dask, half=st.half, guiding=st.guiding,
                       validity=st.texel_validity, sun=sun, sun_detail=st.sun_detail,
                       sun_edges=bool(sun) and (st.sun_edges if sun_edges is None else sun_edges), lamps=lamps)


def job_array_bytes(scene) -> int:
    """Bytes of the scene's numpy arrays (what the loaded job holds)."""
    return sum(a.nbytes for a in vars(scene).values() if isinstance(a, np.ndarray))


def kernels_compile(ctx: BakeContext, plan: BakePlan) -> bool:
    """This bake's process will compile the bounce's numba kernels (runner's
    hit_kernel.warm_up finds them missing from numba's cache): a local bake with bounces."""
    st = ctx.settings
    return (plan.bouncing and ctx.dask is None
            and hit_kernel.compile_pending(st.bands, relightable=st.bounce_mode == "relightable",
                                           glossy_bands=min(GLOSSY_BANDS, st.bands)))


def bake_memory_bytes(set_sizes, st: BakeSettings, *, n_triangles: int, bouncing: bool) -> int:
    """The largest of :func:`bake_stage_bytes`: the bake's estimated peak."""
    return peak_stage(bake_stage_bytes(set_sizes, st, n_triangles=n_triangles, bouncing=bouncing))[1]


def scene_set_sizes(sc, set_ids) -> list[tuple[int, int, int]]:
    """(width, height, covered texels estimated from the UV area) of sets ``set_ids`` of ``sc``."""
    areas = uv_areas(sc.uvs, sc.set_id, sc.n_sets)
    edges = uv_boundaries(sc.uvs, sc.set_id, sc.n_sets)
    out = []
    for s in set_ids:
        w, h = (int(v) for v in sc.set_resolution[s])
        out.append((w, h, covered_texels(float(areas[s]), w, h, float(edges[s]))))
    return out


def check_memory(ctx: BakeContext, plan: BakePlan, downscales: list[int] | None = None) -> None:
    """MemoryLimitError unless the bake's estimated peak (:func:`bake_stage_bytes`:
    the largest stage) fits in the memory available, before anything of the
    bake is allocated; the estimate goes into the manifest's ``memory``. The
    refusal names the estimate, the memory available and what to lower.

    Called again with ``downscales`` once the first G-buffer has chosen the
    bounce grids (a grid that cannot be coarser, thin UV margins at this
    resolution, holds 4x the bounce texels): before the trace allocates."""
    sc, st = ctx.scene, ctx.settings
    first = ctx.memory.held_extra is None
    before = resident_bytes() if first else None
    compiling = kernels_compile(ctx, plan)        # imports numba for a bake with bounces
    if first:
        # Read once, before the bake allocates: what the process holds, and what
        # numba's import took (both vary with the machine: file-backed pages).
        ctx.memory.held_extra = process_extra(before, job_array_bytes(sc), resident_bytes())
    sizes = scene_set_sizes(sc, ctx.set_ids) if st.textures else []
    if ctx.masked and st.sun_detail > 1:
        for i, (w, h, _) in zip(ctx.set_ids, sizes):
            if max(w, h) * st.sun_detail > MAX_RESOLUTION:
                raise BakeError(f"texture set {sc.set_names[i]!r}: a sun mask of {st.sun_detail} x its {w}x{h} "
                                f"texels is {w * st.sun_detail}x{h * st.sun_detail}, over the {MAX_RESOLUTION} a "
                                f"texture may have a side; lower --sun-detail (Sun Shadow Detail) or the resolution")
    stages = bake_stage_bytes(sizes, st, n_triangles=sc.n_triangles, bouncing=plan.bouncing,
                              downscales=downscales, compiling=compiling, extra=ctx.memory.held_extra,
                              dask=ctx.dask is not None, sun=ctx.masked, lamps=len(ctx.lamps),
                              sun_edges=ctx.sun is not None and st.sun_edges)
    stage, need = peak_stage(stages)
    ctx.memory.estimate_mb = round(need / 2 ** 20, 1)
    biggest = max(sizes, key=lambda s: s[0] * s[1], default=None)
    what = (f"the bake ({len(sizes)} texture set(s), the largest {biggest[0]}x{biggest[1]}, {st.bands} bands"
            + (f", {st.bounces} {st.bounce_mode} bounce(s)" if plan.bouncing else "") + f"; its peak: {stage})"
            if biggest else "the bake")
    check_fits(need, what, advice="lower --resolution (memory grows with texels), --bands, or the bounces "
                                   "(--bounces, --bounce-downscale 2 or 4), or give the objects smaller "
                                   "texture sets")
