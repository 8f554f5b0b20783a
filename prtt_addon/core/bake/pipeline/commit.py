"""The bake's last stage: the manifest, then every staged output renamed into
place with the manifest last (a cancelled, failed or killed bake leaves the
previous outputs untouched)."""
from __future__ import annotations

import datetime
import json
import os
import time

from ....version import __version__
from ...base import atomic
from ...base.atomic import atomic_write
from ...base.errors import BakeError
from ...light.lamp import LAMP_RAYS
from ...light.sun import SUN_RAYS
from .bounce_stage import BounceResult
from .context import BAKE_FORMAT_VERSION, MANIFEST, BakeContext
from .plan import BakePlan, manifest_dicts, plain_names
from .stages import Geometry, SetResult, VertexResult
from .sun_stage import EDGE_SUFFIX, LAMP_SUFFIX, MASK_SUFFIX, SUN_SUFFIXES


def finish_skipped(ctx: BakeContext, plan: BakePlan) -> dict:
    """An identical bake is already there: its manifest, marked ``skipped``."""
    old = plan.old_manifest
    old["skipped"] = True
    ctx.emit(type="done", skipped=True, manifest=os.path.join(ctx.out_dir, MANIFEST))
    return old


def make_manifest(ctx: BakeContext, plan: BakePlan, geo: Geometry, sets: list[SetResult],
                  vertex: VertexResult | None, bounce: BounceResult | None, t_start: float) -> dict:
    """The manifest (docs/format.md) without its ``file_info`` (commit_bake adds
    it). A reused transfer keeps the previous manifest's files and reports.
    ``t_start``: time.perf_counter() when the bake began (seconds["total"]).
    BakeError when nothing at all was baked."""
    st, old = ctx.settings, plan.old_manifest
    vertex_reports, vertex_files = (vertex.reports, vertex.files) if vertex is not None else ([], [])
    if plan.transfer_reused:
        transfer_files = old.get("transfer_files", old.get("files", []))
        set_reports = manifest_dicts(old.get("sets"))
        vertex_reports = manifest_dicts(old.get("vertex"))
        if plan.sun_only:
            # the masks baked anew over the reused transfer (or none, the sun gone)
            transfer_files = [f for f in transfer_files if not f.endswith(SUN_SUFFIXES)] + [
                f for r in sets for f in r.files if f.endswith(SUN_SUFFIXES)]
            new = {r.name: r.report for r in sets}
            set_reports = [new.get(r.get("name"), {k: v for k, v in r.items() if not k.startswith("sun_")})
                           for r in set_reports]
    else:
        transfer_files = [f for r in sets for f in r.files] + vertex_files
        set_reports = [r.report for r in sets]
    bounce_entry = bounce.manifest_entry(plan, st) if bounce is not None else None
    if bounce is None and plan.bouncing and plan.transfer_reused and plan.bounce_reused:
        bounce_entry = old.get("bounce")               # a masks-only re-bake: the bounce as it was
    files = transfer_files + (bounce_entry["files"] if bounce_entry else [])
    if not files:
        raise BakeError("nothing was baked: no texture set has covered texels")
    totals = {"rays_traced": 0, "rays_naive": 0, "texels": 0, "analytic_texels": 0,
              "rays_below_horizon_skipped": 0, "guided_texels": 0}
    for r in set_reports:
        for k in totals:
            totals[k] += r.get(k, 0)
    totals["rays_traced"] += sum(v.get("rays_traced", 0) for v in vertex_reports)
    ctx.seconds["total"] = time.perf_counter() - t_start
    trace_s = ctx.seconds["trace"] + ctx.seconds["vertex"]
    reused = plan.transfer_reused
    return {
        "format": "prtt-bake", "format_version": BAKE_FORMAT_VERSION,
        "prtt_version": __version__, "kind": "transfer",
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "input_hash": plan.input_hash, "settings_hash": plan.settings_hash, "settings": st.as_dict(),
        "files": files, "transfer_files": transfer_files, "sets": set_reports, "vertex": vertex_reports,
        "bounce": bounce_entry, "transfer_reused": bool(reused),
        "analytic_test": geo.clear_stats, "totals": totals, "seconds": ctx.seconds,
        "rays_per_second_trace": totals["rays_traced"] / trace_s if trace_s > 0 and not reused else 0.0,
        "rays_per_second_end_to_end": totals["rays_traced"] / ctx.seconds["total"] if not reused else 0.0,
        "memory": {"peak_rss_mb": ctx.memory.peaks(), "process_peak_rss_mb": ctx.memory.process,
                   "estimate_mb": ctx.memory.estimate_mb,
                   **({"dask_workers": ctx.memory.dask_workers} if ctx.memory.dask_workers else {})},
        "warnings": ctx.warnings, "skipped": False,
        # Only with a sun: a bake without one writes the manifest it wrote before suns.
        **({"sun": {**ctx.sun.as_dict(), "rays": SUN_RAYS, "key": plan.sun_key,
                    "files": [f for f in transfer_files if f.endswith(MASK_SUFFIX)],
                    # Only with edges: a bake without them writes the sun entry it wrote before them.
                    **({"edge_files": edge_files} if (edge_files := [f for f in transfer_files
                                                                     if f.endswith(EDGE_SUFFIX)]) else {})}}
            if ctx.sun is not None else {}),
        # Only with lamps: a bake without them writes the manifest it wrote before lamps.
        **({"lamps": {"lamps": [lp.as_dict() for lp in ctx.lamps], "rays": LAMP_RAYS, "key": plan.sun_key,
                      "files": [f for f in transfer_files if f.endswith(LAMP_SUFFIX)]}}
           if ctx.lamps else {}),
    }


