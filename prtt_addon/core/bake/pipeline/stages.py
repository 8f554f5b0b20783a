"""The transfer stages of a bake, each callable alone (e.g. on a worker machine).

After plan.plan_bake:

1. geometry   :func:`build_geometry` -> :class:`Geometry` (Embree BVH, per-face
   data); :func:`start_gbuffer` / :func:`start_tables` overlap it with the
   first G-buffer and the ray tables on helper threads.
2. per texture set (:func:`transfer_set` chains these):
   :func:`gbuffer_stage` -> texels.gbuffer.GBuffer;
   :func:`check_gbuffer` -> the set's report (warnings, empty sets);
   :func:`trace_set` -> :class:`SetRows` (transfer rows of the covered texels);
   :func:`project_rows` -> :class:`SetPlanes` (channel planes + coverage mask);
   :func:`mip_and_dilate` (mips from the undilated planes, then dilation);
   :func:`write_set` -> :class:`SetFiles` (staged EXRs).
   A bounce-only re-bake reads the transfer instead: :func:`load_transfer_set`.
3. vertex transfer: :func:`vertex_stage` -> :class:`VertexResult`.

Then bounce_stage.bounce_levels and commit.make_manifest / commit_bake.

Conventions: SH coefficient index k = l² + l + m, K = bands² per colour. A
transfer coefficient is dimensionless (the SH projection of visibility x
max(0, cos θ) over the sphere: lit by radiance SH L it gives irradiance
T · L). Texel index = row * W + column, row 0 at the bottom (v up); channel
planes are (C, H, W) float32, texel rows (N, C) float32 in ``gb.texel`` order.
"""
from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import os
import time

import numpy as np

from ...base.errors import BakeError, Cancelled
from ...base.memory import release_free_memory
from ...io import exr_io
from ...model.scene import Scene
from ...texels.dilate import dilate, grown_mask, mip_chain
from ...texels.gbuffer import GBuffer, build_gbuffer, face_normals
from ...texels.texsample import planes_from_rows
from ..estimators import guided_filter, validity
from ..estimators.bounce import (
    HALF_OPEN_TOLERANCE,
    OPEN_TOLERANCE,
    IncidentSet,
    SurfaceTexels,
    open_texels,
    surface_texels,
)
from ..estimators.hemisphere_clear import FLAT_COS, clear_triangles
from ..estimators.raytrace import RayScene, surface_area
from ..estimators.transfer import SAME_NORMAL, Points, bake_points, warm_tables
from .context import BakeContext
from .plan import BakePlan
from .sun_stage import sun_set

# --- per-face data and the kernel's input ------------------------------------------------

