"""What every stage of a bake is given and shares: settings, the context object.

* :class:`BakeSettings` every bake setting (the job file's ``extra.settings``);
* :class:`BakeError` a bake that cannot run, with the reason;
* :class:`StagedOutputs` output files written as temporaries and renamed
  together when the bake commits;
* :class:`BakeContext` one bake's inputs (scene, folder, settings, light) and
  shared state (progress and cancellation, the helper thread pool, staged
  files, seconds per stage, warnings, the warmed ray tables). The stages
  (stages.py, bounce_stage.py, plan.py, commit.py) take it as first argument;
  it is slotted: a field it does not declare cannot be set on it.
"""
from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import os
import threading
from collections.abc import Callable

import numpy as np

from ... import settings_schema as _schema
from ...base import atomic
from ...base.errors import BakeError, Cancelled
from ...base.memory import StagePeaks
from ...io.outdir import file_info
from ...model.scene import Scene
from ...shading.shade import prepare_light, sun_sh
from ..estimators.transfer import TransferSettings

MANIFEST = "manifest.json"
BAKE_FORMAT_VERSION = 1
#: Integer settings of the bake beyond TransferSettings': (lowest, highest, why),
#: derived from settings_schema.SETTINGS (scope "bake").
BAKE_INT_LIMITS = _schema.int_limits("bake")
#: Tuning auto: mantissa bits of half storage for SH bands l >= 1 (of 10): a
#: rounding step of 2^-7 relative, far below a 256-ray texel's Monte Carlo
#: noise in those bands; ~0.73 of the bytes (bench auto, docs/benchmarks.md).
AUTO_MANTISSA_BITS = 6
#: Stage timers (the manifest's "seconds"), zero before the stage runs; "bvh",
#: "analytic_test" and "total" are added as those steps finish.
STAGE_SECONDS = ("gbuffer", "trace", "dilate", "write", "vertex", "bounce_exit", "bounce_trace", "bounce_write")
#: tuning "auto": the bounce grid it asks for, 1/2 per side (4x fewer texels
#: and bytes; bounce_stage.choose_grid takes it where no UV islands mix).
AUTO_DOWNSCALE = 2


def asked_downscale(bounces: int, tuning: str, bounce_downscale: int) -> int:
    """The coarsest bounce grid (1/N per side) a bake asks for; choose_grid
    then takes the coarsest of 1/N, 1/(N/2) ... that mixes no UV islands (the
    unwrap leaves room for 1/N: blender/scene/uv_maps.margin_texels)."""
    if bounces <= 0:
        return 1
    return max(bounce_downscale, AUTO_DOWNSCALE) if tuning == "auto" else bounce_downscale


#: The bounce stages among them: exit forms, trace + shade, dilate + write.
BOUNCE_STAGES = ("bounce_exit", "bounce_trace", "bounce_write")


def bounce_seconds(seconds: dict) -> float:
    """The bounce stages' seconds of a bake's ``seconds`` (its manifest's)."""
    return float(sum(seconds.get(k, 0.0) for k in BOUNCE_STAGES))

_d = _schema.default