def commit_bake(ctx: BakeContext, plan: BakePlan, manifest: dict) -> dict:
    """Seal the staged files (fsync, size and sha256 into ``manifest["file_info"]``),
    rename them into place, write the manifest, remove bounce textures the
    previous bake had and this one does not (levels, relightable); then the "done" event. Returns
    the manifest. A cancel before the commit lock is taken wins (Cancelled,
    nothing renamed)."""
    old = plan.old_manifest or {}
    files = manifest["files"]
    old_files = old.get("files", [])
    stale = [f for f in (old_files if plain_names(old_files) else [])
             if f not in files and (".bounce" in f or f.endswith((".relight.exr",) + SUN_SUFFIXES))]
    ctx.check_cancel()
    new_info = ctx.staging.seal()
    # The reused files' entries (the transfer's, and a masks-only re-bake's bounce) were verified by plan.reusable.
    reused_info = {f: old["file_info"][f] for f in files if f in (old.get("file_info") or {})} \
        if plan.transfer_reused else {}
    manifest["file_info"] = {f: (new_info.get(f) or reused_info[f]) for f in files}
    _rename_into_place(ctx, manifest, stale)
    ctx.emit(type="done", skipped=False, manifest=os.path.join(ctx.out_dir, MANIFEST))
    return manifest


def _rename_into_place(ctx: BakeContext, manifest: dict, stale: list[str]) -> None:
    """Rename the staged outputs into place and write the manifest, holding
    atomic.COMMIT_LOCK: a signal's watchdog (worker.py) waits for it rather
    than exiting between the renames and the manifest. A cancel that came
    before the lock was taken still wins (nothing is renamed)."""
    with atomic.COMMIT_LOCK:
        ctx.check_cancel()
        ctx.staging.commit()
        with atomic_write(os.path.join(ctx.out_dir, MANIFEST)) as tmp:
            with open(tmp, "w", encoding="utf-8") as f:
                json.dump(manifest, f, indent=1)
        for f in stale:                       # bounce levels no longer baked
            try:
                os.remove(os.path.join(ctx.out_dir, f))
            except OSError:
                pass
        atomic.mark_committed()