def scene_face_data(sc: Scene, *, analytic: bool = True,
                    cancel=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Per-triangle data every set of a bake needs.

    Returns (face normals (T, 3) turned to the shaded side (the mean corner
    normal), zero for degenerate faces; normal group (T,) int64, equal for
    faces whose oriented normals agree to 1e-9, -1 for degenerate ones;
    clear (T,) bool from hemisphere_clear; its stats).
    """
    def check():
        if cancel is not None and cancel.is_set():
            raise Cancelled()

    fn, _ = face_normals(sc.positions)
    mean_n = sc.normals.astype(np.float64).sum(axis=1)
    fn = np.where((np.einsum("tc,tc->t", fn, mean_n) < 0)[:, None], -fn, fn)
    baked = np.flatnonzero((sc.set_id >= 0) & np.any(fn != 0, axis=1))
    normal_group = np.full(sc.n_triangles, -1, np.int64)
    check()
    if baked.size:
        _, inv = np.unique(np.round(fn[baked], 9), axis=0, return_inverse=True)
        normal_group[baked] = inv.reshape(-1)
    check()
    clear = np.zeros(sc.n_triangles, bool)
    stats = {}
    if analytic:
        clear, stats = clear_triangles(sc.positions, fn, candidates=np.flatnonzero(sc.set_id >= 0),
                                       cancel=cancel)
    return fn, normal_group, clear, stats


def bake_points_input(sc: Scene, set_index: int, gb: GBuffer, fn: np.ndarray, clear: np.ndarray,
                      normal_group: np.ndarray) -> Points:
    """The transfer kernel's input for one set's G-buffer.

    Texels use the zero-ray analytic path where their triangle is clear, flat
    shaded and not normal-mapped; flat-shaded texels of faces with a common
    normal form frame groups (see transfer.py, "Shared frames"). Point ids are
    the texel index tagged with the set, so patterns never repeat across sets.
    """
    cos = np.einsum("nc,nc->n", gb.normal, gb.geo_normal)
    same_side = np.einsum("nc,nc->n", gb.geo_normal, fn[gb.tri]) > 0
    analytic = clear[gb.tri] & (cos >= FLAT_COS) & ~gb.normal_mapped & same_side
    flat = (cos >= 1.0 - SAME_NORMAL) & ~gb.normal_mapped & same_side
    group = np.where(flat, normal_group[gb.tri], -1)
    # The set's own surface: a set of one small object in a large scene sizes its guide's
    # cells by it. Its triangles by a mask, not np.unique's sort of every texel (1.6 s at 4096²).
    covered = np.zeros(sc.n_triangles, bool)
    covered[gb.tri] = True
    area = surface_area(sc.positions, np.flatnonzero(covered))
    return Points(gb.position, gb.normal, gb.geo_normal,
                  gb.texel + (np.int64(set_index) << 40), analytic, group, area)


# --- stage 1: geometry -------------------------------------------------------------------

@dataclasses.dataclass(eq=False)
class Geometry:
    """What every set traces against (build_geometry). T = scene triangles."""

    rays: RayScene | None          # Embree BVH of every triangle (normalised scene units); None when a
                                   # Dask cluster traces (ctx.remote: each worker builds its own)
    face_normal: np.ndarray        # (T, 3) float64 unit, turned to the shaded side; zero where degenerate
    normal_group: np.ndarray       # (T,) int64: equal for faces with the same normal (1e-9); -1 degenerate
    clear: np.ndarray              # (T,) bool: no geometry above the face (hemisphere_clear)
    clear_stats: dict              # hemisphere_clear's stats (the manifest's "analytic_test")

    def points(self, sc: Scene, set_index: int, gb: GBuffer) -> Points:
        """The transfer kernel's input for set ``set_index``'s G-buffer (bake_points_input)."""
        return bake_points_input(sc, set_index, gb, self.face_normal, self.clear, self.normal_group)


def build_set_gbuffer(ctx: BakeContext, set_index: int) -> GBuffer:
    """Set ``set_index``'s G-buffer, its row bands built on the helper pool
    (stops when the bake is cancelled or fails)."""
    st = ctx.settings
    return build_gbuffer(ctx.scene, set_index, normal_maps=st.normal_maps, executor=ctx.helpers,
                         bands=max(2, st.n_threads), cancel=ctx.stop)


def start_gbuffer(ctx: BakeContext, set_index: int) -> cf.Future:
    """Start set ``set_index``'s G-buffer on a helper (it overlaps the BVH build);
    pass the future to :func:`gbuffer_stage`."""
    return ctx.helpers.submit(build_set_gbuffer, ctx, set_index)


def start_tables(ctx: BakeContext) -> None:
    """Compute the ray patterns and estimator tables on a helper while the cores
    are not tracing (ctx.tables; ctx.wait_tables() before tracing)."""
    ctx.tables = ctx.helpers.submit(warm_tables, ctx.settings, ctx.stop)


def build_geometry(ctx: BakeContext) -> Geometry:
    """Build the BVH (not with a Dask cluster) and the per-face data (progress
    stages "bvh", "analytic-test")."""
    st = ctx.settings
    ctx.emit(type="progress", stage="bvh", fraction=0.0)
    t = time.perf_counter()
    # With a cluster the workers trace the transfer's and the bounce's rays; the
    # client needs a BVH only for the guided texels' pilot and rays (guided.py),
    # which it traces on its own threads (the local bake's bits either way).
    rs = (RayScene(ctx.scene.positions, cancel=ctx.cancel) if ctx.remote is None or st.guiding
          else None)
    ctx.seconds["bvh"] = time.perf_counter() - t
    t = time.perf_counter()
    if st.analytic:
        ctx.emit(type="progress", stage="analytic-test", fraction=0.0)
    fn, normal_group, clear, clear_stats = scene_face_data(ctx.scene, analytic=st.analytic, cancel=ctx.cancel)
    ctx.seconds["analytic_test"] = time.perf_counter() - t
    return Geometry(rs, fn, normal_group, clear, clear_stats)


# --- stage 2: one texture set ------------------------------------------------------------

def gbuffer_stage(ctx: BakeContext, set_index: int, pending: cf.Future | None = None) -> GBuffer:
    """Set ``set_index``'s G-buffer (progress stage "gbuffer"): ``pending``'s
    result when start_gbuffer began it, else built now."""
    t = time.perf_counter()
    ctx.check_cancel()
    ctx.emit(type="progress", stage="gbuffer", set=ctx.scene.set_names[set_index], fraction=0.0)
    gb = ctx.wait(pending) if pending is not None else build_set_gbuffer(ctx, set_index)
    release_free_memory()       # the rasteriser's temporaries, freed on helper threads
    ctx.seconds["gbuffer"] += time.perf_counter() - t
    return gb


def check_gbuffer(ctx: BakeContext, gb: GBuffer) -> dict:
    """The set's report so far (name, resolution [W, H], the G-buffer's stats).
    Warns about overlapping UV islands (BakeError with settings.overlap
    "error"), zero-area UV triangles and a set without texels (then the
    report has ``skipped: True`` and the set is not traced)."""
    name = ctx.scene.set_names[gb.set_index]
    rep = {"name": name, "resolution": [gb.width, gb.height], **gb.stats}
    if gb.stats["overlap_texels"]:
        msg = (f"set {name!r}: {gb.stats['overlap_texels']} texels are covered by overlapping "
               f"UV islands (objects: {', '.join(gb.stats['overlap_objects'])}); each keeps "
               f"one surface, the others are wrong there. Re-unwrap without overlaps.")
        if ctx.settings.overlap == "error":
            raise BakeError(msg)
        ctx.warn(msg)
    if gb.stats["zero_area_uv_triangles"]:
        ctx.warn(f"set {name!r}: {gb.stats['zero_area_uv_triangles']} triangles have zero UV area "
                 f"and get no texels (they still cast shadows)")
    if gb.n == 0:
        ctx.warn(f"set {name!r}: no texel is covered by its UV layout; skipped")
        rep["skipped"] = True
    return rep


@dataclasses.dataclass(eq=False)
class SetRows:
    """One set's traced transfer (trace_set). N = covered texels, K = bands²."""

    gbuffer: GBuffer
    points: Points | None          # the kernel's input (N points); None once released
    rows: np.ndarray | None        # (N, K) float32, row i = texel gbuffer.texel[i]; None once projected
    info: dict                     # transfer.bake_points' stats (rays_traced, analytic_points, ...)

    def release_surface(self) -> None:
        """Drop the points and the G-buffer's surface arrays (a set that does not bounce)."""
        self.points = None
        self.gbuffer.release_surface()


