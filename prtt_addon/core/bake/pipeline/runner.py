"""Baking a scene: transfer textures, then bounce textures, then the manifest.

``bake_scene(scene, out_dir, settings, light=...)`` is the one code path
behind the worker, ``python -m prtt_addon bake-job`` and the Blender
operator. Outputs (docs/format.md), all staged as temporaries and renamed only
when every set is done, manifest last — a cancelled, failed or killed bake
leaves the previous outputs untouched:

* ``<set>.transfer.exr``        one per texture set (K channels sh000..)
* ``<set>.transfer.mip<k>.exr`` optional coverage-weighted mip levels
* ``<set>.vertex.npz``          optional per-vertex transfer (vertex mode)
* ``<set>.bounce<k>.exr``       inter-reflection levels k = 1..bounces (RGB SH)
* ``<set>.relight.exr``         instead, with bounce_mode "relightable": all levels as a map of the light
* ``manifest.json``             settings, per-set stats, seconds per stage, hashes

The bake is a pipeline of stages over one context object
(context.BakeContext: inputs, progress, cancellation, helper threads, staged
files, seconds, warnings); each stage is a module-level function that takes
it and returns what it made, so one stage can run alone (tests, a worker
machine). :func:`run_stages` is the order:

1. plan.plan_bake: input hashes, what the folder's outputs let it reuse (an
   identical bake is not repeated; when only the light or materials changed,
   only the bounce textures are re-baked), memory_check.check_memory;
2. stages.build_geometry: Embree BVH and per-face data (the first G-buffer
   and the ray tables start on helper threads meanwhile);
3. per texture set, stages.transfer_set: G-buffer, trace (transfer rows),
   rows to planes, mips and dilation, write (or stages.load_transfer_set for a
   bounce-only re-bake);
4. stages.vertex_stage: per-vertex transfer (vertex mode);
5. bounce_stage.bounce_levels: inter-reflection levels;
6. commit.make_manifest, commit.commit_bake: rename everything into place,
   manifest last.

One bake runs per output folder at a time (outdir.FolderLock, taken for the
whole bake); temporaries that dead bakes left there are removed when a bake
starts (atomic.remove_stale_temporaries).

Progress goes to ``progress(event: dict)`` (the worker prints these as JSON).
"""
from __future__ import annotations

import os
import threading
import time

from ...base import atomic
from ...base.errors import BakeError
from ...base.memory import numpy_hugepage_advice
from ...io.outdir import FolderBusyError, FolderLock
from ...model.scene import Scene
from ..estimators import hit_kernel
from ..executors.dask_cluster import DaskBake
from ..executors.dask_spec import parse_spec
from . import memory_plan
from .bounce_stage import bounce_levels, choose_grid
from .commit import commit_bake, finish_skipped, make_manifest
from .context import BAKE_FORMAT_VERSION, BAKE_INT_LIMITS, MANIFEST, BakeContext, BakeSettings, asked_downscale, emit
from .memory_check import bake_memory_bytes, check_memory
from .plan import (
    bounce_key,
    manifest_dicts,
    outputs_changed,
    plan_bake,
    read_manifest,
    settings_hash,
)
from .relightable_stage import relight_glossy_bands, relight_levels
from .stages import (
    SetResult,
    bake_points_input,
    build_geometry,
    gbuffer_stage,
    load_transfer_set,
    scene_face_data,
    start_gbuffer,
    start_tables,
    sun_only_set,
    transfer_set,
    vertex_stage,
)

#: What other modules and tests import from here (most of it defined in the stage modules).
__all__ = ["BAKE_FORMAT_VERSION", "BAKE_INT_LIMITS", "MANIFEST", "BakeError", "BakeSettings", "bake_memory_bytes",
           "bake_points_input", "bake_scene", "bounce_key", "check_out_dir", "lock_out_dir", "outputs_changed",
           "read_manifest", "run_stages", "scene_face_data", "settings_hash"]


