"""One bake code path for the UI, background mode and both command lines.

``prepare`` exports the evaluated scene into a job file in the output folder,
:class:`BakeWatch` runs the worker and handles its events (one loop for the
modal operator, a step per timer tick, and for ``bake_blocking``), ``finish``
turns the worker's result into images and metadata on the scene.
``bake_blocking`` runs a bake to the end (background mode, ``blender -c prtt
bake``, ``python -m prtt_addon bake``).
"""
from __future__ import annotations

import dataclasses
import json
import os
import time
import uuid

import bpy
import numpy as np

from ...core.bake.pipeline.context import BakeSettings
from ...core.bake.pipeline.runner import check_out_dir
from ...core.base.atomic import atomic_write, temp_prefix
from ...core.base.errors import BakeError
from ...core.io.exr_io import TextureError, read_dc_plane
from ...core.io.jobfile import save_scene
from ...core.settings_schema import core_from_ui
from ..record import materials_signature
from ..rna_arrays import write_pixels
from ..scene.job import GENERATED_UVS, ExportError, export_scene, output_folder
from ..shared import redraw_viewports
from .worker_job import WorkerJob

EXIT_CANCELLED = 3


def job_path(out_dir: str) -> str:
    """A fresh job file name in ``out_dir`` for this bake.

    Named per bake (this process and a random token), so two bakes into one
    folder never read each other's scene (the worker's folder lock then lets
    one of them run). It is a temporary of this (Blender's) process: a later
    bake removes it only once this process is gone (atomic.remove_stale_temporaries).
    """
    return os.path.join(out_dir, f"{temp_prefix('job')}{uuid.uuid4().hex[:12]}.npz")


@dataclasses.dataclass
class Prepared:
    job: str
    out_dir: str
    export: object
    settings: dict
    materials_signature: str = ""     # of the scene as exported (it may change while the worker runs)
    out_setting: str = ""             # the Output Folder setting as the bake started (//... or absolute)


@dataclasses.dataclass
class Outcome:
    status: str                # "done", "skipped", "cancelled", "failed"
    message: str
    manifest: dict | None = None
    warnings: list = dataclasses.field(default_factory=list)   # the export's (the worker reports its own)


def bake_settings(scene, overrides: dict | None = None) -> BakeSettings:
    """The scene's bake settings, made once per bake on this side of the
    worker: the settings scene.prtt holds, mapped by core/settings_schema.py
    (Storage -> half, Adaptive + Tolerance -> adaptive_tol, Vertex Transfer ->
    vertex_mode, ...), the others at their defaults, then ``overrides``
    (BakeSettings fields: the command line's), validated. The job file
    carries its dict, from which the worker makes its own once."""
    st = scene.prtt
    merged = core_from_ui(lambda name: getattr(st, name))
    merged.update(overrides or {})
    return BakeSettings.from_dict(merged).validate()


def prepare(context, overrides: dict | None = None) -> Prepared:
    """Export the scene to a job file. Raises ExportError (nothing written)."""
    scene = context.scene
    out_dir = output_folder(scene)
    st = bake_settings(scene, overrides)
    settings = st.as_dict()
    exp = export_scene(context, with_light=st.bounces > 0)
    try:
        check_out_dir(out_dir)
    except BakeError as exc:
        raise ExportError(str(exc)) from exc
    extra = {"settings": settings, "blend": bpy.data.filepath, "set_objects": exp.set_objects}
    if exp.light is not None:
        extra["light"] = {"coeffs": exp.light.tolist(), "description": exp.light_description}
    if exp.sun is not None:
        extra["sun"] = exp.sun.as_dict()
    if exp.lamps:
        extra["lamps"] = [lp.as_dict() for lp in exp.lamps]
    job = job_path(out_dir)
    save_scene(exp.scene, job, extra=extra)
    return Prepared(job, out_dir, exp, settings, materials_signature(scene), scene.prtt.output_dir or "//prtt/")