@dataclasses.dataclass
class BakeSettings(TransferSettings):
    """Every bake setting (the job file's ``extra.settings``). Defaults, types,
    ranges and help are declared once in settings_schema.SETTINGS (scope
    "bake" for these fields); docs/format.md §5 is generated from it."""

    dilate: int = _d("dilate")              # texels of dilation
    sun_detail: int = _d("sun_detail")      # a sun mask's texels per set texel, per side (sun_stage)
    sun_refine: bool = _d("sun_refine")     # a finer mask traces all its rays only in penumbrae (sun_mask)
    sun_edges: bool = _d("sun_edges")       # sub-texel shadow edges beside the mask (sun_edge)
    half: bool = _d("half")                 # float16 EXR (auto float32 on overflow)
    mips: bool = _d("mips")                 # write coverage-weighted mip levels
    texel_validity: bool = _d("texel_validity")   # fill texels inside geometry from their neighbours
    guided_filter: bool = _d("guided_filter")     # smooth the guided texels' transfer (estimators/guided_filter.py)
    normal_maps: bool = _d("normal_maps")
    vertex_mode: bool = _d("vertex_mode")   # also bake per-vertex transfer
    textures: bool = _d("textures")         # bake texture sets (False: vertex mode only)
    overlap: str = _d("overlap")            # overlapping UVs: "warn" or "error"
    bounces: int = _d("bounces")            # inter-reflection levels (0 = off; needs a light)
    bounce_rays: int = _d("bounce_rays")    # rays per texel per bounce level
    bounce_tolerance: float = _d("bounce_tolerance")  # stop levels below this fraction of the direct energy
    bounce_denoise: str = _d("bounce_denoise")        # "auto", "none", "edge-aware", "oidn" (core/bake/estimators/denoise.py)
    bounce_downscale: int = _d("bounce_downscale")    # bounce textures at 1/N resolution per side (bounce_stage.py)
    tuning: str = _d("tuning")                        # "fixed" | "auto": per-set choices (bounce_stage.py)
    bounce_mode: str = _d("bounce_mode")              # "baked" | "relightable" (relightable_stage.py)

    def validate(self) -> "BakeSettings":
        """Check every field's type and range (ValueError "name must be ..., got ...")."""
        super().validate()
        _schema.validate(self, "bake")
        if not (self.textures or self.vertex_mode):
            raise ValueError("nothing to bake: enable textures or vertex mode")
        return self

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "BakeSettings":
        if not isinstance(d, dict):
            raise ValueError(f"bake settings must be a JSON object, got {type(d).__name__}")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown bake settings: {sorted(unknown)}")
        return cls(**d)

    def storage_bits(self) -> int:
        """Mantissa bits the half textures keep for the coefficients of bands
        l >= 1 (exr_io.quantize_half; the DC keeps all 10): AUTO_MANTISSA_BITS
        under tuning auto, all 10 otherwise (fixed writes today's bits)."""
        return AUTO_MANTISSA_BITS if self.tuning == "auto" and self.half else 10

    def result_key(self) -> dict:
        """Settings that change the transfer textures (not threads, chunking or bounces)."""
        d = self.as_dict()
        for k in ("threads", "chunk_rays", "bounces", "bounce_rays", "bounce_tolerance", "bounce_denoise",
                  "bounce_downscale", "tuning", "bounce_mode", "sun_detail", "sun_refine",
                  "sun_edges"):     # (the sun's key)
            d.pop(k)
        if self.storage_bits() < 10:
            d["storage_bits"] = self.storage_bits()     # absent under fixed: its keys are as before
        if not self.texel_validity:
            d.pop("texel_validity")                     # off: the keys of the bakes before it
        if not (self.guided_filter and self.guiding):
            d.pop("guided_filter")                      # no texel filtered: the keys of the bakes before it
        return d


class StagedOutputs:
    """Output files written as temporaries (``.prtt-tmp-<pid>-<stem>-<n><ext>``,
    registered with atomic.py for a hard exit), renamed together on commit."""

    def __init__(self, folder: str):
        self.folder = folder
        self.files: list[tuple[str, str]] = []      # (temporary path, final path)

    def path(self, name: str) -> str:
        """A fresh temporary path in the folder for output file ``name``."""
        base, ext = os.path.splitext(name)
        tmp = os.path.join(self.folder, f"{atomic.temp_prefix(base)}{len(self.files)}{ext}")
        self.files.append((tmp, os.path.join(self.folder, name)))
        atomic.register(tmp)
        return tmp

    def seal(self) -> dict:
        """fsync every staged file and return {final name: file_info} (size, sha256).
        Done before the commit lock is taken: it reads every byte once."""
        info = {}
        for tmp, final in self.files:
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
            info[os.path.basename(final)] = file_info(tmp)
        return info

    def commit(self) -> None:
        """Rename every staged file into place (call with atomic.COMMIT_LOCK held)."""
        for tmp, final in self.files:
            os.replace(tmp, final)
            atomic.unregister(tmp)
        self.files = []

    def abort(self) -> None:
        """Remove every staged file (a failed or cancelled bake)."""
        for tmp, _ in self.files:
            try:
                os.remove(tmp)
            except OSError:
                pass
            atomic.unregister(tmp)
        self.files = []


