"""The bounce stage of a bake: inter-reflection levels 1..bounces of every set.

Level 1 lights each surface with the fixed light through its transfer
texture; each level's exit radiance (bounce.ExitShader) is what the next
level's rays gather (bounce.py has the estimator). Per level n and set the
texture ``<set>.bounce<n>.exr`` holds the cosine-weighted incident radiance
after exactly n reflections, projected to SH: RGB planes (3K, H, W) float32
(R.sh000.. G.. B.., SH index k = l² + l + m) in the units of the direct
term M(L) T it is added to at render time; denoised (settings.bounce_denoise),
then dilated like the transfer. Levels stop early once one carries less than
settings.bounce_tolerance of the direct light's energy.

Callable in parts: :func:`bounce_inputs` (per-set skip masks, surface texels,
level-1 incident radiance), :func:`level_shader` (one level's exit textures),
:func:`bounce_set_level` (one set at one level); :func:`bounce_levels` runs them.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from ...base.memory import numpy_hugepage_advice
from ...sh.zonal import phong_factors
from ...shading.materials import eval_materials
from ...texels.dilate import dilate
from ...texels.gbuffer import GBuffer, build_gbuffer
from ...texels.islands import coarse_grid_conflicts, island_labels
from ..estimators import denoise
from ..estimators.bounce import (
    ExitShader,
    SurfaceTexels,
    bake_bounce_set,
    block_mean_incident,
    bounce_settings,
    exit_textures,
    glossy_triangles,
    incident_at,
    incident_dc_at,
    level_energy,
    surface_texels,
    textured_triangles,
)
from ..estimators.relightable import uniform_energy
from ..estimators.transfer import TransferSettings, warm_tables
from .context import AUTO_DOWNSCALE, BakeContext, BakeSettings, asked_downscale  # noqa: F401 (re-exported)
from .plan import BakePlan
from .stages import BounceSource, Geometry, write_planes


@dataclasses.dataclass(eq=False)
class BounceInputs:
    """Per set (keyed by scene set index) of the sets that bounce. N = covered
    texels, M = valid (covered + dilated) texels, K = bands²."""

    skip: dict[int, np.ndarray]         # (N,) bool: texels that get zero without rays (analytic or open)
    surface: dict[int, SurfaceTexels]   # materials and normals at the M valid texels
    direct: float                       # level_energy of the level-1 incident radiance, all sets
    glossy_tri: np.ndarray              # (T,) bool: triangles with a glossy material
    grids: dict[int, BounceGrid]        # the grid each set's bounce textures are baked on
    sources: list[BounceSource]         # the sets as the levels bake them (on their grids)
    # Sets baked on a coarser grid: level 1's diffuse light leaves from the
    # transfer's grid, (albedo there, DC of the incident radiance (M', 3)).
    level1_diffuse: dict[int, tuple[SurfaceTexels, np.ndarray]]


@dataclasses.dataclass
class BounceSetLevel:
    """One set at one level (bounce_set_level)."""

    report: dict                        # the manifest's bounce "sets" entry
    file: str | None                    # staged ``<set>.bounce<level>.exr``; None when skipped
    incident: np.ndarray | None         # next level's Lp (M, 3, K) float32; None at the last level or skipped
    energy: float                       # level_energy of this level's texture at the covered texels


@dataclasses.dataclass
class BounceResult:
    """Every level of every set (bounce_levels)."""

    reports: list[dict]                 # per set and level, in level then set order
    files: list[str]                    # staged bounce textures
    stopped: dict | None                # early stop: after_level, energy_ratio, tolerance, levels_not_baked

    def manifest_entry(self, plan: BakePlan, st: BakeSettings) -> dict:
        """The manifest's "bounce" object."""
        relightable = st.bounce_mode == "relightable"
        return {"key": plan.bounce_key, "levels": st.bounces, "rays": st.bounce_rays,
                **({"mode": "relightable"} if relightable else {}), "stopped_early": self.stopped,
                "light_hash": None if relightable else plan.light_hash,
                "materials_hash": plan.materials_hash, "files": self.files, "sets": self.reports,
                "rays_traced": sum(r["rays_traced"] for r in self.reports),
                "hits_shaded": sum(r["hits_shaded"] for r in self.reports)}


