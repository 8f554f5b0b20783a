"""The bounce stage under ``bounce_mode = "relightable"``: levels 1..bounces of
every set as linear maps of the light (estimators/relightable.py), summed into one texture
per set, ``<set>.relight.exr`` (kind "relight": exr_io.relight_channel_names).

The same inputs, grids, rays, seeds and skips as the baked levels
(bounce_stage.bounce_inputs, bounce.trace_bounce_level); the light is not
needed. Levels stop early by the energy under a uniform white light
(relightable.uniform_energy), so what is stored does not depend on any light.
"""
from __future__ import annotations

import time

import numpy as np

from ...base.memory import numpy_hugepage_advice
from ...io.exr_io import expand_shared_glossy, relight_channel_names
from ...texels.dilate import DilatedRows
from ..estimators.bounce import bounce_settings
from ..estimators.relightable import (
    GLOSSY_BANDS,
    RelightRows,
    RelightShader,
    bake_relight_set,
    later_exit,
    level1_exit,
    relight_shared_colour,
    uniform_energy,
)
from .bounce_stage import BounceResult, bounce_inputs, early_stop, set_level_plan, skipped_set
from .context import BakeContext
from .plan import BakePlan
from .stages import BounceSource, Geometry, write_planes


def relight_glossy_bands(st) -> int:
    """Bands of the relightable glossy part, in and out (relightable.GLOSSY_BANDS, at most the bake's)."""
    return min(GLOSSY_BANDS, st.bands)


def close_spills(levels) -> None:
    """Delete the temporary files of the levels kept in one (estimators.column_spill)."""
    for t in levels:
        if hasattr(t, "close"):
            t.close()


def relight_levels(ctx: BakeContext, geo: Geometry, plan: BakePlan, sources: list[BounceSource]) -> BounceResult:
    """Bake the relightable bounce light of every set in ``sources`` and stage
    one ``<set>.relight.exr`` per set that any level reached."""
    sums: dict[int, list] = {}
    try:
        return _relight_levels(ctx, geo, plan, sources, sums)
    finally:
        # A cancelled or failed bake leaves no spill file behind (a written set's are closed already).
        for entry in sums.values():
            close_spills(entry[1])


