"""What a bake will hold in memory, estimated before it starts, stage by stage
(memory_check.check_memory checks the largest against the memory available,
base/memory.check_fits; the manifest's ``memory`` records it beside the peak
each stage measured).

The model follows what each stage holds (stages.py, bounce_stage.py,
relightable_stage.py), per texture set of A = W x H texels of which N are
covered (estimated from the UV layout's area: :func:`covered_texels`) and V
hold a value once dilated (N and the dilation rings around every island).
K = bands², C the relightable channels (3K + the glossy rows). Bytes:

* every stage: the process (Python, numpy, numba's kernels, Embree: BASE),
  the scene's arrays and its BVH (:func:`scene_bytes`; from the G-buffer
  stage on also the geometry's per-triangle tables, GEOMETRY), what the process
  already holds beyond a bare bake worker and its job (:func:`process_extra`:
  a CLI's or a test runner's imports), and on a bake that compiles the
  bounce's kernels (nothing cached yet) what the compiler keeps;
* G-buffer: the G-buffer and its rasteriser's temporaries, GBUFFER_BUILD a texel;
* trace: the G-buffer and kernel points (SURFACE a texel) and the traced rows
  4 K N; projection: the float32 planes 4 K A (the rows are consumed into
  them) beside the G-buffer's layout (LAYOUT a texel) and what the bounce
  keeps of the surface;
* write: the planes, given back a band at a time as the file is written
  (exr_io.write_sh_planes), while the texture at its valid texels (4 K V)
  fills when the bake bounces: the two are not both whole. Beside them one
  band of rows in the file's type (B, a band's file bytes: exr_io.write_band_rows
  rows, about WRITE_BAND_BYTES) and OpenEXR's line buffers (exr_io.writer_bytes:
  a few hundred of the file's rows, with its threads);
* bounce (relightable), the largest of two moments. Its inputs: on the
  transfer's grid the texture (4 K V) and the albedo (FINE_DIFFUSE a valid
  texel), while the bounce grid (1/f per side: A/f², N/f², V/f² texels) gets
  its G-buffer (GBUFFER_BUILD) and block means (4 K V/f²). Its trace: the
  diffuse exit table 4 K V and its scales (FINE_SCALE V + 4 A), on the bounce
  grid the G-buffer and points, the glossy exit table 4 Kg² V and its
  scales and normals (EXIT_SCALES), and each set's traced columns: one level
  waits in a temporary file (estimators.column_spill), only its DC responses in
  memory (12 B a covered texel); more levels hold 4 C N each and the
  surface (SURFACE_SHADING a valid texel). Baked bounces hold the level's
  (3K, A) planes and exit rows instead;
* write relight: each set's relightable texture made a band of rows at a
  time from its levels' columns (texels.dilate.DilatedRows: a float32 band
  per level summed with its dilation rings, 1.25 x its float32 bytes each, the
  file's band B and
  OpenEXR's line buffers for its C channels),
  beside every set's G-buffer (SURFACE N) and, with more than one level, the
  levels' columns (4 C N/f² each; one level is read from its file);
* sets baked earlier keep, when bouncing, their surface and texture (SURFACE
  N + 4 K V; with a coarser bounce grid the albedo instead of the surface,
  FINE_DIFFUSE V + 4 K V) until the bounce.

The constants are measured (bench memory: the demo room at 512² to 4096²,
the 1.27M-triangle room and bunnies); docs/benchmarks.md tabulates the
estimate against the measured peak.
"""
from __future__ import annotations

import math

import numpy as np

from ...io.exr_io import write_band_rows, writer_bytes
from ...light.sun import SUN_RAYS
from ..estimators.guided import guide_build_bytes, guide_bytes
from ..estimators.guided_filter import filter_bytes
from ..estimators.sun_edge import edge_bytes
from ..estimators.sun_mask import mask_bytes
from ..estimators.validity import validity_bytes

#: Bytes a texel of a sun's edge planes costs while they are filled and written:
#: three float32 planes and their dilation's copy.
EDGE_PLANES = 3 * 4 * 2
#: Bytes a texel of the grid costs per lamp while its masks are filled and
#: written (sun_stage._lamp_set): a float32 plane and its dilation's copy.
LAMP_PLANE = 4 * 2

MiB = 1 << 20

