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
* ``manifest.json``             settings, per-set stats, seconds per stage, hashes

Work the inputs do not need is skipped: an identical bake is not repeated,
and when only the light or the materials changed, only the bounce textures
are re-baked (from the transfer textures on disk). "Identical" is checked on
the files themselves: the manifest records each output's size and sha256
(``file_info``), and a missing, truncated or replaced output is re-baked.

One bake runs per output folder at a time (outdir.FolderLock, taken for the
whole bake); temporaries that dead bakes left there are removed when a bake
starts (atomic.remove_stale_temporaries).

Progress goes to ``progress(event: dict)`` (the worker prints these as JSON).
"""
from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import datetime
import hashlib
import json
import os
import threading
import time

import numpy as np

from ..io import atomic, exr_io
from ...version import __version__
from . import settings_schema as _schema
from ..io.atomic import atomic_write
from ..texels.dilate import dilate, mip_chain
from ..texels.gbuffer import build_gbuffer, face_normals
from .hemisphere_clear import FLAT_COS, clear_triangles
from .memory import (bounce_resident_bytes, bvh_bytes, check_fits, numpy_hugepage_advice, release_free_memory,
                     set_bytes)
from ..io.outdir import FolderBusyError, FolderLock, file_info, verify_files
from .raytrace import RayScene
from ..io.scene import Scene, geometry_hash
from ..texels.texsample import pixel_major, planes_from_rows
from .transfer import SAME_NORMAL, Cancelled, Points, TransferSettings, bake_points, warm_tables

MANIFEST = "manifest.json"
BAKE_FORMAT_VERSION = 1
#: Integer settings of the bake beyond TransferSettings': (lowest, highest, why),
#: derived from settings_schema.SETTINGS (scope "bake").
BAKE_INT_LIMITS = _schema.int_limits("bake")
_d = _schema.default


@dataclasses.dataclass
class BakeSettings(TransferSettings):
    """Every bake setting (the job file's ``extra.settings``). Defaults, types,
    ranges and help are declared once in settings_schema.SETTINGS (scope
    "bake" for these fields); docs/format.md §5 is generated from it."""

    dilate: int = _d("dilate")              # texels of dilation
    half: bool = _d("half")                 # float16 EXR (auto float32 on overflow)
    mips: bool = _d("mips")                 # write coverage-weighted mip levels
    normal_maps: bool = _d("normal_maps")
    vertex_mode: bool = _d("vertex_mode")   # also bake per-vertex transfer
    textures: bool = _d("textures")         # bake texture sets (False: vertex mode only)
    overlap: str = _d("overlap")            # overlapping UVs: "warn" or "error"
    bounces: int = _d("bounces")            # inter-reflection levels (0 = off; needs a light)
    bounce_rays: int = _d("bounce_rays")    # rays per texel per bounce level
    bounce_tolerance: float = _d("bounce_tolerance")  # stop levels below this fraction of the direct energy
    bounce_denoise: str = _d("bounce_denoise")        # "auto", "none", "edge-aware", "oidn" (core/bake/denoise.py)

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

    def result_key(self) -> dict:
        """Settings that change the transfer textures (not threads, chunking or bounces)."""
        d = self.as_dict()
        for k in ("threads", "chunk_rays", "bounces", "bounce_rays", "bounce_tolerance", "bounce_denoise"):
            d.pop(k)
        return d


class BakeError(RuntimeError):
    """A bake could not run; the message says why (nothing was written)."""


class _Stage:
    """Output files written as temporaries (``.prtt-tmp-<pid>-<stem>-<n><ext>``,
    registered with atomic.py for a hard exit), renamed together on commit."""

    def __init__(self, folder):
        self.folder = folder
        self.files: list[tuple[str, str]] = []

    def path(self, name: str) -> str:
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

    def commit(self):
        """Rename every staged file into place (call with atomic.COMMIT_LOCK held)."""
        for tmp, final in self.files:
            os.replace(tmp, final)
            atomic.unregister(tmp)
        self.files = []

    def abort(self):
        for tmp, _ in self.files:
            try:
                os.remove(tmp)
            except OSError:
                pass
            atomic.unregister(tmp)
        self.files = []


def _emit(progress, **event):
    if progress is not None:
        progress(event)


def settings_hash(settings: BakeSettings) -> str:
    return hashlib.sha256(json.dumps(settings.result_key(), sort_keys=True).encode()).hexdigest()


def read_manifest(out_dir) -> dict | None:
    """The folder's manifest as a dict, or None (missing, unreadable, not an object)."""
    try:
        with open(os.path.join(out_dir, MANIFEST), encoding="utf-8") as f:
            m = json.load(f)
    except (OSError, ValueError, RecursionError):
        return None
    return m if isinstance(m, dict) else None


def _dicts(x) -> list:
    """The dict entries of a manifest list (anything else in it is ignored)."""
    return [d for d in x if isinstance(d, dict)] if isinstance(x, list) else []


def _plain_names(names) -> bool:
    """A list of bare file names (a manifest is read from disk: no paths out of the folder)."""
    return isinstance(names, list) and all(
        isinstance(n, str) and n and os.path.basename(n) == n and not n.startswith(".") for n in names)


def outputs_changed(m: dict, out_dir, files) -> str | None:
    """Why ``files`` in ``out_dir`` are not the ones manifest ``m`` recorded (a
    file missing, of another size or content, or a manifest without file_info),
    or None when every one checks out (size and sha256)."""
    if not _plain_names(files):
        return "the manifest's file list is not a list of file names"
    return verify_files(out_dir, files, m.get("file_info"))


def transfer_up_to_date(m: dict | None, out_dir, in_hash: str, set_hash: str) -> bool:
    """Does manifest ``m`` describe complete transfer outputs of these inputs,
    with every file as the manifest recorded it (size and sha256)?"""
    return bool(m and m.get("input_hash") == in_hash and m.get("settings_hash") == set_hash
                and outputs_changed(m, out_dir, m.get("transfer_files", m.get("files", []))) is None)


def bake_memory_bytes(set_resolution, st: BakeSettings, *, n_triangles: int, bouncing: bool) -> int:
    """Peak bytes a bake adds to its scene's arrays: Embree's BVH, the largest
    set (memory.set_bytes) and, with bounces, every set's resident textures.
    ``set_resolution`` (S, 2) (width, height)."""
    K = st.bands ** 2
    per_set = resident = 0
    for w, h in np.asarray(set_resolution).reshape(-1, 2).tolist():
        per_set = max(per_set, set_bytes(int(w), int(h), K, threads=st.n_threads, chunk_rays=st.chunk_rays,
                                         rays=st.rays))
        resident += bounce_resident_bytes(int(w), int(h), K) if bouncing else 0
    return bvh_bytes(n_triangles) + per_set + resident


def bounce_key(in_hash: str, set_hash: str, light: np.ndarray | None, mat_hash: str,
               st: BakeSettings) -> str:
    """Identity of the bounce textures: transfer, light, materials, bounce settings."""
    from ..shading.model import light_hash
    h = hashlib.sha256("|".join([in_hash, set_hash, light_hash(light) if light is not None else "-",
                                 mat_hash, str(st.bounces), str(st.bounce_rays),
                                 repr(float(st.bounce_tolerance)), st.bounce_denoise]).encode())
    return h.hexdigest()


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


def _vertex_points(sc: Scene, tris: np.ndarray):
    """Unique render vertices (object, position, normal) of triangles ``tris``."""
    P = sc.positions[tris].reshape(-1, 3)
    Nn = sc.normals[tris].reshape(-1, 3).astype(np.float64)
    obj = np.repeat(sc.object_id[tris], 3).astype(np.float64)[:, None]
    key = np.concatenate([obj, P, Nn], axis=1)
    uniq, inverse = np.unique(key, axis=0, return_inverse=True)
    n = uniq[:, 4:7]
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(ln > 1e-6, n / np.where(ln > 0, ln, 1), [0.0, 0.0, 1.0])
    return uniq[:, 1:4], n, inverse.reshape(-1, 3).astype(np.int32)


def scene_face_data(sc: Scene, *, analytic: bool = True, cancel=None):
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


def bake_points_input(sc: Scene, set_index: int, gb, fn, clear, normal_group) -> Points:
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
    return Points(gb.position, gb.normal, gb.geo_normal,
                  gb.texel + (np.int64(set_index) << 40), analytic, group)



@dataclasses.dataclass
class _SetResult:
    index: int
    name: str
    report: dict
    files: list
    incident: object = None         # bounce.IncidentSet of the transfer (when bouncing)
    T_texels: np.ndarray | None = None
    gb: object = None
    pts: object = None
    storage: str = "float32"        # precision of T_texels: "float32" (this run) or "half" (loaded)


class _AnyEvent:
    """is_set() of either event: helpers stop when the user cancels *or* the bake
    fails (without setting the caller's event on a failure)."""

    def __init__(self, *events):
        self.events = [e for e in events if e is not None]

    def is_set(self) -> bool:
        return any(e.is_set() for e in self.events)


class _Bake:
    """One bake: shared state of its stages (see bake_scene)."""

    def __init__(self, sc, out_dir, st, light, progress, cancel, sets):
        self.sc, self.out_dir, self.st, self.progress, self.cancel = sc, out_dir, st, progress, cancel
        self.failed = threading.Event()
        self.stop = _AnyEvent(cancel, self.failed)      # what helper tasks check
        self.seconds: dict[str, float] = {}
        self.warnings: list[str] = []
        self.stage = _Stage(out_dir)
        self.set_ids = list(range(sc.n_sets))
        if sets is not None:
            unknown = set(sets) - set(sc.set_names)
            if unknown:
                raise BakeError(f"unknown texture sets {sorted(unknown)}; the scene has {sc.set_names}")
            self.set_ids = [sc.set_names.index(s) for s in sets]
        self.K = st.bands ** 2
        self.light = None
        if light is not None:
            from ..shading.model import prepare_light
            self.light = prepare_light(light, st.bands)
        # One more worker than cores: the first set's G-buffer is built from a
        # helper that then waits for its row bands on this same pool.
        self.helpers = cf.ThreadPoolExecutor(max_workers=max(2, st.n_threads) + 1)

    def emit(self, **event):
        _emit(self.progress, **event)

    def check_cancel(self):
        """Raise Cancelled if the bake was cancelled (cheap: between sets, levels, files)."""
        if self.cancel is not None and self.cancel.is_set():
            raise Cancelled()

    def wait(self, future):
        """A helper's result, waiting in 50 ms steps so that cancellation is noticed."""
        while True:
            try:
                return future.result(timeout=0.05)
            except cf.TimeoutError:
                self.check_cancel()

    def wait_tables(self):
        """Wait for the ray patterns and estimator tables (warm_tables on a helper)."""
        fut = getattr(self, "tables", None)
        if fut is not None and not fut.done():
            self.emit(type="progress", stage="tables", fraction=0.0)
        if fut is not None:
            self.wait(fut)

    def warn(self, msg):
        self.warnings.append(msg)
        self.emit(type="warning", message=msg)

    def gbuffer_of(self, s):
        return build_gbuffer(self.sc, s, normal_maps=self.st.normal_maps, executor=self.helpers,
                             bands=max(2, self.st.n_threads), cancel=self.stop)

    # --- geometry shared by every stage -------------------------------------------------
    def prepare(self, first_set):
        st = self.st
        first_gb = self.helpers.submit(self.gbuffer_of, first_set) if first_set is not None else None
        self.tables = None
        if first_set is not None or st.vertex_mode:
            # Ray patterns, while the cores are not tracing.
            self.tables = self.helpers.submit(warm_tables, st, self.stop)
        self.emit(type="progress", stage="bvh", fraction=0.0)
        t = time.perf_counter()
        self.rs = RayScene(self.sc.positions, cancel=self.cancel)
        self.seconds["bvh"] = time.perf_counter() - t
        t = time.perf_counter()
        if st.analytic:
            self.emit(type="progress", stage="analytic-test", fraction=0.0)
        self.fn, self.normal_group, self.clear, self.clear_stats = scene_face_data(self.sc, analytic=st.analytic,
                                                                                   cancel=self.cancel)
        self.seconds["analytic_test"] = time.perf_counter() - t
        return first_gb

    # --- transfer ---------------------------------------------------------------------------
    def transfer_set(self, si, s, gb, keep_for_bounce):
        st, sc, K = self.st, self.sc, self.K
        name = sc.set_names[s]
        rep = {"name": name, "resolution": [gb.width, gb.height], **gb.stats}
        if gb.stats["overlap_texels"]:
            msg = (f"set {name!r}: {gb.stats['overlap_texels']} texels are covered by overlapping "
                   f"UV islands (objects: {', '.join(gb.stats['overlap_objects'])}); each keeps "
                   f"one surface, the others are wrong there. Re-unwrap without overlaps.")
            if st.overlap == "error":
                raise BakeError(msg)
            self.warn(msg)
        if gb.stats["zero_area_uv_triangles"]:
            self.warn(f"set {name!r}: {gb.stats['zero_area_uv_triangles']} triangles have zero UV area "
                      f"and get no texels (they still cast shadows)")
        if gb.n == 0:
            self.warn(f"set {name!r}: no texel is covered by its UV layout; skipped")
            rep["skipped"] = True
            return _SetResult(s, name, rep, [])
        pts = bake_points_input(sc, s, gb, self.fn, self.clear, self.normal_group)
        self.wait_tables()
        t = time.perf_counter()

        def on_progress(done, total, rays):
            self.emit(type="progress", stage="trace", set=name, fraction=done / max(total, 1), rays=rays,
                      rays_per_s=rays / max(time.perf_counter() - t, 1e-9), set_index=si,
                      sets=len(self.set_ids))

        # Chunks write whole rows (N, K) (a chunk's texels are scattered over the
        # atlas; K separate plane writes per texel cost more than the trace glue).
        T_texels, info = bake_points(self.rs, pts, st, progress=on_progress, cancel=self.cancel)
        self.seconds["trace"] += time.perf_counter() - t
        t = time.perf_counter()
        if not keep_for_bounce:
            # The surface is traced: free it before the planes join the texel rows
            # (this keeps the peak below G-buffer + planes).
            del pts
            gb.release_surface()
        texel = gb.texel
        tex = planes_from_rows(texel, T_texels, gb.height * gb.width,
                               executor=self.helpers).reshape(K, gb.height, gb.width)
        if not keep_for_bounce:
            T_texels = None
        mask = np.zeros(gb.height * gb.width, bool)
        mask[texel] = True
        mask = mask.reshape(gb.height, gb.width)
        mips = []
        if st.mips:
            cov = np.zeros(gb.height * gb.width, np.float32)
            cov[texel] = gb.coverage
            mips = mip_chain(tex, cov.reshape(gb.height, gb.width))
        dilate(tex, mask, st.dilate, executor=self.helpers)
        self.seconds["dilate"] += time.perf_counter() - t
        t = time.perf_counter()
        attrs = dict(self.attrs_common, kind_detail="visibility*cosine", dilate=st.dilate,
                     texels=int(gb.n), analytic_texels=info["analytic_points"])
        fname = f"{name}.transfer.exr"
        self.check_cancel()
        half = self.write_planes(fname, tex, "transfer", attrs, rgb=False)
        files = [fname]
        for lvl, (mt, _) in enumerate(mips, start=1):
            mname = f"{name}.transfer.mip{lvl}.exr"
            self.write_planes(mname, mt, "transfer", dict(attrs, mip_level=lvl), rgb=False, half=half)
            files.append(mname)
        self.seconds["write"] += time.perf_counter() - t
        rep.update(file=fname, storage="half" if half else "float",
                   analytic_texels=info["analytic_points"], traced_texels=info["traced_points"],
                   rays_traced=info["rays_traced"], rays_naive=info["rays_naive"],
                   rays_below_horizon_skipped=info["rays_below_horizon_skipped"],
                   adaptive_early_stops=info["adaptive_early_stops"],
                   threads=info["threads"], trace_seconds=info["seconds"])
        res = _SetResult(s, name, rep, files, T_texels=T_texels)
        if keep_for_bounce:
            from .bounce import IncidentSet
            with numpy_hugepage_advice(True):   # looked up at random by bounce rays
                res.incident = IncidentSet(pixel_major(tex), gb.width, gb.height)
            res.gb, res.pts = gb, pts
        return res

    def write_planes(self, fname, planes, kind, attrs, *, rgb, half=None):
        """Write staged; half precision unless values overflow it. Returns half."""
        self.check_cancel()
        self.emit(type="progress", stage="write", file=fname, fraction=0.0)
        half = self.st.half if half is None else half
        rng = exr_io.value_range(planes, self.helpers)
        over = exr_io.half_overflow(planes, rng) if half else 0
        if over:
            self.warn(f"{fname}: {over} values exceed the half-float range; stored as float32")
            half = False
        exr_io.write_sh_planes(self.stage.path(fname), planes, kind=kind, half=half, rgb=rgb,
                               attrs=attrs, atomic=False, executor=self.helpers, rng=rng)
        return half

    def load_transfer_set(self, s, gb, old_report):
        """Bounce-only re-bake: the set's transfer as written (what renders)."""
        from .bounce import IncidentSet
        name = self.sc.set_names[s]
        data, attrs = exr_io.read_sh_exr(os.path.join(self.out_dir, f"{name}.transfer.exr"))
        planes = np.ascontiguousarray(np.moveaxis(data, 2, 0))
        with numpy_hugepage_advice(True):       # looked up at random by bounce rays
            pm = pixel_major(planes)
            incident = IncidentSet(pm, gb.width, gb.height)
        res = _SetResult(s, name, old_report, [], T_texels=pm[gb.texel], incident=incident)
        res.gb = gb
        res.pts = bake_points_input(self.sc, s, gb, self.fn, self.clear, self.normal_group)
        res.storage = attrs.get("storage", "half")
        return res

    # --- bounces ---------------------------------------------------------------------------
    def bounce_levels(self, results):
        """Bake levels 1..bounces of every set that has texels; returns (per set
        and level reports, files written, early-stop note or None)."""
        from .bounce import (HALF_OPEN_TOLERANCE, OPEN_TOLERANCE, ExitShader, bake_bounce_set,
                             bounce_settings, exit_textures, glossy_triangles, incident_at, level_energy,
                             open_texels, surface_texels)
        from .denoise import denoise_bounce, resolve_filter
        st, sc, K = self.st, self.sc, self.K
        bst = bounce_settings(st, st.bounce_rays)
        live = [r for r in results if r.incident is not None]
        filt = resolve_filter(st.bounce_denoise, st.bounce_rays)
        reports, files = [], []
        skip, surf = {}, {}
        t = time.perf_counter()
        for r in live:
            self.check_cancel()
            # Zero without rays: analytic texels, and texels no transfer ray saw geometry
            # from (tested against half-float rounding when read back from disk).
            tol = HALF_OPEN_TOLERANCE if r.storage == "half" else OPEN_TOLERANCE
            skip[r.index] = r.pts.analytic | open_texels(r.T_texels, r.gb.normal, st.bands, tol)
            surf[r.index] = surface_texels(sc, r.gb, st.dilate)
        glossy_tri = glossy_triangles(sc)
        # Level 1 leaves each surface with the fixed light times its transfer.
        Lp = {r.index: incident_at(surf[r.index], r.incident, self.light, st.bands) for r in live}
        for r in live:
            r.incident = None                  # the exit textures replace it
        direct = sum(level_energy(v) for v in Lp.values())
        self.seconds["bounce_exit"] = time.perf_counter() - t
        stopped = None
        for level in range(1, st.bounces + 1):
            self.check_cancel()
            t = time.perf_counter()
            exits = {i: exit_textures(surf[i], v, st.bands) for i, v in Lp.items()}
            shader = ExitShader(sc, exits, st.bands, glossy_tri)
            self.seconds["bounce_exit"] += time.perf_counter() - t
            nxt, energy = {}, 0.0
            for r in live:
                self.check_cancel()
                name = r.name
                t = time.perf_counter()
                if skip[r.index].all():
                    reports.append({"name": name, "level": level, "skipped": "sees no geometry",
                                    "texels": int(r.gb.n), "rays_traced": 0, "hits_shaded": 0})
                    continue

                def on_progress(done, total, rays, name=name, level=level):
                    self.emit(type="progress", stage="bounce", set=name, level=level,
                              fraction=done / max(total, 1), rays=rays)

                tex, mask, stats = bake_bounce_set(self.rs, r.gb, r.pts, skip[r.index], shader, bst, level,
                                                   progress=on_progress, cancel=self.cancel)
                self.seconds["bounce_trace"] += time.perf_counter() - t
                t = time.perf_counter()
                tex = tex.reshape(3 * K, r.gb.height, r.gb.width)
                if filt != "none":
                    td = time.perf_counter()
                    self.check_cancel()
                    tex = denoise_bounce(tex, r.gb, filt, st.bands)
                    stats["denoise"] = {"filter": filt, "seconds": time.perf_counter() - td}
                energy += level_energy(tex.reshape(3 * K, -1)[:, r.gb.texel].T)
                fname = f"{name}.bounce{level}.exr"
                attrs = dict(self.attrs_common, level=level, rays=st.bounce_rays,
                             light_hash=self.light_hash, materials_hash=self.materials_hash,
                             texels=int(r.gb.n))
                with numpy_hugepage_advice(False):      # fresh arrays, streamed once
                    dilate(tex, mask, st.dilate, executor=self.helpers)
                    half = self.write_planes(fname, tex, "bounce", attrs, rgb=True)
                files.append(fname)
                if level < st.bounces:
                    nxt[r.index] = tex.reshape(3 * K, -1)[:, surf[r.index].valid].T.reshape(-1, 3, K)
                stats.update(name=name, level=level, file=fname, storage="half" if half else "float")
                reports.append(stats)
                self.seconds["bounce_write"] += time.perf_counter() - t
            del exits, shader
            Lp = nxt
            if not Lp:
                break
            ratio = energy / direct if direct > 0 else 0.0
            if level < st.bounces and ratio < st.bounce_tolerance:
                stopped = {"after_level": level, "energy_ratio": ratio, "tolerance": st.bounce_tolerance,
                           "levels_not_baked": st.bounces - level}
                self.emit(type="info", message=f"bounce level {level} carries {100 * ratio:.3g} % of the direct "
                          f"light (< {100 * st.bounce_tolerance:g} %): levels {level + 1}-{st.bounces} "
                          f"are not baked")
                break
        return reports, files, stopped

    def close(self, failed: bool = False):
        """Shut the helper pool down. After a failure its running tasks stop at
        their next check; after a cancel they are not waited for (a G-buffer
        band may be inside a long numpy call), so the caller can exit at once."""
        if failed:
            self.failed.set()
        cancelled = self.cancel is not None and self.cancel.is_set()
        self.helpers.shutdown(wait=not cancelled, cancel_futures=True)


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
               job: str | None = None, source: str | None = None) -> dict:
    """Bake every texture set of ``sc`` into ``out_dir``.

    light : (K', 3) RGB SH of the environment in world coordinates, K' >= bands^2;
            needed for bounce textures (without it they are skipped with a warning).
    job, source : the job file this scene came from and what that was made from
          (e.g. the .blend), recorded in the folder's lock so that a second
          bake into the folder can say which bake holds it.
    Returns the manifest dict (``manifest["skipped"]`` is True when an identical
    bake was already there). Raises BakeError (also when another bake holds the
    folder) / SceneError / MemoryLimitError for bad input and transfer.Cancelled
    when ``cancel`` is set. The folder lock is released on every exit path.
    """
    from ..shading.materials import materials_hash
    from ..shading.model import light_hash
    st = (settings or BakeSettings()).validate()
    out_dir = check_out_dir(out_dir)
    t_all = time.perf_counter()
    lock = lock_out_dir(out_dir, job, source)
    try:
        if lock.taken_over:
            _emit(progress, type="warning", message=f"took over the lock of a bake that is gone "
                                                    f"(pid {lock.taken_over.get('pid')})")
        removed = atomic.remove_stale_temporaries(out_dir)
        bk = _Bake(sc, out_dir, st, light, progress, cancel, sets)
        if removed:
            bk.warn(f"removed {len(removed)} temporary file(s) left by an interrupted bake")
        failed = True
        try:
            result = _run(bk, sc, st, out_dir, t_all, skip_if_unchanged, light_hash, materials_hash)
            failed = False
            return result
        except BaseException:
            bk.stage.abort()
            raise
        finally:
            bk.close(failed)
    finally:
        lock.release()