def check_out_dir(out_dir) -> str:
    """The absolute output folder, created if needed; BakeError if it cannot be written."""
    out_dir = os.path.abspath(os.fspath(out_dir))
    try:
        os.makedirs(out_dir, exist_ok=True)
    except OSError as exc:
        raise BakeError(f"cannot create output folder {out_dir}: {exc.strerror}") from exc
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise BakeError(f"output folder {out_dir} is not writable")
    return out_dir


def lock_out_dir(out_dir, job=None, source=None) -> FolderLock:
    """Take the output folder's lock (BakeError naming the other bake if it is busy)."""
    try:
        return FolderLock(out_dir, job, source).acquire()
    except FolderBusyError as exc:
        raise BakeError(str(exc)) from None
    except OSError as exc:
        raise BakeError(f"cannot lock output folder {out_dir}: {exc.strerror or exc}") from exc


def bake_scene(sc: Scene, out_dir, settings: BakeSettings | None = None, *, light=None,
               progress=None, cancel: threading.Event | None = None,
               skip_if_unchanged: bool = True, sets: list[str] | None = None,
               job: str | None = None, source: str | None = None, dask: str | None = None,
               sun=None, lamps=()) -> dict:
    """Bake every texture set of ``sc`` into ``out_dir``.

    light : (K', 3) RGB SH of the environment in world coordinates, K' >= bands^2;
            needed for bounce textures (without it they are skipped with a warning).
    job, source : the job file this scene came from and what that was made from
          (e.g. the .blend), recorded in the folder's lock so that a second
          bake into the folder can say which bake holds it.
    dask : run the ray chunks on a Dask cluster: "local[:N]", a scheduler
          address (tcp://HOST:PORT) or "env" ($DASK_SCHEDULER_ADDRESS);
          the outputs are the local bake's, bit for bit (executors/dask_cluster.py).
    sun : a core.light.sun.Sun: each set also gets ``<set>.sun.exr``, the
          visible fraction of the sun's disc per texel (pipeline/sun_stage.py).
    lamps : core.light.lamp.Lamp (point and spot, at most 4): each set also
          gets ``<set>.lamps.exr``, the visible fraction of each lamp's sphere.
    Returns the manifest dict (``manifest["skipped"]`` is True when an identical
    bake was already there). Raises BakeError (also when another bake holds the
    folder) / SceneError / MemoryLimitError for bad input and transfer.Cancelled
    when ``cancel`` is set. The folder lock is released on every exit path.
    """
    st = (settings or BakeSettings()).validate()
    spec = parse_spec(dask) if dask is not None else None
    out_dir = check_out_dir(out_dir)
    t_start = time.perf_counter()
    lock = lock_out_dir(out_dir, job, source)
    try:
        if lock.taken_over:
            emit(progress, type="warning", message=f"took over the lock of a bake that is gone "
                                                   f"(pid {lock.taken_over.get('pid')})")
        removed = atomic.remove_stale_temporaries(out_dir)
        ctx = BakeContext.create(sc, out_dir, st, light=light, progress=progress, cancel=cancel, sets=sets,
                                 dask=spec, sun=sun, lamps=lamps)
        if removed:
            ctx.warn(f"removed {len(removed)} temporary file(s) left by an interrupted bake")
        failed = True
        try:
            result = run_stages(ctx, t_start, skip_if_unchanged=skip_if_unchanged)
            failed = False
            return result
        except BaseException:
            ctx.staging.abort()
            raise
        finally:
            ctx.close(failed)
    finally:
        lock.release()