#: The bake process before any set: interpreter, numpy, numba's compiled kernels, Embree's allocator.
BASE = 150 * MiB
#: What numba's compiler keeps resident once it has compiled the bounce's kernels (a first bake
#: after installing or updating PRTT; later bakes load them from numba's cache): measured 55-58 MB.
JIT_COMPILE = 60 * MiB
#: What a bake worker holds once its job is loaded, beyond the job's arrays (interpreter, numpy,
#: embreex imported): measured 62 MB at the "setup" stage of bench memory's worker.
BARE_PROCESS = 64 * MiB
#: What importing numba (llvmlite, PRTT's kernels module) adds to a process: measured 59 MB
#: (the worker's venv here; a freshly installed one measured 98 MB, process_extra counts the rest).
NUMBA_IMPORT = 60 * MiB
#: What a Dask client adds to the bake process (dask and distributed imported, the client's I/O loop):
#: measured 31 MiB (the demo's "dask" stage against a local bake's "setup", 1024² and 2048²).
DASK_CLIENT = 32 * MiB
#: Copies of the exit tables a Dask client holds while it scatters them to the workers.
DASK_COPIES = 1.5
#: Bytes a scene triangle holds: the job's arrays (positions, normals, UVs, ids) and Embree's BVH.
TRIANGLE = 400
#: Bytes a triangle adds from the analytic test on (its face data and clear tables, the hit
#: shading's UV frames): measured 316 on the 1.27M-triangle room and bunnies (its
#: "analytic-test" stage against its "bvh" stage), counted from the G-buffer stage on.
GEOMETRY = 300
#: The G-buffer while it is built: the merged arrays and the row bands' rasteriser temporaries.
GBUFFER_BUILD = 240
#: A covered texel's G-buffer (position, normals, barycentrics, ids: 117 B) and kernel points (17 B).
SURFACE = 134
#: A valid texel's shading on the bounce grid: albedo, spec, exponent, normal (float64), exit scales.
SURFACE_SHADING = 120
#: A valid texel of the transfer's grid that level 1's diffuse light leaves from: albedo, texel id, row.
FINE_DIFFUSE = 40
#: What the diffuse exit table keeps of it through the trace: the scales (float32 RGB).
FINE_SCALE = 12
#: A valid texel of the glossy exit table's grid: its colour scales and normal (float32).
EXIT_SCALES = 24
#: A covered texel's G-buffer layout kept once its surface is dropped (texel id, coverage).
LAYOUT = 12
#: Dilation rings: V = N (1 + RING * dilate / sqrt(A)) (the islands' perimeters in texels).
RING = 18.0
#: Covered texels: N = UV area x A + EDGE x the islands' boundary length x sqrt(A) (conservative
#: rasterisation of island edges: measured 0.52-0.63 on the demo room and the benches' room, 128² to 1024²).
EDGE = 0.55
#: One trace thread's ray chunk: rays x (origin, direction, hits) bytes.
RAY_BYTES = 66


def covered_texels(uv_area: float, width: int, height: int, boundary: float = 0.0) -> int:
    """Texels a UV layout of total area ``uv_area`` and island boundary length
    ``boundary`` (unit square: area 1, side 1) covers at W x H."""
    A = width * height
    return int(min(A, uv_area * A + EDGE * boundary * math.sqrt(max(A, 1))))


def uv_boundaries(uvs: np.ndarray, set_id: np.ndarray, n_sets: int) -> np.ndarray:
    """(S,) length of each set's UV island boundaries: the UV edges only one
    triangle has (endpoints matched to 2^-20; a hashed key, so a rare
    collision only moves the estimate)."""
    uv = np.asarray(uvs, np.float64)
    a, b = uv, np.roll(uv, -1, axis=1)                                           # (T, 3, 2) edge ends
    q = np.round(np.concatenate([a, b], axis=2).reshape(-1, 4) * (1 << 20)).astype(np.int64)
    swap = (q[:, 0] > q[:, 2]) | ((q[:, 0] == q[:, 2]) & (q[:, 1] > q[:, 3]))
    q[swap] = q[swap][:, [2, 3, 0, 1]]
    key = (q[:, 0] * np.int64(73856093)) ^ (q[:, 1] * np.int64(19349663)) ^ (q[:, 2] * np.int64(83492791)) \
        ^ (q[:, 3] * np.int64(2654435761))
    sid = np.repeat(np.asarray(set_id), 3)
    key = key ^ (sid.astype(np.int64) * np.int64(0x9E3779B97F4A7C15 & 0x7FFFFFFFFFFFFFFF))
    _, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    once = (cnt[inv.reshape(-1)] == 1) & (sid >= 0)
    length = np.linalg.norm((b - a).reshape(-1, 2), axis=1)
    ok = once & np.isfinite(length)
    return np.bincount(sid[ok], weights=length[ok], minlength=n_sets)[:n_sets]