def trace_set(ctx: BakeContext, geo: Geometry, gb: GBuffer, *, position: int = 0,
              inside: np.ndarray | None = None) -> SetRows:
    """Trace the transfer of ``gb``'s covered texels (progress stage "trace";
    ``position`` = the set's place among ctx.set_ids, reported as set_index)
    but those ``inside`` geometry ((N,) bool: dropped and filled by the
    dilation; their rows zero). Waits for the ray tables first. Needs gb.n > 0."""
    name = ctx.scene.set_names[gb.set_index]
    pts = geo.points(ctx.scene, gb.set_index, gb)
    ctx.wait_tables()
    t = time.perf_counter()

    def on_progress(done, total, rays):
        ctx.emit(type="progress", stage="trace", set=name, fraction=done / max(total, 1), rays=rays,
                 rays_per_s=rays / max(time.perf_counter() - t, 1e-9), set_index=position,
                 sets=len(ctx.set_ids))

    # Chunks write whole rows (N, K) (a chunk's texels are scattered over the
    # atlas; K separate plane writes per texel cost more than the trace glue).
    rows, info = bake_points(geo.rays, pts, ctx.settings, progress=on_progress, cancel=ctx.cancel,
                             remote=ctx.remote, skip=inside)
    ctx.seconds["trace"] += time.perf_counter() - t
    return SetRows(gb, pts, rows, info)


@dataclasses.dataclass(eq=False)
class SetPlanes:
    """One set's transfer texture (project_rows, then mip_and_dilate).

    ``mips`` (empty until mip_and_dilate, and without settings.mips): level k =
    1, 2, .. as (planes (K, H_k, W_k) float32, coverage weight (H_k, W_k)
    float64), sizes halving (rounded up) down to 1 x 1 (texels.dilate.mip_chain).
    """

    planes: np.ndarray             # (K, H, W) float32 channel planes, zero where no texel (until dilated)
    mask: np.ndarray               # (H, W) bool: covered texels
    mips: list[tuple[np.ndarray, np.ndarray]] = dataclasses.field(default_factory=list)
    grown: np.ndarray | None = None   # (H, W) bool: the texels that hold a value once dilated