def _relight_levels(ctx: BakeContext, geo: Geometry, plan: BakePlan, sources: list[BounceSource],
                    sums: dict[int, list]) -> BounceResult:
    st, sc = ctx.settings, ctx.scene
    K = st.bands ** 2
    gbands = relight_glossy_bands(st)
    kg = gbands * gbands
    shared = relight_shared_colour(st)
    bst = bounce_settings(st, st.bounce_rays)
    inputs, T = bounce_inputs(ctx, sources, geo, lit=False)
    glossy_sets = {s.index: bool(inputs.glossy_tri[sc.triangles_of_set(s.index)].any()) for s in inputs.sources}
    reports, stopped, rows = [], None, {}
    # One level: each set's rows are only written, so they wait in a temporary
    # file (estimators.column_spill) instead of memory, the bounce's largest table (#35).
    one_level = st.bounces == 1
    for level in range(1, st.bounces + 1):
        ctx.check_cancel()
        t = time.perf_counter()
        if level == 1:
            # Each set's transfer rows and fine albedo are dropped as its exit is built:
            # the exits hold what later levels read.
            exits = {}
            last = level == st.bounces
            for i in list(T):
                exits[i] = level1_exit(inputs.surface[i], T.pop(i), gbands, fine=inputs.level1_diffuse.pop(i, None),
                                       consume_surface=last)
            T = None
        else:
            # The previous level's rows go as each exit is made from them: not held
            # through this level's trace (3 K + 3 (Kg - 1) Kg floats a texel).
            exits = {i: later_exit(inputs.surface[i], rows.pop(i), gbands) for i in list(rows)}
        shader = RelightShader(sc, exits, st.bands, gbands, inputs.glossy_tri)
        if level == st.bounces:
            # The exits hold what the last level reads: the surface texels' float64
            # albedo, spec and normals (~80 B a bounce texel) are not held through its trace.
            inputs.surface = {}
        ctx.seconds["bounce_exit"] += time.perf_counter() - t
        nxt, energy = {}, 0.0
        for src in inputs.sources:
            ctx.check_cancel()
            gb, skip = src.gbuffer, inputs.skip[src.index]
            if skip.all():
                reports.append(skipped_set(src, level))
                continue
            t = time.perf_counter()
            lbst, extra, on_progress = set_level_plan(ctx, inputs, src, level, bst)
            cols, mask, stats = bake_relight_set(geo.rays, gb, src.points, skip, shader, lbst, level,
                                                 glossy_out=glossy_sets[src.index], shared_colour=shared,
                                                 spill_folder=ctx.out_dir if one_level else None,
                                                 progress=on_progress, cancel=ctx.cancel, remote=ctx.remote)
            ctx.seconds["bounce_trace"] += time.perf_counter() - t
            t = time.perf_counter()
            # Each level is kept at its covered texels; dilated, and the levels
            # summed, a band of rows at a time as the texture is written (DilatedRows).
            # Recorded first: a spill is closed by relight_levels whatever happens next.
            if src.index in sums:
                sums[src.index][1].append(cols)
            else:
                sums[src.index] = [src, [cols], lbst.rays, mask]
            # The early stop reads only the DC responses to the light's DC (channels c K).
            energy += uniform_energy(np.stack([cols[c] for c in range(0, 3 * K, K)]).T[:, :, None])
            if level < st.bounces:
                valid = inputs.surface[src.index].valid
                M = valid.size
                with numpy_hugepage_advice(False):
                    flat = DilatedRows([cols], gb.texel, mask, st.dilate).at(valid, executor=ctx.helpers)
                dc_rows = np.ascontiguousarray(flat[:3 * K].T.reshape(M, 3, K))
                g_rows = None
                if flat.shape[0] > 3 * K and shared:
                    # The next level reads what is stored: the shared rows, tinted per colour.
                    g_rows = expand_shared_glossy(dc_rows, flat[3 * K:].T.reshape(M, kg - 1, kg))
                elif flat.shape[0] > 3 * K:
                    g_rows = np.ascontiguousarray(flat[3 * K:].T.reshape(M, 3, kg - 1, kg))
                nxt[src.index] = RelightRows(dc_rows, g_rows)
                flat = None
            stats.update(name=src.name, level=level, file=f"{src.name}.relight.exr", rays=lbst.rays, **extra)
            if shared and glossy_sets[src.index]:
                stats["glossy_colour"] = "shared: tuning auto stores the glossy rows once, tinted per colour on reading"
            reports.append(stats)
            ctx.seconds["bounce_write"] += time.perf_counter() - t
        if ctx.remote is not None:
            ctx.remote.forget_shader()        # its scattered copy shares the exit tables
        rows = nxt
        if not rows:
            break
        stopped = early_stop(ctx, level, energy, inputs.direct, "uniform white light")
        if stopped:
            break
    # The levels' exit tables and rows are done with: only the sums are written.
    inputs = exits = shader = rows = nxt = None
    files = []
    for i in list(sums):
        src, levels, rays, mask = sums[i]
        planes = DilatedRows(levels, src.gbuffer.texel, mask, st.dilate)
        t = time.perf_counter()
        g = glossy_sets[i]
        fname = f"{src.name}.relight.exr"
        attrs = dict(plan.exr_attrs(st), levels=max(r["level"] for r in reports if r["name"] == src.name),
                     rays=rays, materials_hash=plan.materials_hash, texels=int(src.gbuffer.n),
                     glossy_bands=gbands if g else 0, bounce_mode="relightable")
        if g and shared:
            attrs["glossy_colour"] = "shared"
        write_planes(ctx, fname, planes, "relight", attrs, rgb=False,
                     names=relight_channel_names(K, kg if g else 0, g and shared), bands=st.bands)
        close_spills(levels)
        del sums[i]
        planes = levels = None
        files.append(fname)
        ctx.seconds["bounce_write"] += time.perf_counter() - t
    return BounceResult(reports, files, stopped)