def valid_texels(covered: int, width: int, height: int, dilate: int) -> int:
    """Texels that hold a value once ``dilate`` rings are grown around ``covered`` ones."""
    A = width * height
    return int(min(A, covered * (1.0 + RING * dilate / math.sqrt(max(A, 1)))))


def uv_areas(uvs: np.ndarray, set_id: np.ndarray, n_sets: int) -> np.ndarray:
    """(S,) total UV area of each set's triangles (uvs (T, 3, 2), set_id (T,), -1 = not baked)."""
    uv = np.asarray(uvs, np.float64)
    a = 0.5 * np.abs((uv[:, 1, 0] - uv[:, 0, 0]) * (uv[:, 2, 1] - uv[:, 0, 1])
                     - (uv[:, 2, 0] - uv[:, 0, 0]) * (uv[:, 1, 1] - uv[:, 0, 1]))
    sid = np.asarray(set_id)
    ok = (sid >= 0) & np.isfinite(a)
    return np.bincount(sid[ok], weights=a[ok], minlength=n_sets)[:n_sets]


def process_extra(resident: int | None, job_arrays: int, after_imports: int | None = None) -> int:
    """Bytes this process holds beyond what BASE assumes of it: its resident
    memory before the bake (``resident``, memory.resident_bytes; None:
    unknown) less a bare worker (BARE_PROCESS) and its job's arrays
    (``job_arrays`` bytes, counted by scene_bytes), plus what numba's import
    took beyond NUMBA_IMPORT (``after_imports``: the resident memory after
    the check imported it; None or equal: not imported). A bake run in a CLI
    or a test process that imported more holds that through every stage; a
    freshly installed environment's numba import measured 98 MB against 51
    (CI's "setup" stage: 142-148 MB against 98)."""
    if resident is None:
        return 0
    extra = max(0, int(resident) - BARE_PROCESS - int(job_arrays))
    if after_imports is not None and after_imports - resident > 16 * MiB:
        extra += max(0, int(after_imports) - int(resident) - NUMBA_IMPORT)
    return extra


def band_bytes(channels: int, width: int, height: int, half: bool = True) -> int:
    """File bytes of one band of rows the EXR writer holds (exr_io.write_band_rows,
    at most the whole texture) of a ``channels`` x ``width`` x ``height`` texture."""
    rows = min(int(height), write_band_rows(channels, width, half))
    return int(channels) * int(width) * rows * (2 if half else 4)


def scene_bytes(n_triangles: int) -> int:
    """The scene's arrays and Embree's BVH (per triangle)."""
    return TRIANGLE * int(n_triangles)