def project_rows(ctx: BakeContext, traced: SetRows, *, keep_rows: bool = True,
                 visit=None) -> SetPlanes:
    """The set's channel planes holding its texel rows, zero elsewhere. The
    rows are consumed as they are placed (texsample.planes_from_rows: rows
    and planes are never both whole in memory; traced.rows becomes None);
    ``visit(a, b)`` reads rows a..b - 1 first (the bounce's open texels).

    keep_rows False (a set that does not bounce): the points and the
    G-buffer's surface are dropped before the planes are allocated
    (traced.points becomes None)."""
    t = time.perf_counter()
    if not keep_rows:
        traced.release_surface()
    gb = traced.gbuffer
    texel = gb.texel
    tex = planes_from_rows(texel, traced.rows, gb.height * gb.width, executor=ctx.helpers, visit=visit,
                           consume=True).reshape(ctx.n_coeffs, gb.height, gb.width)
    traced.rows = None
    mask = np.zeros(gb.height * gb.width, bool)
    mask[texel] = True
    ctx.seconds["dilate"] += time.perf_counter() - t
    return SetPlanes(tex, mask.reshape(gb.height, gb.width))


def mip_and_dilate(ctx: BakeContext, sp: SetPlanes, gb: GBuffer, inside: np.ndarray | None = None) -> SetPlanes:
    """With settings.mips, the coverage-weighted mip levels of the undilated
    planes (weights: gb.coverage); then settings.dilate rings of dilation, in
    place. ``inside`` (N,) bool (settings.texel_validity: validity.inside_texels):
    those texels are emptied first, so the dilation fills them from their
    valid neighbours and the mips leave them out. Returns ``sp``."""
    st = ctx.settings
    t = time.perf_counter()
    if inside is not None and inside.any():
        drop = gb.texel[inside]
        sp.planes.reshape(sp.planes.shape[0], -1)[:, drop] = 0.0
        sp.mask.reshape(-1)[drop] = False
    if st.mips:
        cov = np.zeros(gb.height * gb.width, np.float32)
        cov[gb.texel] = gb.coverage
        if inside is not None:
            cov[gb.texel[inside]] = 0.0
        sp.mips = mip_chain(sp.planes, cov.reshape(gb.height, gb.width))
    sp.grown = dilate(sp.planes, sp.mask, st.dilate, executor=ctx.helpers)
    ctx.seconds["dilate"] += time.perf_counter() - t
    return sp


def write_planes(ctx: BakeContext, fname: str, planes: np.ndarray, kind: str, attrs: dict, *, rgb: bool,
                 half: bool | None = None, names: list[str] | None = None, bands: int | None = None,
                 consume: bool = False, visit=None) -> bool:
    """Write ``planes`` (C, H, W), or a source that makes them a band of rows
    at a time (texels.dilate.DilatedRows), as staged output ``fname`` (progress stage
    "write"); half precision (settings.half unless given) unless values
    overflow it (a warning, then float32). ``consume``: the caller is done
    with ``planes``, which give their memory back band by band as they are
    written (exr_io.write_sh_planes) and read as zeros afterwards;
    ``visit(y0, band)`` sees each band of rows first. Returns whether it was written as half."""
    ctx.check_cancel()
    ctx.emit(type="progress", stage="write", file=fname, fraction=0.0)
    half = ctx.settings.half if half is None else half
    if hasattr(planes, "band"):            # made a band of rows at a time (texels.dilate.DilatedRows)
        rng = planes.value_range()
        over = half and not (-exr_io.HALF_MAX <= rng[0] and rng[1] <= exr_io.HALF_MAX)
        if over:
            ctx.warn(f"{fname}: values up to {max(-rng[0], rng[1]):.6g} exceed the half-float range; "
                     f"stored as float32")
    else:
        rng = exr_io.value_range(planes, ctx.helpers)
        over = exr_io.half_overflow(planes, rng) if half else 0
        if over:
            ctx.warn(f"{fname}: {over} values exceed the half-float range; stored as float32")
    if over:
        half = False
    # Tuning auto rounds the half coefficients of bands l >= 1 (context.AUTO_MANTISSA_BITS),
    # and every relightable channel but the DC-to-DC one.
    exr_io.write_sh_planes(ctx.staging.path(fname), planes, kind=kind, half=half, rgb=rgb,
                           attrs=attrs, atomic=False, executor=ctx.helpers, rng=rng, names=names, bands=bands,
                           mantissa_bits=ctx.settings.storage_bits(),
                           full_bits=None if names is None else exr_io.relight_full_bits(names),
                           consume=consume, visit=visit)
    return half