def _run(bk, sc, st, out_dir, t_all, skip_if_unchanged, light_hash, materials_hash):
    in_hash = geometry_hash(sc)
    set_hash = settings_hash(st)
    bouncing = st.bounces > 0 and st.textures
    if bouncing and bk.light is None:
        bk.warn("no light given: bounce textures (which bake the light in) are skipped")
        bouncing = False
    if bouncing and st.bounce_denoise == "oidn":
        from .denoise import oidn_available
        if not oidn_available():
            raise BakeError("bounce denoiser 'oidn' needs the optional package pyoidn (pip install pyoidn); "
                            "or use --bounce-denoise edge-aware or none")
    bk.light_hash = light_hash(bk.light) if bk.light is not None else None
    bk.materials_hash = materials_hash(sc)
    b_key = bounce_key(in_hash, set_hash, bk.light, bk.materials_hash, st) if bouncing else None
    old = read_manifest(out_dir)
    transfer_ok, bounce_ok = _reusable(bk, old, out_dir, in_hash, set_hash, b_key, bouncing, skip_if_unchanged)
    if transfer_ok and bounce_ok:
        old["skipped"] = True
        bk.emit(type="done", skipped=True, manifest=os.path.join(out_dir, MANIFEST))
        return old

    resident = 0
    for s in bk.set_ids:
        w, h = (int(v) for v in sc.set_resolution[s])
        check_fits(set_bytes(w, h, bk.K, threads=st.n_threads, chunk_rays=st.chunk_rays, rays=st.rays,
                             bounce=bouncing) + bvh_bytes(sc.n_triangles),
                   f"texture set {sc.set_names[s]!r} at {w}x{h}, {st.bands} bands")
        resident += bounce_resident_bytes(w, h, bk.K) if bouncing else 0
    if resident:
        check_fits(resident, f"bouncing light between {len(bk.set_ids)} texture sets (all stay in memory)")
    bk.attrs_common = {"rays": st.rays, "seed": st.seed, "sampler": st.sampler,
                       "estimator": st.estimator, "input_hash": in_hash}
    bk.seconds.update(gbuffer=0.0, trace=0.0, dilate=0.0, write=0.0, vertex=0.0,
                      bounce_exit=0.0, bounce_trace=0.0, bounce_write=0.0)
    todo = bk.set_ids if st.textures else []
    results = []
    old_reports = {r.get("name"): r for r in _dicts((old or {}).get("sets"))}
    # G-buffers, texel rows, planes, EXR channels: fresh arrays streamed once,
    # which fault in faster as normal pages (memory.numpy_hugepage_advice).
    with numpy_hugepage_advice(False):
        first_gb = bk.prepare(todo[0] if todo else None)
        for si, s in enumerate(todo):
            t = time.perf_counter()
            bk.check_cancel()
            bk.emit(type="progress", stage="gbuffer", set=sc.set_names[s], fraction=0.0)
            gb = bk.wait(first_gb) if si == 0 else bk.gbuffer_of(s)
            release_free_memory()       # the rasteriser's temporaries, freed on helper threads
            bk.seconds["gbuffer"] += time.perf_counter() - t
            if transfer_ok:
                if gb.n:
                    results.append(bk.load_transfer_set(s, gb, old_reports.get(sc.set_names[s], {})))
            else:
                results.append(bk.transfer_set(si, s, gb, keep_for_bounce=bouncing))

    vertex_reports, vertex_files = [], []
    if st.vertex_mode and not transfer_ok:
        t = time.perf_counter()
        for s in bk.set_ids:
            name = sc.set_names[s]
            tris = sc.triangles_of_set(s)
            vp, vn, corner = _vertex_points(sc, tris)
            bk.check_cancel()
            bk.emit(type="progress", stage="vertex", set=name, fraction=0.0)
            bk.wait_tables()
            pts = Points(vp, vn, vn, np.arange(vp.shape[0], dtype=np.int64) + (np.int64(s) << 40)
                         + (np.int64(1) << 62), np.zeros(vp.shape[0], bool))
            vc, info = bake_points(bk.rs, pts, dataclasses.replace(st, analytic=False), cancel=bk.cancel)
            vname = f"{name}.vertex.npz"
            bk.check_cancel()
            with open(bk.stage.path(vname), "wb") as f:
                np.savez(f, format=np.array("prtt-vertex-transfer"), version=np.array(1),
                         bands=np.array(st.bands), positions=vp.astype(np.float32),
                         normals=vn.astype(np.float32), coeffs=vc, corner_vertex=corner,
                         triangles=tris.astype(np.int64), input_hash=np.array(in_hash))
            vertex_files.append(vname)
            vertex_reports.append({"name": name, "file": vname, "vertices": int(vp.shape[0]),
                                   "rays_traced": info["rays_traced"]})
        bk.seconds["vertex"] = time.perf_counter() - t

    bounce = None
    if bouncing:
        reports, bfiles, stopped = bk.bounce_levels(results)
        bounce = {"key": b_key, "levels": st.bounces, "rays": st.bounce_rays, "stopped_early": stopped,
                  "light_hash": bk.light_hash, "materials_hash": bk.materials_hash,
                  "files": bfiles, "sets": reports,
                  "rays_traced": sum(r["rays_traced"] for r in reports),
                  "hits_shaded": sum(r["hits_shaded"] for r in reports)}

    reused_info = {}
    if transfer_ok:
        transfer_files = old.get("transfer_files", old.get("files", []))
        set_reports = _dicts(old.get("sets"))
        vertex_reports = _dicts(old.get("vertex"))
        vertex_files = [v.get("file") for v in vertex_reports]
        reused_info = {f: old["file_info"][f] for f in transfer_files}     # verified by _reusable
    else:
        transfer_files = [f for r in results for f in r.files] + vertex_files
        set_reports = [r.report for r in results]
    files = transfer_files + (bounce["files"] if bounce else [])
    if not files:
        raise BakeError("nothing was baked: no texture set has covered texels")
    totals = {"rays_traced": 0, "rays_naive": 0, "texels": 0, "analytic_texels": 0,
              "rays_below_horizon_skipped": 0}
    for r in set_reports:
        for k in totals:
            totals[k] += r.get(k, 0)
    totals["rays_traced"] += sum(v.get("rays_traced", 0) for v in vertex_reports)
    bk.seconds["total"] = time.perf_counter() - t_all
    trace_s = bk.seconds["trace"] + bk.seconds["vertex"]
    manifest = {
        "format": "prtt-bake", "format_version": BAKE_FORMAT_VERSION,
        "prtt_version": __version__, "kind": "transfer",
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "input_hash": in_hash, "settings_hash": set_hash, "settings": st.as_dict(),
        "files": files, "transfer_files": transfer_files, "sets": set_reports, "vertex": vertex_reports,
        "bounce": bounce, "transfer_reused": bool(transfer_ok),
        "analytic_test": getattr(bk, "clear_stats", {}), "totals": totals, "seconds": bk.seconds,
        "rays_per_second_trace": totals["rays_traced"] / trace_s if trace_s > 0 and not transfer_ok else 0.0,
        "rays_per_second_end_to_end": totals["rays_traced"] / bk.seconds["total"] if not transfer_ok else 0.0,
        "warnings": bk.warnings, "skipped": False,
    }
    old_files = (old or {}).get("files", [])
    stale = [f for f in (old_files if _plain_names(old_files) else []) if f not in files and ".bounce" in f]
    bk.check_cancel()
    new_info = bk.stage.seal()
    manifest["file_info"] = {f: (new_info.get(f) or reused_info[f]) for f in files}
    _commit(bk, manifest, out_dir, stale)
    bk.emit(type="done", skipped=False, manifest=os.path.join(out_dir, MANIFEST))
    return manifest


