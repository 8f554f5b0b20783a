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

from ..texels.dilate import dilate
from . import denoise
from .bounce import (HALF_OPEN_TOLERANCE, OPEN_TOLERANCE, ExitShader, SurfaceTexels, bake_bounce_set,
                     bounce_settings, exit_textures, glossy_triangles, incident_at, level_energy, open_texels,
                     surface_texels)
from .context import BakeContext, BakeSettings
from .memory import numpy_hugepage_advice
from .plan import BakePlan
from .stages import BounceSource, Geometry, write_planes
from .transfer import TransferSettings


@dataclasses.dataclass(eq=False)
class BounceInputs:
    """Per set (keyed by scene set index) of the sets that bounce. N = covered
    texels, M = valid (covered + dilated) texels, K = bands²."""

    skip: dict[int, np.ndarray]         # (N,) bool: texels that get zero without rays (analytic or open)
    surface: dict[int, SurfaceTexels]   # materials and normals at the M valid texels
    direct: float                       # level_energy of the level-1 incident radiance, all sets
    glossy_tri: np.ndarray              # (T,) bool: triangles with a glossy material


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
        return {"key": plan.bounce_key, "levels": st.bounces, "rays": st.bounce_rays,
                "stopped_early": self.stopped, "light_hash": plan.light_hash,
                "materials_hash": plan.materials_hash, "files": self.files, "sets": self.reports,
                "rays_traced": sum(r["rays_traced"] for r in self.reports),
                "hits_shaded": sum(r["hits_shaded"] for r in self.reports)}


def bounce_inputs(ctx: BakeContext, sources: list[BounceSource]) -> tuple[BounceInputs, dict[int, np.ndarray]]:
    """Skip masks and surface texels of every set, and level 1's incident
    radiance {set index: Lp (M, 3, K) float32} (ctx.light through each
    transfer texture). Drops each source's ``incident`` texture once used
    (the exit textures replace it)."""
    st, sc = ctx.settings, ctx.scene
    skip, surf = {}, {}
    t = time.perf_counter()
    for r in sources:
        ctx.check_cancel()
        # Zero without rays: analytic texels, and texels no transfer ray saw geometry
        # from (tested against half-float rounding when read back from disk).
        tol = HALF_OPEN_TOLERANCE if r.storage == "half" else OPEN_TOLERANCE
        skip[r.index] = r.points.analytic | open_texels(r.rows, r.gbuffer.normal, st.bands, tol)
        surf[r.index] = surface_texels(sc, r.gbuffer, st.dilate)
    glossy_tri = glossy_triangles(sc)
    # Level 1 leaves each surface with the fixed light times its transfer.
    Lp = {r.index: incident_at(surf[r.index], r.incident, ctx.light, st.bands) for r in sources}
    for r in sources:
        r.incident = None                  # the exit textures replace it
    direct = sum(level_energy(v) for v in Lp.values())
    ctx.seconds["bounce_exit"] = time.perf_counter() - t
    return BounceInputs(skip, surf, direct, glossy_tri), Lp


def level_shader(ctx: BakeContext, inputs: BounceInputs, incident: dict[int, np.ndarray]) -> ExitShader:
    """The radiance leaving every surface at this level, from its incident
    radiance ``incident`` {set index: Lp (M, 3, K)} (sets missing from it are dark)."""
    t = time.perf_counter()
    exits = {i: exit_textures(inputs.surface[i], v, ctx.settings.bands) for i, v in incident.items()}
    shader = ExitShader(ctx.scene, exits, ctx.settings.bands, inputs.glossy_tri)
    ctx.seconds["bounce_exit"] += time.perf_counter() - t
    return shader


def bounce_set_level(ctx: BakeContext, geo: Geometry, plan: BakePlan, src: BounceSource, inputs: BounceInputs,
                     shader: ExitShader, level: int, *, bst: TransferSettings, filt: str) -> BounceSetLevel:
    """Trace, denoise, dilate and stage one set's level (progress stage
    "bounce", then "write"). ``bst`` = bounce.bounce_settings(settings,
    settings.bounce_rays); ``filt`` = the resolved denoiser (not "auto")."""
    st, K = ctx.settings, ctx.n_coeffs
    name, gb, skip = src.name, src.gbuffer, inputs.skip[src.index]
    t = time.perf_counter()
    if skip.all():
        return BounceSetLevel({"name": name, "level": level, "skipped": "sees no geometry",
                               "texels": int(gb.n), "rays_traced": 0, "hits_shaded": 0}, None, None, 0.0)

    def on_progress(done, total, rays):
        ctx.emit(type="progress", stage="bounce", set=name, level=level, fraction=done / max(total, 1), rays=rays)

    tex, mask, stats = bake_bounce_set(geo.rays, gb, src.points, skip, shader, bst, level,
                                       progress=on_progress, cancel=ctx.cancel)
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
    attrs = dict(plan.exr_attrs(st), level=level, rays=st.bounce_rays, light_hash=plan.light_hash,
                 materials_hash=plan.materials_hash, texels=int(gb.n))
    with numpy_hugepage_advice(False):      # fresh arrays, streamed once
        dilate(tex, mask, st.dilate, executor=ctx.helpers)
        half = write_planes(ctx, fname, tex, "bounce", attrs, rgb=True)
    nxt = None
    if level < st.bounces:
        nxt = tex.reshape(3 * K, -1)[:, inputs.surface[src.index].valid].T.reshape(-1, 3, K)
    stats.update(name=name, level=level, file=fname, storage="half" if half else "float")
    ctx.seconds["bounce_write"] += time.perf_counter() - t
    return BounceSetLevel(stats, fname, nxt, energy)


def bounce_levels(ctx: BakeContext, geo: Geometry, plan: BakePlan, sources: list[BounceSource]) -> BounceResult:
    """Bake levels 1..settings.bounces of every set in ``sources`` (the sets
    with texels, in bake order), stopping early below settings.bounce_tolerance
    (an "info" event says so)."""
    st = ctx.settings
    bst = bounce_settings(st, st.bounce_rays)
    filt = denoise.resolve_filter(st.bounce_denoise, st.bounce_rays)
    reports, files = [], []
    inputs, Lp = bounce_inputs(ctx, sources)
    stopped = None
    for level in range(1, st.bounces + 1):
        ctx.check_cancel()
        shader = level_shader(ctx, inputs, Lp)
        nxt, energy = {}, 0.0
        for src in sources:
            ctx.check_cancel()
            out = bounce_set_level(ctx, geo, plan, src, inputs, shader, level, bst=bst, filt=filt)
            reports.append(out.report)
            if out.file is not None:
                files.append(out.file)
            if out.incident is not None:
                nxt[src.index] = out.incident
            energy += out.energy
        del shader
        Lp = nxt
        if not Lp:
            break
        ratio = energy / inputs.direct if inputs.direct > 0 else 0.0
        if level < st.bounces and ratio < st.bounce_tolerance:
            stopped = {"after_level": level, "energy_ratio": ratio, "tolerance": st.bounce_tolerance,
                       "levels_not_baked": st.bounces - level}
            ctx.emit(type="info", message=f"bounce level {level} carries {100 * ratio:.3g} % of the direct "
                     f"light (< {100 * st.bounce_tolerance:g} %): levels {level + 1}-{st.bounces} "
                     f"are not baked")
            break
    return BounceResult(reports, files, stopped)