@dataclasses.dataclass
class SetFiles:
    """What write_set staged: ``<set>.transfer.exr`` then ``<set>.transfer.mip<k>.exr``."""

    files: list[str]               # file names in the output folder
    half: bool                     # stored as float16 (all of the set's files alike)


def write_set(ctx: BakeContext, plan: BakePlan, gb: GBuffer, sp: SetPlanes, info: dict, *,
              visit=None) -> SetFiles:
    """Stage the set's transfer texture and its mips (the mips in the texture's
    precision). Consumes ``sp``: its planes give their memory back as they are
    written and read as zeros afterwards (write_planes); ``visit(y0, band)``
    sees each band of the texture's rows first."""
    st = ctx.settings
    name = ctx.scene.set_names[gb.set_index]
    t = time.perf_counter()
    attrs = dict(plan.exr_attrs(st), kind_detail="visibility*cosine", dilate=st.dilate,
                 texels=int(gb.n), analytic_texels=info["analytic_points"])
    fname = f"{name}.transfer.exr"
    ctx.check_cancel()
    half = write_planes(ctx, fname, sp.planes, "transfer", attrs, rgb=False, consume=True, visit=visit)
    files = [fname]
    for lvl, (mt, _) in enumerate(sp.mips, start=1):
        mname = f"{name}.transfer.mip{lvl}.exr"
        write_planes(ctx, mname, mt, "transfer", dict(attrs, mip_level=lvl), rgb=False, half=half, consume=True)
        files.append(mname)
    ctx.seconds["write"] += time.perf_counter() - t
    return SetFiles(files, half)


@dataclasses.dataclass(eq=False)
class BounceSource:
    """What the bounce levels need of one set's transfer (bounce_stage)."""

    index: int                     # scene set index
    name: str
    gbuffer: GBuffer               # with its surface arrays
    points: Points | None          # the transfer kernel's input (N points); None once a coarser
                                   # bounce grid replaces the set's (bounce_stage.bounce_inputs)
    open: np.ndarray               # (N,) bool: no transfer ray of the texel met geometry (bounce.open_texels,
                                   # with the tolerance of the transfer's precision: float32 traced now, or
                                   # half read from disk); these texels trace no bounce rays
    incident: IncidentSet | None   # the dilated transfer texture at the texels that hold a value;
                                   # None once the level-1 incident radiance is computed
    fine: SurfaceTexels | None = None      # the albedo where level 1's diffuse light leaves
                                           # (bounce.surface_texels diffuse_only), taken before the
                                           # write when the bounce grid is coarser; then points is
                                           # None and the G-buffer's surface released
    analytic: np.ndarray | None = None     # (N,) bool: points.analytic, kept when points is None


@dataclasses.dataclass(eq=False)
class SetResult:
    """One set's part of the bake: its manifest report and staged files."""

    index: int                     # scene set index
    name: str
    report: dict                   # the manifest's "sets" entry
    files: list[str]               # staged file names ([] when skipped or reused)
    bounce: BounceSource | None = None   # when the bake bounces and the set has texels


def transfer_set(ctx: BakeContext, geo: Geometry, plan: BakePlan, gb: GBuffer, *, position: int = 0,
                 keep_for_bounce: bool = False) -> SetResult:
    """Stage 2 for one set from its G-buffer: check, trace, project, mips and
    dilation, write; with ``keep_for_bounce`` the result carries a BounceSource."""
    rep = check_gbuffer(ctx, gb)
    name = rep["name"]
    if rep.get("skipped"):
        return SetResult(gb.set_index, name, rep, [])
    inside, step = validity_pass(ctx, geo, gb, rep)
    traced = trace_set(ctx, geo, gb, position=position, inside=inside)
    sun_files = []
    if ctx.masked and ctx.settings.sun_detail == 1:
        # Before the texture's write may release the G-buffer's points (moved by validity).
        files, sun_rep = sun_set(ctx, geo.rays, gb, inside, plan.sun_key)
        sun_files += files
        rep.update(sun_rep)
    res = _finish_transfer_set(ctx, geo, plan, gb, rep, traced, inside, step, sun_files, keep_for_bounce)
    if ctx.masked and ctx.settings.sun_detail > 1:
        # A finer mask of its own G-buffer, once this set's rows are written and given back.
        files, sun_rep = sun_detail_set(ctx, geo, plan, gb.set_index)
        res.files += files
        res.report.update(sun_rep)
    return res