def _commit(bk, manifest: dict, out_dir: str, stale: list[str]) -> None:
    """Rename the staged outputs into place and write the manifest, holding
    atomic.COMMIT_LOCK: a signal's watchdog (worker.py) waits for it rather
    than exiting between the renames and the manifest. A cancel that came
    before the lock was taken still wins (nothing is renamed)."""
    with atomic.COMMIT_LOCK:
        bk.check_cancel()
        bk.stage.commit()
        with atomic_write(os.path.join(out_dir, MANIFEST)) as tmp:
            with open(tmp, "w", encoding="utf-8") as f:
                json.dump(manifest, f, indent=1)
        for f in stale:                       # bounce levels no longer baked
            try:
                os.remove(os.path.join(out_dir, f))
            except OSError:
                pass
        atomic.mark_committed()


def _reusable(bk, old, out_dir, in_hash, set_hash, b_key, bouncing, skip_if_unchanged):
    """(transfer outputs reusable, bounce outputs reusable) per the old manifest,
    with every file checked against its recorded size and sha256. A mismatch is
    reported as a warning and that part is re-baked."""
    if not (skip_if_unchanged and old):
        return False, False
    same_inputs = old.get("input_hash") == in_hash and old.get("settings_hash") == set_hash
    transfer_ok = False
    if same_inputs:
        why = outputs_changed(old, out_dir, old.get("transfer_files", old.get("files", [])))
        transfer_ok = why is None
        if why:
            bk.warn(f"re-baking the transfer: {why}")
    old_bounce = old.get("bounce") or {}
    if not bouncing:
        return transfer_ok, not old_bounce.get("files")
    if old_bounce.get("key") != b_key:
        return transfer_ok, False
    why = outputs_changed(old, out_dir, old_bounce.get("files", []))
    if why:
        bk.warn(f"re-baking the bounce textures: {why}")
    return transfer_ok, why is None