def run_stages(ctx: BakeContext, t_start: float, *, skip_if_unchanged: bool = True) -> dict:
    """The bake's stages in order (bake_scene holds the folder lock and cleans up
    on failure): plan; geometry; per set G-buffer and transfer (or, for a
    bounce-only re-bake, the transfer read back); vertex transfer; bounce
    levels; manifest and commit. Returns the manifest."""
    st = ctx.settings
    plan = plan_bake(ctx, skip_if_unchanged=skip_if_unchanged)
    if plan.skipped:
        return finish_skipped(ctx, plan)
    check_memory(ctx, plan)
    if ctx.dask is not None:
        ctx.remote = DaskBake(ctx.dask, emit=ctx.emit, ray_bytes=memory_plan.RAY_BYTES,
                              scene_need=memory_plan.scene_bytes(ctx.scene.n_triangles),
                              kernel_code=memory_plan.NUMBA_IMPORT + memory_plan.JIT_COMPILE
                              ).open(ctx.scene, f"{plan.input_hash}-{plan.materials_hash}")
    todo = ctx.set_ids if st.textures else []
    old_reports = {r.get("name"): r for r in manifest_dicts((plan.old_manifest or {}).get("sets"))}
    results = []
    # G-buffers, texel rows, planes, EXR channels: fresh arrays streamed once,
    # which fault in faster as normal pages (memory.numpy_hugepage_advice).
    with numpy_hugepage_advice(False):
        # The first G-buffer and the ray tables are built on helpers while the BVH is.
        first_gb = start_gbuffer(ctx, todo[0]) if todo else None
        if todo or st.vertex_mode:
            start_tables(ctx)
        if plan.bouncing and ctx.remote is None:
            hit_kernel.warm_up(st.bands, relightable=st.bounce_mode == "relightable",
                               glossy_bands=relight_glossy_bands(st))
        geo = build_geometry(ctx)
        for position, s in enumerate(todo):
            gb = gbuffer_stage(ctx, s, first_gb if position == 0 else None)
            if plan.bouncing and gb.n and s not in ctx.bounce_grids:
                # The bounce grid each set gets is known from its G-buffer: the
                # estimate is checked again with it before the trace allocates.
                asked = asked_downscale(st.bounces, st.tuning, st.bounce_downscale)
                ctx.bounce_grids[s] = choose_grid(gb, asked)
                if ctx.bounce_grids[s].downscale != asked:
                    check_memory(ctx, plan, [ctx.bounce_grids[i].downscale if i in ctx.bounce_grids else asked
                                             for i in ctx.set_ids])
            if not plan.transfer_reused:
                results.append(transfer_set(ctx, geo, plan, gb, position=position,
                                            keep_for_bounce=plan.bouncing))
            elif gb.n:
                old_rep = old_reports.get(ctx.scene.set_names[s], {})
                if plan.bouncing and not plan.bounce_reused:
                    r = load_transfer_set(ctx, geo, gb, old_rep)
                else:
                    r = SetResult(gb.set_index, ctx.scene.set_names[s], old_rep, [])
                if plan.sun_only:
                    # only the sun changed (or came, or went): its masks alone over the transfer on disk
                    r.files, sun_rep = sun_only_set(ctx, geo, plan, gb)
                    r.report = {**{k: v for k, v in old_rep.items() if not k.startswith(("sun_", "lamp_"))}, **sun_rep}
                results.append(r)
        # The results hold what the bounce needs of each G-buffer: not the last one whole (#35).
        gb = first_gb = None
    vertex = vertex_stage(ctx, geo, plan) if st.vertex_mode and not plan.transfer_reused else None
    bounce = None
    if plan.bouncing and not (plan.transfer_reused and plan.bounce_reused):
        levels = relight_levels if st.bounce_mode == "relightable" else bounce_levels
        sources = [r.bounce for r in results if r.bounce is not None]
        for r in results:
            r.bounce = None         # bounce_inputs consumes the sources: held by the list alone
        bounce = levels(ctx, geo, plan, sources)
    if ctx.remote is not None:
        # Every ray is traced: shut the cluster down (its summary event) before
        # the commit, whose "done" event must be the bake's last.
        ctx.remote.close()
        ctx.memory.dask_workers = ctx.remote.worker_report
        ctx.remote = None
    manifest = make_manifest(ctx, plan, geo, results, vertex, bounce, t_start)
    return commit_bake(ctx, plan, manifest)