def sun_detail_set(ctx: BakeContext, geo: Geometry, plan: BakePlan, set_index: int) -> tuple[list, dict]:
    """Set ``set_index``'s sun mask at settings.sun_detail f times its
    resolution per side: a G-buffer of its own over the same UV layout
    (build_gbuffer's resolution), texel validity on it, the mask dilated by f
    times the set's rings (the same gutter in UV space). Returns ([its
    files] or [], the report's sun entries, ``sun_detail`` among them)."""
    st = ctx.settings
    f = st.sun_detail
    W, H = (int(v) for v in ctx.scene.set_resolution[set_index])
    t = time.perf_counter()
    fine = build_gbuffer(ctx.scene, set_index, normal_maps=st.normal_maps, executor=ctx.helpers,
                         bands=max(2, st.n_threads), cancel=ctx.stop, resolution=(W * f, H * f))
    ctx.seconds["gbuffer"] += time.perf_counter() - t
    if not fine.n:
        return [], {}
    inside, _ = validity_pass(ctx, geo, fine, {})
    files, sun_rep = sun_set(ctx, geo.rays, fine, inside, plan.sun_key, rings=st.dilate * f)
    return files, {**sun_rep, "sun_detail": f}


def validity_pass(ctx: BakeContext, geo: Geometry, gb: GBuffer, rep: dict) -> tuple[np.ndarray | None, float]:
    """Texel validity of set ``gb`` (settings.texel_validity): (its texels
    inside geometry (N,) bool or None, the set's texel footprint in metres);
    texels beside a single-plane wall moved to its darker side, in
    ``gb.position``; ``rep`` gets the counts. The footprint is validity's
    contact distance and the guided texels' filter's (0 when neither runs)."""
    inside = None
    step = validity.texel_step(gb.texel, gb.position, gb.width) if (
        ctx.settings.texel_validity or ctx.settings.guided_filter) else 0.0
    if ctx.settings.texel_validity:
        if ctx.validity_scene is None:
            # Once per bake, not per set: the winding normals, and under Dask (no
            # local BVH in geo) the BVH the pass traces.
            ctx.validity_scene = (geo.rays if geo.rays is not None else RayScene(ctx.scene.positions),
                                  validity.winding_normals(ctx.scene.positions))
        t = time.perf_counter()
        inside = validity.inside_texels(*ctx.validity_scene, gb.position, gb.geo_normal,
                                        contact=validity.CONTACT_TEXELS * step,
                                        seed=ctx.settings.seed, executor=ctx.helpers,
                                        grid=(gb.texel, gb.width, gb.height))
        rep["inside_texels"] = int(inside.sum())
        # Texels beside a wall standing on their surface take its darker side's
        # light (no bright leak into a room under a single-plane wall).
        moved, where = validity.across_walls(*ctx.validity_scene, gb.position, gb.geo_normal, step, gb.texel,
                                             gb.width, gb.height, inside=inside, seed=ctx.settings.seed,
                                             executor=ctx.helpers)
        if moved.size:
            gb.position[moved] = where
        rep["moved_texels"] = int(moved.size)
        ctx.seconds["trace"] += time.perf_counter() - t         # with the trace, as the guided filter
    return inside, step