def interpret(job: WorkerJob, code: int) -> Outcome:
    """The worker's exit and last message as an Outcome."""
    last = job.last_event or {}
    if code == 0 and last.get("type") == "done":
        with open(last["manifest"], encoding="utf-8") as f:
            manifest = json.load(f)
        if last.get("skipped"):
            return Outcome("skipped", "PRTT: inputs unchanged since the last bake; nothing to do", manifest)
        return Outcome("done", "PRTT: bake finished", manifest)
    if code == EXIT_CANCELLED or job.cancelled:
        return Outcome("cancelled", "PRTT: bake cancelled; the previous textures are unchanged")
    if last.get("type") == "error":
        return Outcome("failed", f"PRTT: {last['message']}")
    tail = job.stderr_tail()
    how = f"was killed (signal {-code})" if code is not None and code < 0 else f"exited with code {code}"
    return Outcome("failed", f"PRTT: the bake worker {how}; the previous textures are unchanged"
                   + (f". Its last output: {tail}" if tail else ""))


def finish(context, prepared: Prepared, outcome: Outcome) -> None:
    """Record the result on the scene and load the baked textures as images."""
    st = context.scene.prtt
    st.baking = False
    st.progress = 1.0 if outcome.status in ("done", "skipped") else 0.0
    st.status = outcome.message.replace("PRTT: ", "")
    try:
        os.remove(prepared.job)
    except OSError:
        pass
    if outcome.status not in ("done", "skipped") or outcome.manifest is None:
        return
    m = outcome.manifest
    write_generated_uvs(prepared.out_dir, prepared.export.generated_uvs)
    # The folder as written (absolute: found again after Blender's own Save As
    # elsewhere) and, when the setting was relative to the .blend (//textures/),
    # that form too (found again after the project folder moved).
    relative = prepared.out_setting if prepared.out_setting.startswith("//") else None
    summary = {"out_dir": prepared.out_dir, "out_dir_relative": relative, "files": m["files"], "input_hash": m["input_hash"],
               "settings": m["settings"], "set_objects": prepared.export.set_objects,
               "bounce": None if not m.get("bounce") else {k: m["bounce"][k] for k in
                                                          ("levels", "light_hash", "materials_hash", "files")},
               "light": prepared.export.light_description, "seconds": m["seconds"].get("total"),
               **({"sun": m["sun"]} if m.get("sun") else {}),
               **({"lamps": m["lamps"]} if m.get("lamps") else {}),
               "warnings": m.get("warnings", []) + prepared.export.warnings,
               "objects": prepared.export.objects,
               "materials_signature": prepared.materials_signature,
               "time": time.strftime("%Y-%m-%d %H:%M:%S")}
    st.last_bake = json.dumps(summary)
    load_preview_images(prepared.out_dir, m, outcome.warnings.append)
    redraw_viewports(context)


def write_generated_uvs(out_dir: str, generated: dict) -> None:
    """The UVs the export generated (export.GENERATED_UVS), written atomically
    after a successful bake so that they always match the textures beside them.
    Removed when the bake generated none."""
    path = os.path.join(out_dir, GENERATED_UVS)
    if not generated:
        if os.path.exists(path):
            os.remove(path)
        return
    keys = sorted(generated)
    with atomic_write(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, keys=np.array(keys, dtype=str),
                     **{f"uv_{i}": np.asarray(generated[k], np.float32) for i, k in enumerate(keys)})


def keep_image(img) -> None:
    """Make an image the add-on computed survive save and reload: its pixels
    packed into the .blend (a generated image would come back blank) and a
    fake user (nothing else uses it, and unused data is not saved)."""
    img.update()
    img.pack()
    img.use_fake_user = True


def load_preview_images(out_dir: str, manifest: dict, warn=None) -> list:
    """Per set an image "PRTT AO <set>": the transfer's DC term normalised so
    open sky is 1 (what Blender can show of a 25-channel EXR). A texture that
    cannot be read gets no image and ``warn(message)`` (default: print)."""
    made = []
    for name in manifest.get("transfer_files", manifest["files"]):
        if not name.endswith(".transfer.exr"):
            continue
        # The DC channel alone: Blender's process holds no copy of the whole texture.
        try:
            dc = read_dc_plane(os.path.join(out_dir, name))
        except TextureError as exc:
            # The bake itself succeeded; the AO picture is a convenience: say why it is missing.
            (warn or print)(f"no AO image for {name}: {exc}")
            continue
        ao = np.clip(dc / 0.886226925, 0.0, None)   # A_0 y_00 = pi / (2 sqrt(pi))
        h, w = ao.shape
        title = f"PRTT AO {name[:-len('.transfer.exr')]}"
        img = bpy.data.images.get(title)
        if img is not None and tuple(img.size) != (w, h):
            bpy.data.images.remove(img)
            img = None
        if img is None:
            img = bpy.data.images.new(title, w, h, float_buffer=True, alpha=False)
            img.colorspace_settings.name = "Non-Color"
        rgba = np.ones((h, w, 4), np.float32)
        rgba[..., :3] = ao[..., None]
        write_pixels(img, rgba)                          # row 0 = bottom, like ours
        keep_image(img)
        made.append(img)
    return made