def stage_bytes(sets, *, bands: int, dilate: int, n_triangles: int, threads: int = 2,
                chunk_rays: int = 1 << 19, rays: int = 256, bounce_rays: int = 64, mips: bool = False, bounces: int = 0,
                bounce_mode: str = "relightable", downscale: int = 1, relight_channels: int = 0,
                glossy_coeffs: int = 0, compiling: bool = False, extra: int = 0,
                dask: bool = False, half: bool = True, guiding: bool = False,
                validity: bool = False, sun: bool = False, sun_detail: int = 1,
                sun_edges: bool = False, lamps: int = 0) -> dict[str, int]:
    """Estimated peak bytes of each stage of a bake.

    sets : (width, height, covered texels) per texture set being baked, in bake order.
    rays, bounce_rays : rays per texel of the transfer and of a bounce level.
    bounces : levels baked (0: none); downscale: the bounce grid's 1/f per
    side (bounce_stage.asked_downscale), or one per set once their grids are
    chosen (bounce_stage.choose_grid); relight_channels: C of a
    relightable texture; glossy_coeffs: Kg² of its glossy exit table (0: none);
    compiling: numba compiles the bounce's kernels in this process (JIT_COMPILE
    from the start: they are compiled on a helper thread while the first set is).
    extra: bytes the process holds beyond BASE's assumption (:func:`process_extra`).
    half: the textures are written as half floats (the write's band bytes).
    guiding: rays are guided toward openings (estimators/guided.py: building
    the guide holds ~64 B a traced point before the rows exist, its tables and
    cells are held through the trace; its chunks hold ~45 B a ray at 5 bands,
    within the transfer's RAY_BYTES, and project their coefficients a few MB
    at a time; the guided texels' filter then holds two bands of rows, guided_filter.filter_bytes).
    validity: texel validity runs before each set's trace (estimators/validity.py: its chunks of
    rays and the inside regions' labels, validity.validity_bytes).
    sun: each set's sun mask is traced after its transfer, beside its rows (pipeline/sun_stage.py,
    sun_mask.mask_bytes); with ``sun_detail`` f > 1 on a G-buffer of its own, f² as many texels,
    once the set's rows are written (stages.sun_detail_set): its build, then its surface beside
    validity's pass and the mask's. sun_edges: the mask's sub-texel edges are found after its trace
    (sun_edge.edge_bytes) and filled into three planes (EDGE_PLANES a texel of the grid).
    lamps: point and spot lamps whose masks are traced in the same pass, one
    at a time (mask_bytes each), into LAMP_PLANE a texel each (``sun`` is then
    true, with or without a sun).
    dask: the rays are traced on a Dask cluster (the client's share: DASK_CLIENT,
    and while a level's exit tables are sent to the workers, Dask's serialised
    copy of them beside them; a worker's own need is checked before each pass,
    executors/dask_worker.check_worker_memory).
    Returns {stage: bytes} with the stage names of the manifest's ``memory``.
    """
    K = bands * bands
    base = (BASE + scene_bytes(n_triangles) + (JIT_COMPILE if compiling else 0) + max(0, int(extra))
            + (DASK_CLIENT if dask else 0))
    threads = max(1, threads)

    def chunks(texels: int, per_texel: int) -> int:
        # A thread's chunk holds chunk_rays, or all of a small set's rays shared out.
        return threads * min(chunk_rays, -(-texels * per_texel // threads)) * RAY_BYTES
    out = {"setup": base, "gbuffer": 0, "trace": 0, "write transfer": 0}
    # From the analytic test on, every stage holds the geometry's per-triangle tables too.
    base += GEOMETRY * int(n_triangles)
    held = 0                                   # what earlier sets keep for the bounce
    per_set = downscale if isinstance(downscale, (list, tuple)) else [downscale] * len(sets)
    for (w, h, n), f in zip(sets, per_set):
        A = w * h
        v = valid_texels(n, w, h, dilate)
        planes = 4 * K * A * (4 / 3 if mips else 1)
        out["gbuffer"] = max(out["gbuffer"], base + held + GBUFFER_BUILD * n)
        # A coarser bounce grid keeps the albedo, not the surface (stages.transfer_set).
        surface = (FINE_DIFFUSE * v if f > 1 else SURFACE * n) if bounces else 0
        # The rows are consumed into the planes as they are projected: the trace's and
        # the projection's holdings are not both whole.
        projection = base + held + int(planes) + LAYOUT * n + surface
        guide = guide_bytes(n) if guiding else 0
        # The guide is built before the rows exist (its cells' search), then held through the trace.
        build = base + held + SURFACE * n + guide_build_bytes(n) if guiding else 0
        # The guided texels' filter runs on the rows once they are traced (estimators/guided_filter.py).
        smooth = base + held + SURFACE * n + 4 * K * n + guide + filter_bytes(w, K, h) if guiding else 0
        # Texel validity runs before the trace, beside the G-buffer's surface (estimators/validity.py).
        valid_pass = base + held + SURFACE * n + validity_bytes(w, h, n, threads) if validity else 0
        # The sun's mask is traced once the rows are, beside them (pipeline/sun_stage.py).
        # Its edges (sun_edge.py) after the trace, then their three planes (EDGE_PLANES a texel).
        sun_pass = (base + held + SURFACE * n + 4 * K * n + guide + max(
            mask_bytes(w, h, n, threads, chunk_rays, SUN_RAYS, refine=True),
            (edge_bytes(n) + EDGE_PLANES * w * h) if sun_edges else 0)
            + LAMP_PLANE * lamps * w * h) if sun and sun_detail == 1 else 0
        if sun and sun_detail > 1:
            fw, fh, fn = w * sun_detail, h * sun_detail, n * sun_detail * sun_detail
            kept = held + ((surface + 4 * K * v) if bounces else 0)         # this set's bounce source too
            sun_pass = base + kept + max(GBUFFER_BUILD * fn, SURFACE * fn + max(
                validity_bytes(fw, fh, fn, threads) if validity else 0,
                mask_bytes(fw, fh, fn, threads, chunk_rays, SUN_RAYS, refine=True),
                (edge_bytes(fn) + EDGE_PLANES * fw * fh) if sun_edges else 0) + LAMP_PLANE * lamps * fw * fh)
        out["trace"] = max(out["trace"], base + held + SURFACE * n + 4 * K * n + chunks(n, rays) + guide,
                           projection, build, smooth, valid_pass, sun_pass)
        # The planes are given back as the texture at its valid texels fills (4 K V < 4 K A);
        # beside them the band in the file's type and OpenEXR's copy of it.
        out["write transfer"] = max(out["write transfer"], projection + band_bytes(K, w, h, half)
                                    + writer_bytes(K, w, half, "transfer"))
        held += (surface + 4 * K * v) if bounces else 0
    if bounces:
        total = base + chunks(max((n for _, _, n in sets), default=0), bounce_rays)
        inputs, build = base, 0
        table = 4 * min(bounces, 2)
        for (w, h, n), f in zip(sets, per_set):
            f = max(1, int(f))
            f2 = f * f
            A = w * h
            v = valid_texels(n, w, h, dilate)
            wc, hc = max(1, w // f), max(1, h // f)
            nc = max(1, n // f2)
            vc = valid_texels(nc, wc, hc, dilate)
            if bounce_mode == "relightable":
                # One level: its columns wait in a file, its 3 DC responses in memory;
                # more: every level's columns, and the surface the next level's exit reads.
                columns = 12 * nc if bounces == 1 else int(table * relight_channels * nc) + SURFACE_SHADING * vc
                if bounces > 1:
                    # The next level's rows (RelightRows: dc (3, K), glossy per colour) made from
                    # the dilated columns (C channels) beside them, kept while that level traces.
                    columns += 4 * relight_channels * vc + 12 * (K + glossy_coeffs) * vc
                total += SURFACE * nc + EXIT_SCALES * vc + 4 * glossy_coeffs * vc + columns + 12 * wc * hc
                exits = 4 * glossy_coeffs * vc + 24 * vc
                # The inputs: the coarse grid's G-buffer built and its block means taken
                # beside the transfer's texture and albedo.
                inputs += 4 * K * v + (FINE_DIFFUSE * v + SURFACE * nc + SURFACE_SHADING * vc + 4 * K * vc
                                       if f2 > 1 else SURFACE * n + SURFACE_SHADING * v)
                build = max(build, GBUFFER_BUILD * nc if f2 > 1 else 0)
            else:
                total += SURFACE * nc + SURFACE_SHADING * vc + 4 * 3 * K * (wc * hc + 2 * vc)
                exits = 4 * 3 * K * vc
            total += 4 * K * v + FINE_SCALE * v + 4 * A if f2 > 1 else 4 * K * v
            if dask:
                # Dask serialises what it scatters as it sends it: measured as 1.0 copy of the
                # exit tables at 1024² and 1.6 at 2048² (the client's peak against a local
                # bake's, bench memory), not traced further: DASK_COPIES of them.
                total += int(DASK_COPIES * (exits + 4 * K * v + 12 * v))
        out["bounce"] = max(total, inputs + build) if bounce_mode == "relightable" else total
        if bounce_mode == "relightable":
            # The sums are written set by set once every level is traced: what each set keeps
            # until its turn, and the largest set's band (a float32 band per level, the file's).
            levels = max(1, int(bounces))
            kept, band = 0, 0
            for (w, h, n), f in zip(sets, per_set):
                f = max(1, int(f))
                wc, hc, nc = max(1, w // f), max(1, h // f), max(1, n // (f * f))
                kept += SURFACE * n + (4 * relight_channels * nc * levels if levels > 1 else 0)
                b = band_bytes(relight_channels, wc, hc, half)
                f32 = b * (2 if half else 1)           # the band as float32, as DilatedRows makes it
                band = max(band, int(1.25 * f32 * min(levels, 2)) + b + writer_bytes(relight_channels, wc, half,
                                                                                     "relight"))
            out["write relight"] = base + kept + band
    return out


def floor_bytes(set_resolution, *, bands: int, n_triangles: int) -> int:
    """A lower bound of any bake's peak, from the set sizes alone (no UV
    layout yet): the process, the scene and the float32 channel planes of the
    largest set, which the projection holds whatever the coverage. A job
    refused by it would truly not fit (the worker's check before loading)."""
    K = bands * bands
    largest = max((int(w) * int(h) for w, h in np.asarray(set_resolution).reshape(-1, 2).tolist()), default=0)
    return BASE + scene_bytes(n_triangles) + 4 * K * largest


def peak_stage(stages: dict[str, int]) -> tuple[str, int]:
    """(stage, bytes) of the largest estimate."""
    name = max(stages, key=stages.get)
    return name, stages[name]