class AnyEvent:
    """is_set() of either event: helpers stop when the user cancels *or* the bake
    fails (without setting the caller's event on a failure)."""

    def __init__(self, *events):
        self.events = [e for e in events if e is not None]

    def is_set(self) -> bool:
        return any(e.is_set() for e in self.events)


def emit(progress: Callable[[dict], None] | None, **event) -> None:
    """Send ``event`` to ``progress`` (when there is one)."""
    if progress is not None:
        progress(event)


@dataclasses.dataclass(slots=True, eq=False)
class BakeContext:
    """One bake's inputs and the state its stages share (see runner.bake_scene).

    Build it with :meth:`create`; :meth:`close` shuts its helper pool down.
    What a stage computes is returned by that stage (plan.BakePlan,
    stages.Geometry, stages.SetRows ...), not stored here.
    """

    scene: Scene
    out_dir: str                              # absolute, writable (runner.check_out_dir)
    settings: BakeSettings                    # validated
    light: np.ndarray | None                  # (K, 3) float64 RGB SH, K = bands², world frame; None: no bounces
    progress: Callable[[dict], None] | None   # receives event dicts (the worker prints them as JSON)
    cancel: threading.Event | None            # the caller's cancel: set -> transfer.Cancelled at the next check
    set_ids: list[int]                        # texture sets to bake (scene set indices, in bake order)
    helpers: cf.ThreadPoolExecutor            # G-buffer bands, dilation, EXR channels, ray tables
    # State the stages share (not arguments of the constructor):
    failed: threading.Event = dataclasses.field(init=False)     # set when the bake fails
    stop: AnyEvent = dataclasses.field(init=False)              # cancel or failed: what helper tasks check
    staging: StagedOutputs = dataclasses.field(init=False)      # output files written so far (temporaries)
    seconds: dict[str, float] = dataclasses.field(init=False)   # seconds per stage (the manifest's)
    warnings: list[str] = dataclasses.field(init=False)         # every warning emitted, in order
    tables: cf.Future | None = dataclasses.field(init=False)    # warm_tables on a helper (stages.start_tables)
    dask: object | None = None                  # distributed.DaskSpec: trace on a Dask cluster (runner opens it)
    sun: object | None = None                   # core.light.sun.Sun: its mask is baked per set (sun_stage)
    lamps: tuple = ()                           # core.light.lamp.Lamp (at most 4): their masks per set (sun_stage)
    remote: object | None = dataclasses.field(init=False)       # the open executors.dask_cluster.DaskBake, else None
    memory: StagePeaks = dataclasses.field(init=False)          # peak RSS per stage (the manifest's "memory")
    bounce_grids: dict = dataclasses.field(init=False)          # set index -> bounce_stage.BounceGrid, chosen
    validity_scene: tuple | None = dataclasses.field(init=False)  # (RayScene, winding normals): texel_validity's, made once
                                                                # from its G-buffer (runner; bounce_inputs reads it)

    def __post_init__(self):
        self.failed = threading.Event()
        self.stop = AnyEvent(self.cancel, self.failed)
        self.staging = StagedOutputs(self.out_dir)
        self.seconds = dict.fromkeys(STAGE_SECONDS, 0.0)
        self.warnings = []
        self.tables = None
        self.remote = None
        self.memory = StagePeaks()
        self.bounce_grids = {}
        self.validity_scene = None

    @classmethod
    def create(cls, scene: Scene, out_dir: str, settings: BakeSettings, *, light=None,
               progress: Callable[[dict], None] | None = None, cancel: threading.Event | None = None,
               sets: list[str] | None = None, dask=None, sun=None, lamps=()) -> "BakeContext":
        """The context of one bake of ``scene`` into ``out_dir``.

        light : (K', 3) RGB SH, K' >= bands² (truncated to bands²), or None.
        sets : names of the texture sets to bake (default: all, in scene order);
               BakeError for a name the scene does not have.
        dask : a distributed.DaskSpec: the ray chunks run on that Dask cluster.
        sun : a core.light.sun.Sun, or None: each set's sun mask is baked, and
              baked bounces see it as its SH projection (:attr:`bounce_light`).
        lamps : core.light.lamp.Lamp (point and spot, at most MAX_LAMPS): each
              set's lamp masks are baked (channel i lamp i); their light is
              drawn per pixel, not in the bounces.
        """
        set_ids = list(range(scene.n_sets))
        if sets is not None:
            unknown = set(sets) - set(scene.set_names)
            if unknown:
                raise BakeError(f"unknown texture sets {sorted(unknown)}; the scene has {scene.set_names}")
            set_ids = [scene.set_names.index(s) for s in sets]
        prepared = prepare_light(light, settings.bands) if light is not None else None
        # One more worker than cores: the first set's G-buffer is built from a
        # helper that then waits for its row bands on this same pool.
        helpers = cf.ThreadPoolExecutor(max_workers=max(2, settings.n_threads) + 1)
        return cls(scene=scene, out_dir=out_dir, settings=settings, light=prepared, progress=progress,
                   cancel=cancel, set_ids=set_ids, helpers=helpers, dask=dask, sun=sun, lamps=tuple(lamps))

    @property
    def masked(self) -> bool:
        """The bake has masks (a sun or lamps: sun_stage)."""
        return self.sun is not None or bool(self.lamps)

    @property
    def bounce_light(self) -> np.ndarray | None:
        """(K, 3) what baked bounces are lit by: ``light`` and, with a sun, its
        SH projection (shade.sun_sh: E y_k(l)), as the preview relights
        relightable bounces; ``light`` itself without a sun."""
        if self.light is None or self.sun is None:
            return self.light
        return self.light + sun_sh(self.sun.direction, self.sun.irradiance, self.settings.bands)

    @property
    def n_coeffs(self) -> int:
        """K = bands²: SH coefficients per texel and colour (index k = l² + l + m)."""
        return self.settings.bands ** 2

    def emit(self, **event) -> None:
        """Send a progress / warning / info / done event (a progress event's
        stage also starts that stage's peak-memory account, :meth:`mark`)."""
        if event.get("type") == "progress" and event.get("stage"):
            stage = event["stage"]
            if stage == "write" and isinstance(event.get("file"), str):
                stage = "write " + event["file"].split(".")[-2]        # transfer / relight / bounce1 / mip1
            self.mark(stage)
        emit(self.progress, **event)

    def mark(self, stage: str) -> None:
        """Account this process's memory from now on to ``stage`` (base.memory.StagePeaks)."""
        self.memory.enter(stage)

    def check_cancel(self) -> None:
        """Raise Cancelled if the bake was cancelled (cheap: between sets, levels, files)."""
        if self.cancel is not None and self.cancel.is_set():
            raise Cancelled()

    def wait(self, future: cf.Future):
        """A helper's result, waiting in 50 ms steps so that cancellation is noticed."""
        while True:
            try:
                return future.result(timeout=0.05)
            except cf.TimeoutError:
                self.check_cancel()

    def wait_tables(self) -> None:
        """Wait for the ray patterns and estimator tables (warm_tables on a helper)."""
        fut = self.tables
        if fut is not None and not fut.done():
            self.emit(type="progress", stage="tables", fraction=0.0)
        if fut is not None:
            self.wait(fut)

    def warn(self, msg: str) -> None:
        """Record a warning for the manifest and emit it."""
        self.warnings.append(msg)
        self.emit(type="warning", message=msg)

    def close(self, failed: bool = False) -> None:
        """Shut the helper pool down. After a failure its running tasks stop at
        their next check; after a cancel they are not waited for (a G-buffer
        band may be inside a long numpy call), so the caller can exit at once."""
        if failed:
            self.failed.set()
        cancelled = self.cancel is not None and self.cancel.is_set()
        if self.remote is not None:
            self.remote.close()
            self.remote = None
        self.helpers.shutdown(wait=not cancelled, cancel_futures=True)