@dataclasses.dataclass(frozen=True)
class BounceGrid:
    """The texel grid one set's bounce textures are baked and stored on, and
    the bands they keep."""

    downscale: int                      # 1/downscale of the transfer resolution per side (1 = the same grid)
    width: int
    height: int
    why: str                            # why this grid (the manifest's "grid" entry)
    bands: int = 0                      # SH bands stored (0: all the bake's)
    bands_why: str = ""
    rays: int = 0                       # rays per texel on this grid (0: settings.bounce_rays)

    def report(self) -> dict:
        out = {"downscale": self.downscale, "resolution": [self.width, self.height], "why": self.why}
        if self.bands:
            out.update(bands=self.bands, bands_why=self.bands_why)
        if self.rays:
            out.update(rays=self.rays)
        return out


#: tuning "auto": the rays per coarse texel relative to settings.bounce_rays
#: (x1.5: 0.375x the rays in all; without it the coarse grid's extra noise and
#: blur cost +0.20 percentage points of preview image error on the room, with
#: it +0.05: bench auto, docs/benchmarks.md). The grid it asks for:
#: context.AUTO_DOWNSCALE.
AUTO_RAY_FACTOR = 1.5
#: A band l is dropped when |A_l(s) / A_0(s)| is below this for every glossy
#: lobe of the set: the shaded glossy term then changes by less than 5 % of
#: the bounce light in those bands.
AUTO_LOBE_TOLERANCE = 0.05


def choose_bounce_bands(sc, set_index: int, glossy_tri: np.ndarray, bands: int) -> tuple[int, str]:
    """(bands to store, why) for one set's bounce textures under tuning "auto".

    Without a glossy triangle every reader of the texture (diffuse shading, the
    next level's diffuse exit radiance) takes only its DC term: 1 band, exact.
    With glossy triangles, the bands any of their Phong lobes still passes
    (|zonal.phong_factors / band 0| >= AUTO_LOBE_TOLERANCE); a textured
    material keeps every band (its lobe is not one value)."""
    tris = sc.triangles_of_set(set_index)
    glossy = tris[glossy_tri[tris]]
    if glossy.size == 0:
        return 1, "no glossy material: diffuse shading and the next level read only the DC term (exact)"
    if textured_triangles(sc)[glossy].any():
        return bands, f"glossy, textured materials: all {bands} bands"
    p = eval_materials(sc, glossy, np.full((glossy.size, 3), 1.0 / 3.0))
    n = 1
    # Every lobe, not only the sharpest: a Phong lobe's SH factors are not
    # monotonic in the exponent (A_3 / A_0 is -0.04 at exponent 0.72, -0.125 at 0).
    for s in np.unique(p.exponent[np.any(p.spec > 0.0, axis=1)]):
        A = phong_factors(float(s), bands)
        keep = np.flatnonzero(np.abs(A / A[0]) >= AUTO_LOBE_TOLERANCE)
        n = max(n, int(keep.max()) + 1 if keep.size else 1)
    return n, (f"glossy materials: {n} of {bands} bands pass their Phong lobes "
               f"(|A_l / A_0| >= {AUTO_LOBE_TOLERANCE:g})")


#: Coarse grids narrower than this get no texels for small islands at all.
MIN_BOUNCE_SIDE = 16