def _finish_transfer_set(ctx, geo, plan, gb, rep, traced, inside, step, sun_files, keep_for_bounce) -> SetResult:
    """transfer_set after the trace: the guided filter, projection, mips and
    dilation, the write, and the bounce's source."""
    name = rep["name"]
    guided_index = traced.info.pop("guided_index", None)
    if ctx.settings.guided_filter and guided_index is not None and guided_index.size:
        t = time.perf_counter()
        valid = np.ones(gb.n, bool) if inside is None else ~inside
        rep["filtered_texels"] = guided_filter.smooth_guided(
            traced.rows, gb.texel, gb.width, gb.height, gb.position, gb.normal,
            guided_index[valid[guided_index]], valid, step, executor=ctx.helpers)
        ctx.seconds["trace"] += time.perf_counter() - t
    grid = ctx.bounce_grids.get(gb.set_index) if keep_for_bounce else None
    fine = analytic = None
    if grid is not None and grid.downscale > 1:
        # The bounce traces a coarser grid: of this one it reads the open texels,
        # the analytic ones and the albedo where level 1's diffuse light leaves.
        # Taken now, the points and surface (134 B a texel) are not held through
        # the projection and the write (1.2 GB less at 4096², #35).
        is_open = open_texels(traced.rows, gb.normal, ctx.settings.bands, OPEN_TOLERANCE)
        analytic = traced.points.analytic
        # The points and positions and normals first: the albedo needs only
        # tri and bary, and is then built beside the rows without them.
        traced.points = None
        gb.release_geometry()
        fine = surface_texels(ctx.scene, gb, ctx.settings.dilate, diffuse_only=True)
        traced.release_surface()
        sp = mip_and_dilate(ctx, project_rows(ctx, traced, keep_rows=False), gb, inside)
    else:
        # The bounce reads of the rows only which texels are open: found as the rows
        # are projected (and consumed), run by run.
        is_open = np.zeros(gb.n, bool) if keep_for_bounce else None
        rows = traced.rows

        def opened(a, b):
            is_open[a:b] = open_texels(rows[a:b], gb.normal[a:b], ctx.settings.bands, OPEN_TOLERANCE)
        sp = mip_and_dilate(ctx, project_rows(ctx, traced, keep_rows=keep_for_bounce,
                                              visit=opened if keep_for_bounce else None), gb, inside)
        rows = None
    info = traced.info
    # What the bounce reads of the texture, taken band by band as the write consumes them.
    incident = None
    if keep_for_bounce:
        # The bounce reads the texture at the covered texels grown by the dilation
        # (surface_texels' valid texels, the fine albedo's): one array of them, not
        # two (100 MB at 4096², #35). Texel validity can leave some of them empty (a
        # region inside geometry wider than the rings): rows there too, zeros, as
        # IncidentSet.at would give, so that the bounce takes these rows as they are
        # instead of a copy at its texels (0.4 GB at 2048²).
        valid = fine.valid if fine is not None else (
            np.flatnonzero(grown_mask(gb.mask(), ctx.settings.dilate).reshape(-1)) if inside is not None else None)
        grown = sp.grown.reshape(-1)
        if valid is not None and int(np.count_nonzero(grown)) != int(np.count_nonzero(grown[valid])):
            valid = None               # a grown texel the surface does not have: rows of its own
        incident = IncidentSet.empty(sp.grown, ctx.n_coeffs, valid=valid)
    written = write_set(ctx, plan, gb, sp, info, visit=incident.take_band if incident is not None else None)
    sp = None
    rep.update(file=written.files[0], storage="half" if written.half else "float",
               analytic_texels=info["analytic_points"], traced_texels=info["traced_points"],
               rays_traced=info["rays_traced"], rays_naive=info["rays_naive"],
               rays_below_horizon_skipped=info["rays_below_horizon_skipped"],
               adaptive_early_stops=info["adaptive_early_stops"],
               guided_texels=info["guided_points"], pilot_rays=info["pilot_rays"],
               threads=info["threads"], trace_seconds=info["seconds"])
    res = SetResult(gb.set_index, name, rep, written.files + sun_files)
    if keep_for_bounce:
        res.bounce = BounceSource(gb.set_index, name, gb, traced.points, is_open, incident, fine, analytic)
    return res


def sun_only_set(ctx: BakeContext, geo: Geometry, plan: BakePlan, gb: GBuffer) -> tuple[list, dict]:
    """A set's sun mask where the transfer on disk is reused (only the sun
    changed, or came or went): texel validity again (the points the full bake
    traces the mask from: the same code, the same bits), then the mask;
    returns ([its file] or [], the set report's sun entries). The G-buffer's
    own positions are left as they are (a bounce re-bake reads them)."""
    if not ctx.masked or not gb.n:
        return [], {}
    if ctx.settings.sun_detail > 1:
        return sun_detail_set(ctx, geo, plan, gb.set_index)
    own = dataclasses.replace(gb, position=gb.position.copy())
    rep = {"name": ctx.scene.set_names[gb.set_index]}
    inside, _ = validity_pass(ctx, geo, own, rep)
    return sun_set(ctx, geo.rays, own, inside, plan.sun_key)