#: Seconds a worker that has exited may stay silent before its output counts
#: as complete (the end of its output normally says so first).
EXIT_GRACE = 0.5


class BakeWatch:
    """A running bake: the worker, and the one loop over its events.

    The modal operator calls :meth:`poll` on every timer tick; headless bakes
    call :meth:`run` (``poll`` with a timeout until the end). Per event: a
    progress event sets the scene's progress bar and status line
    (``scene.prtt.progress``, ``.status``, display only); every event then
    goes to ``on_event`` (the operator reports warnings and infos, the
    command lines print progress). When the worker's output ends (or it
    has exited and stayed silent for :data:`EXIT_GRACE` s) its exit status and
    last event become the Outcome (done, skipped, cancelled, failed), which
    :func:`finish` records on the scene. :meth:`cancel` (Esc, the Cancel
    button, Ctrl+C, SIGTERM) asks the worker to stop.
    """

    def __init__(self, prepared: Prepared, job: WorkerJob, on_event=None):
        self.prepared = prepared
        self.job = job
        self.on_event = on_event
        self._silent_since: float | None = None

    @classmethod
    def start(cls, context, prepared: Prepared, *, force: bool = False, on_event=None,
              dask: str | None = None) -> "BakeWatch":
        """Start the worker on a prepared job; ``dask`` (a --dask value) for
        this bake, else the scene's Dask Scheduler (empty: this machine)."""
        st = context.scene.prtt
        dask = dask if dask is not None else (st.dask_scheduler.strip() or None)
        job = WorkerJob(prepared.job, prepared.out_dir, force=force, dask=dask).start()
        st.baking, st.progress, st.status = True, 0.0, "starting"
        return cls(prepared, job, on_event)

    @property
    def cancelled(self) -> bool:
        return self.job.cancelled

    def poll(self, context, timeout: float | None = None) -> Outcome | None:
        """Handle the events so far (waiting up to ``timeout`` s for the first
        one). Returns the Outcome, recorded on the scene, once the bake has
        ended; None while it runs."""
        st = context.scene.prtt
        asked = time.monotonic()
        events = self.job.events(timeout=timeout)
        ended = None in events
        for e in events:
            if e is None:
                continue
            if e.get("type") == "progress":
                st.progress = float(e.get("fraction", 0.0))
                st.status = f"{e.get('stage')} {e.get('set', '')}".strip()
            if self.on_event is not None:
                self.on_event(e)
        if events or self.job.returncode is None:
            self._silent_since = None
        elif not ended:
            if self._silent_since is None:
                self._silent_since = asked
            ended = time.monotonic() - self._silent_since >= EXIT_GRACE
        return self._finish(context, self.job.wait()) if ended else None

    def cancel(self, context) -> None:
        """Ask the worker to stop (it leaves the previous textures as they were)."""
        self.job.cancel()
        context.scene.prtt.status = "cancelling"

    def run(self, context) -> Outcome:
        """Handle events until the bake ends; Ctrl+C (KeyboardInterrupt) cancels it."""
        try:
            while True:
                outcome = self.poll(context, timeout=0.5)
                if outcome is not None:
                    return outcome
        except KeyboardInterrupt:
            self.cancel(context)
            return self._finish(context, self.job.wait())

    def _finish(self, context, code: int) -> Outcome:
        outcome = interpret(self.job, code)
        outcome.warnings = list(self.prepared.export.warnings)
        finish(context, self.prepared, outcome)
        return outcome


def bake_blocking(context, *, overrides=None, force=False, on_event=None, dask: str | None = None) -> Outcome:
    """Export, run the worker to the end, finish. Never raises for bad input:
    the Outcome says what happened."""
    try:
        prepared = prepare(context, overrides)
    except (ExportError, ValueError, OSError) as exc:
        context.scene.prtt.status = str(exc)
        return Outcome("failed", f"PRTT: {exc}")
    return BakeWatch.start(context, prepared, force=force, on_event=on_event, dask=dask).run(context)