def choose_grid(gb: GBuffer, asked: int) -> BounceGrid:
    """The coarsest grid of 1/asked, 1/(asked/2) ... 1/1 of ``gb``'s resolution
    per side that divides it, keeps at least MIN_BOUNCE_SIDE texels a side and
    never mixes UV islands (islands.coarse_grid_conflicts is 0)."""
    W, H = gb.width, gb.height
    if asked <= 1:
        return BounceGrid(1, W, H, "bounce_downscale 1: the transfer's grid")
    mask = gb.mask()
    labels = None
    why = []
    f = asked
    while f > 1:
        if W % f or H % f:
            why.append(f"1/{f}: {W}x{H} is not a multiple of {f}")
        elif min(W, H) // f < MIN_BOUNCE_SIDE:
            why.append(f"1/{f}: fewer than {MIN_BOUNCE_SIDE} texels a side")
        else:
            if labels is None:
                labels = island_labels(mask)
            bad = coarse_grid_conflicts(mask, f, labels)
            if bad == 0:
                why.append(f"1/{f}: no coarse texel sees two UV islands")
                return BounceGrid(f, W // f, H // f, "; ".join(why))
            why.append(f"1/{f}: {bad} coarse texels would mix UV islands")
        f //= 2
    return BounceGrid(1, W, H, "; ".join(why) + "; the transfer's grid")


def coarse_source(ctx: BakeContext, geo: Geometry, src: BounceSource, grid: BounceGrid,
                  skip_full: np.ndarray) -> tuple[BounceSource, np.ndarray]:
    """``src`` on the coarse ``grid``: its G-buffer and kernel points there and
    the skip mask (a coarse texel traces nothing when every covered texel of
    its block was skipped at full resolution; one without covered texels there
    is traced). The incident texture is left to the caller (bounce_inputs)."""
    f, st = grid.downscale, ctx.settings
    gb = src.gbuffer
    coarse = build_gbuffer(ctx.scene, src.index, normal_maps=st.normal_maps, executor=ctx.helpers,
                           bands=max(2, st.n_threads), cancel=ctx.stop, resolution=(grid.width, grid.height))
    pts = geo.points(ctx.scene, src.index, coarse)
    block = (gb.texel // gb.width // f) * grid.width + (gb.texel % gb.width) // f
    covered = np.bincount(block, minlength=grid.width * grid.height)
    traced = np.bincount(block, weights=(~skip_full).astype(np.float64), minlength=grid.width * grid.height)
    skip = ((covered > 0) & (traced == 0))[coarse.texel]
    skip |= pts.analytic
    return dataclasses.replace(src, gbuffer=coarse, points=pts, open=None, incident=None, fine=None,
                               analytic=None), skip


def bounce_inputs(ctx: BakeContext, sources: list[BounceSource], geo: Geometry | None = None, *,
                  lit: bool = True) -> tuple[BounceInputs, dict[int, np.ndarray]]:
    """Skip masks and surface texels of every set, and level 1's incident
    radiance {set index: Lp (M, 3, K) float32} (ctx.bounce_light through each
    transfer texture). Drops each source's ``incident`` texture once used
    (the exit textures replace it). With settings.bounce_downscale > 1 (and
    ``geo``), sources move to their coarse grid (choose_grid): the returned
    inputs' ``sources`` are what the levels bake. Not ``lit`` (relightable
    bounces): the transfer rows T (M, K) instead of Lp, and in
    ``level1_diffuse`` the fine grid's T rows; ``direct`` is then the energy
    under a uniform unit light (relightable.uniform_energy). ``sources`` is
    consumed (its items become None)."""
    st, sc = ctx.settings, ctx.scene
    skip, surf, level1_diffuse, grids, baked, Lp = {}, {}, {}, {}, [], {}
    t = time.perf_counter()
    glossy_tri = glossy_triangles(sc)
    auto = st.tuning == "auto"
    asked = asked_downscale(st.bounces, st.tuning, st.bounce_downscale)
    if geo is None:
        asked = 1

    K = st.bands ** 2

    def fine_diffuse(r):
        full = r.fine if r.fine is not None else surface_texels(sc, r.gbuffer, st.dilate, diffuse_only=True)
        if not lit:
            return full, r.incident.at(full.valid, K, padded=True)
        return full, incident_dc_at(full, r.incident, ctx.bounce_light, st.bands)

    for at, r in enumerate(sources):
        # Consumed: the full-resolution source (its G-buffer's layout, open mask)
        # is not held through the levels once its coarse source replaces it.
        sources[at] = None
        ctx.check_cancel()
        # Zero without rays: analytic texels, and texels no transfer ray saw geometry
        # from (tested against half-float rounding when read back from disk).
        # The steps below are numpy on one core each: independent ones run on the
        # helper threads beside the island labels (choose_grid) on this one.
        fine_job = ctx.helpers.submit(fine_diffuse, r) if asked > 1 else None
        # Chosen from this G-buffer already when the runner refined the memory estimate.
        grid = ctx.bounce_grids.get(r.index) or choose_grid(r.gbuffer, asked)
        skip[r.index] = (r.points.analytic if r.points is not None else r.analytic) | r.open
        if auto:
            nb, why = choose_bounce_bands(sc, r.index, glossy_tri, st.bands)
            rays = int(round(st.bounce_rays * AUTO_RAY_FACTOR)) if grid.downscale > 1 else st.bounce_rays
            grid = dataclasses.replace(grid, bands=nb, bands_why=why, rays=min(rays, 1 << 14))
        grids[r.index] = grid
        incident = r.incident
        fine = fine_job.result() if fine_job is not None else None
        # The exit textures replace them (the caller's results still hold the source).
        r.incident = r.fine = r.analytic = None
        if grid.downscale > 1:
            # Level 1's diffuse light leaves from the transfer's grid (contact shadows
            # on the surfaces it bounces off stay sharp: 0.04 pp of image error on the
            # room, bench auto); its glossy lobe, a few % of the light and smooth, from
            # the coarse grid with the transfer averaged over each block (4x fewer
            # texels to light and look up).
            level1_diffuse[r.index] = fine
            # The full-resolution texture, points and surface are done with once the
            # block means are taken: freed before the coarse grid's are built.
            incident = block_mean_incident(incident, fine[0].valid, grid.downscale, st.dilate)
            r.points = None
            r.gbuffer.release_surface()
            r, skip[r.index] = coarse_source(ctx, geo, r, grid, skip[r.index])
            surf[r.index] = surface_texels(sc, r.gbuffer, st.dilate)
        else:
            surf[r.index] = surface_texels(sc, r.gbuffer, st.dilate)
        # The levels read the points and the surface texels; the denoiser the
        # positions and normals (the points' own arrays): the rest is dropped.
        r.gbuffer.release_surface(keep_geometry=True)
        if lit:
            Lp[r.index] = incident_at(surf[r.index], incident, ctx.bounce_light, st.bands)
        else:
            # The coarse grid's own incident set (the fine one is level 1's diffuse table: kept).
            Lp[r.index] = incident.at(surf[r.index].valid, K, padded=True, consume=grid.downscale > 1)
        incident = None
        baked.append(r)
    # On the grids the bounce textures are baked on, like each level's energy.
    if lit:
        direct = sum(level_energy(v) for v in Lp.values())
    else:
        direct = sum(uniform_energy(v[:-1, None, :]) for v in Lp.values())
    ctx.seconds["bounce_exit"] = time.perf_counter() - t
    return BounceInputs(skip, surf, direct, glossy_tri, grids, baked, level1_diffuse), Lp


def level_shader(ctx: BakeContext, inputs: BounceInputs, incident: dict[int, np.ndarray],
                 level: int = 1) -> ExitShader:
    """The radiance leaving every surface at this level, from its incident
    radiance ``incident`` {set index: Lp (M, 3, K)} on the bounce grids (sets
    missing from it are dark); level 1's diffuse term from the transfer's grid
    where that is finer (BounceInputs.level1_diffuse)."""
    t = time.perf_counter()
    fine = inputs.level1_diffuse if level == 1 else {}
    exits = {i: exit_textures(inputs.surface[i], v, ctx.settings.bands, diffuse_at=fine.get(i))
             for i, v in incident.items()}
    shader = ExitShader(ctx.scene, exits, ctx.settings.bands, inputs.glossy_tri)
    ctx.seconds["bounce_exit"] += time.perf_counter() - t
    return shader


def skipped_set(src: BounceSource, level: int) -> dict:
    """The bounce "sets" entry of a set none of whose texels sees geometry."""
    return {"name": src.name, "level": level, "skipped": "sees no geometry", "texels": int(src.gbuffer.n),
            "rays_traced": 0, "hits_shaded": 0}


def set_level_plan(ctx: BakeContext, inputs: BounceInputs, src: BounceSource, level: int,
                   bst: TransferSettings) -> tuple[TransferSettings, dict, object]:
    """What one set's level traces with, in either bounce mode: its settings
    (``bst`` with the set's grid's ray count), the extra entries of its report
    (the grid, when tuning or a downscale chose it) and its progress callback."""
    st = ctx.settings
    grid = inputs.grids.get(src.index)
    if grid is not None and grid.rays and grid.rays != bst.rays:
        bst = bounce_settings(st, grid.rays)
    extra = {"grid": grid.report()} if grid is not None and (st.bounce_downscale != 1 or st.tuning != "fixed") else {}

    def on_progress(done, total, rays):
        ctx.emit(type="progress", stage="bounce", set=src.name, level=level, fraction=done / max(total, 1),
                 rays=rays)

    return bst, extra, on_progress


def bounce_set_level(ctx: BakeContext, geo: Geometry, plan: BakePlan, src: BounceSource, inputs: BounceInputs,
                     shader: ExitShader, level: int, *, bst: TransferSettings, filt: str) -> BounceSetLevel:
    """Trace, denoise, dilate and stage one set's level (progress stage
    "bounce", then "write"). ``bst`` = bounce.bounce_settings(settings,
    settings.bounce_rays); ``filt`` = the resolved denoiser (not "auto")."""
    st, K = ctx.settings, ctx.n_coeffs
    name, gb, skip = src.name, src.gbuffer, inputs.skip[src.index]
    t = time.perf_counter()
    if skip.all():
        return BounceSetLevel(skipped_set(src, level), None, None, 0.0)
    grid = inputs.grids.get(src.index)
    bst, extra, on_progress = set_level_plan(ctx, inputs, src, level, bst)
    tex, mask, stats = bake_bounce_set(geo.rays, gb, src.points, skip, shader, bst, level,
                                       progress=on_progress, cancel=ctx.cancel, remote=ctx.remote)
    ctx.seconds["bounce_trace"] += time.perf_counter() - t
    t = time.perf_counter()
    tex = tex.reshape(3 * K, gb.height, gb.width)
    if filt != "none":
        td = time.perf_counter()
        ctx.check_cancel()
        tex = denoise.denoise_bounce(tex, gb, filt, st.bands)
        stats["denoise"] = {"filter": filt, "seconds": time.perf_counter() - td}
    energy = level_energy(tex.reshape(3 * K, -1)[:, gb.texel].T)
    fname = f"{name}.bounce{level}.exr"
    attrs = dict(plan.exr_attrs(st), level=level, rays=bst.rays, light_hash=plan.light_hash,
                 materials_hash=plan.materials_hash, texels=int(gb.n))
    Kb = grid.bands ** 2 if grid is not None and grid.bands else K
    if Kb < K:
        # Only the bands this set's shading reads: the rest of the projection is dropped
        # (readers pad it with zeros, core/preview/pack.py), here and for the next level.
        tex = np.ascontiguousarray(tex.reshape(3, K, gb.height, gb.width)[:, :Kb]).reshape(3 * Kb, gb.height,
                                                                                           gb.width)
        attrs.update(band_limited=1, shading_bands=st.bands)
    with numpy_hugepage_advice(False):      # fresh arrays, streamed once
        dilate(tex, mask, st.dilate, executor=ctx.helpers)
        half = write_planes(ctx, fname, tex, "bounce", attrs, rgb=True, consume=level >= st.bounces)
    nxt = None
    if level < st.bounces:
        rows = tex.reshape(3 * Kb, -1)[:, inputs.surface[src.index].valid].T.reshape(-1, 3, Kb)
        nxt = rows if Kb == K else np.concatenate([rows, np.zeros((rows.shape[0], 3, K - Kb), rows.dtype)], 2)
    stats.update(name=name, level=level, file=fname, storage="half" if half else "float", **extra)
    ctx.seconds["bounce_write"] += time.perf_counter() - t
    return BounceSetLevel(stats, fname, nxt, energy)


def early_stop(ctx: BakeContext, level: int, energy: float, direct: float, judged_under: str = "") -> dict | None:
    """The manifest's ``stopped_early`` (and an "info" event) when level
    ``level`` carries less than settings.bounce_tolerance of the direct
    light's energy and levels remain; else None. ``judged_under``: the light
    the energies were measured under, when not the bake's."""
    st = ctx.settings
    ratio = energy / direct if direct > 0 else 0.0
    if level >= st.bounces or ratio >= st.bounce_tolerance:
        return None
    stopped = {"after_level": level, "energy_ratio": ratio, "tolerance": st.bounce_tolerance,
               "levels_not_baked": st.bounces - level}
    if judged_under:
        stopped["judged_under"] = judged_under
    ctx.emit(type="info", message=f"bounce level {level} carries {100 * ratio:.3g} % of the direct "
             f"light (< {100 * st.bounce_tolerance:g} %{', under a ' + judged_under if judged_under else ''}): "
             f"levels {level + 1}-{st.bounces} are not baked")
    return stopped


def bounce_levels(ctx: BakeContext, geo: Geometry, plan: BakePlan, sources: list[BounceSource]) -> BounceResult:
    """Bake levels 1..settings.bounces of every set in ``sources`` (the sets
    with texels, in bake order), stopping early below settings.bounce_tolerance
    (an "info" event says so)."""
    st = ctx.settings
    bst = bounce_settings(st, st.bounce_rays)
    filt = denoise.resolve_filter(st.bounce_denoise, st.bounce_rays)
    reports, files = [], []
    inputs, Lp = bounce_inputs(ctx, sources, geo)
    # The levels' ray patterns and estimator tables (~0.2 s) on a helper while
    # level 1's exit radiance is computed, not serially before its first chunk.
    for rays in sorted({g.rays or st.bounce_rays for g in inputs.grids.values()} or {st.bounce_rays}):
        ctx.helpers.submit(warm_tables, bounce_settings(st, rays), ctx.stop)
    stopped = None
    for level in range(1, st.bounces + 1):
        ctx.check_cancel()
        shader = level_shader(ctx, inputs, Lp, level)
        nxt, energy = {}, 0.0
        for src in inputs.sources:
            ctx.check_cancel()
            out = bounce_set_level(ctx, geo, plan, src, inputs, shader, level, bst=bst, filt=filt)
            reports.append(out.report)
            if out.file is not None:
                files.append(out.file)
            if out.incident is not None:
                nxt[src.index] = out.incident
            energy += out.energy
        if ctx.remote is not None:
            ctx.remote.forget_shader()        # its scattered copy shares the exit textures
        del shader
        Lp = nxt
        if not Lp:
            break
        stopped = early_stop(ctx, level, energy, inputs.direct)
        if stopped:
            break
    return BounceResult(reports, files, stopped)