def load_transfer_set(ctx: BakeContext, geo: Geometry, gb: GBuffer, old_report: dict) -> SetResult:
    """Bounce-only re-bake: the set's transfer as written (what renders), read
    from ``<set>.transfer.exr`` in the output folder; ``old_report`` is the
    set's entry of the previous manifest (kept as it is)."""
    name = ctx.scene.set_names[gb.set_index]
    data, attrs = exr_io.read_sh_exr(os.path.join(ctx.out_dir, f"{name}.transfer.exr"))
    if data.shape[:2] != (gb.height, gb.width):
        raise BakeError(f"{name}.transfer.exr is {data.shape[1]}x{data.shape[0]}, the set is "
                        f"{gb.width}x{gb.height}: bake the transfer again")
    pm = data.reshape(gb.height * gb.width, -1)    # (H, W, K) rows are already pixel-major
    incident = IncidentSet.from_pixel_major(pm, gb.width, gb.height)
    tol = HALF_OPEN_TOLERANCE if attrs.get("storage", "half") == "half" else OPEN_TOLERANCE
    is_open = open_texels(pm[gb.texel], gb.normal, ctx.settings.bands, tol)
    src = BounceSource(gb.set_index, name, gb, geo.points(ctx.scene, gb.set_index, gb), is_open, incident)
    return SetResult(gb.set_index, name, old_report, [], bounce=src)


# --- stage 3: vertex transfer ------------------------------------------------------------

def vertex_points(sc: Scene, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique render vertices of triangles ``tris`` (indices into the scene).

    Returns (positions (V, 3) float64, unit normals (V, 3) float64 (+Z where
    the corner normal is zero), corner_vertex (len(tris), 3) int32: each
    corner's vertex). Vertices are unique by (object, position, normal)."""
    P = sc.positions[tris].reshape(-1, 3)
    Nn = sc.normals[tris].reshape(-1, 3).astype(np.float64)
    obj = np.repeat(sc.object_id[tris], 3).astype(np.float64)[:, None]
    key = np.concatenate([obj, P, Nn], axis=1)
    uniq, inverse = np.unique(key, axis=0, return_inverse=True)
    n = uniq[:, 4:7]
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(ln > 1e-6, n / np.where(ln > 0, ln, 1), [0.0, 0.0, 1.0])
    return uniq[:, 1:4], n, inverse.reshape(-1, 3).astype(np.int32)


def bake_vertex_set(ctx: BakeContext, geo: Geometry, plan: BakePlan, set_index: int) -> dict:
    """Trace the transfer at set ``set_index``'s vertices (no analytic path) and
    stage ``<set>.vertex.npz`` (docs/format.md: positions, normals (V, 3)
    float32; coeffs (V, K) float32; corner_vertex (F, 3) int32; triangles
    (F,) int64). Returns the manifest's "vertex" entry (progress stage "vertex")."""
    sc, st = ctx.scene, ctx.settings
    name = sc.set_names[set_index]
    tris = sc.triangles_of_set(set_index)
    vp, vn, corner = vertex_points(sc, tris)
    ctx.check_cancel()
    ctx.emit(type="progress", stage="vertex", set=name, fraction=0.0)
    ctx.wait_tables()
    pts = Points(vp, vn, vn, np.arange(vp.shape[0], dtype=np.int64) + (np.int64(set_index) << 40)
                 + (np.int64(1) << 62), np.zeros(vp.shape[0], bool))
    vc, info = bake_points(geo.rays, pts, dataclasses.replace(st, analytic=False), cancel=ctx.cancel,
                           remote=ctx.remote)
    vname = f"{name}.vertex.npz"
    ctx.check_cancel()
    with open(ctx.staging.path(vname), "wb") as f:
        np.savez(f, format=np.array("prtt-vertex-transfer"), version=np.array(1),
                 bands=np.array(st.bands), positions=vp.astype(np.float32),
                 normals=vn.astype(np.float32), coeffs=vc, corner_vertex=corner,
                 triangles=tris.astype(np.int64), input_hash=np.array(plan.input_hash))
    return {"name": name, "file": vname, "vertices": int(vp.shape[0]), "rays_traced": info["rays_traced"]}


@dataclasses.dataclass
class VertexResult:
    """The vertex stage's manifest entries and staged files (one per set)."""

    reports: list[dict]
    files: list[str]


def vertex_stage(ctx: BakeContext, geo: Geometry, plan: BakePlan) -> VertexResult:
    """Vertex transfer of every set being baked (settings.vertex_mode)."""
    t = time.perf_counter()
    reports = [bake_vertex_set(ctx, geo, plan, s) for s in ctx.set_ids]
    ctx.seconds["vertex"] = time.perf_counter() - t
    return VertexResult(reports, [r["file"] for r in reports])
