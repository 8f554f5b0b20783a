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
are re-baked (from the transfer textures on disk).

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

from . import exr_io
from .atomic import TMP_PREFIX, atomic_write
from .dilate import dilate, mip_chain
from .gbuffer import build_gbuffer, face_normals
from .hemisphere_clear import FLAT_COS, clear_triangles
from .memory import bounce_resident_bytes, check_fits, numpy_hugepage_advice, release_free_memory, set_bytes
from .raytrace import RayScene
from .scene import Scene, geometry_hash
from .texsample import pixel_major, planes_from_rows
from .transfer import SAME_NORMAL, Points, TransferSettings, bake_points, warm_tables

MANIFEST = "manifest.json"
BAKE_FORMAT_VERSION = 1


@dataclasses.dataclass
class BakeSettings(TransferSettings):
    dilate: int = 3                 # texels of dilation
    half: bool = True               # float16 EXR (auto float32 on overflow)
    mips: bool = False              # write coverage-weighted mip levels
    normal_maps: bool = True
    vertex_mode: bool = False       # also bake per-vertex transfer
    textures: bool = True           # bake texture sets (False: vertex mode only)
    overlap: str = "warn"           # overlapping UVs: "warn" or "error"
    bounces: int = 1                # inter-reflection levels (0 = off; needs a light)
    bounce_rays: int = 64           # rays per texel per bounce level

    def validate(self) -> "BakeSettings":
        super().validate()
        if isinstance(self.dilate, bool) or not isinstance(self.dilate, (int, np.integer)) \
                or not 0 <= self.dilate <= 64:
            raise ValueError(f"dilate must be an integer 0..64 texels, got {self.dilate!r}")
        if self.overlap not in ("warn", "error"):
            raise ValueError(f"overlap must be 'warn' or 'error', got {self.overlap!r}")
        if not (self.textures or self.vertex_mode):
            raise ValueError("nothing to bake: enable textures or vertex mode")
        for name, hi in (("bounces", 8), ("bounce_rays", 1 << 14)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not \
                    (0 if name == "bounces" else 1) <= v <= hi:
                raise ValueError(f"{name} must be an integer {0 if name == 'bounces' else 1}..{hi}, got {v!r}")
        return self

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "BakeSettings":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown bake settings: {sorted(unknown)}")
        return cls(**d)

    def result_key(self) -> dict:
        """Settings that change the transfer textures (not threads, chunking or bounces)."""
        d = self.as_dict()
        for k in ("threads", "chunk_rays", "bounces", "bounce_rays"):
            d.pop(k)
        return d


class BakeError(RuntimeError):
    """A bake could not run; the message says why (nothing was written)."""


class _Stage:
    """Output files written as temporaries, renamed together on commit."""

    def __init__(self, folder):
        self.folder = folder
        self.files: list[tuple[str, str]] = []

    def path(self, name: str) -> str:
        base, ext = os.path.splitext(name)
        tmp = os.path.join(self.folder, f"{TMP_PREFIX}{base}-{os.getpid()}-{len(self.files)}{ext}")
        self.files.append((tmp, os.path.join(self.folder, name)))
        return tmp

    def commit(self):
        for tmp, final in self.files:
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
        for tmp, final in self.files:
            os.replace(tmp, final)
        self.files = []

    def abort(self):
        for tmp, _ in self.files:
            try:
                os.remove(tmp)
            except OSError:
                pass
        self.files = []


def _emit(progress, **event):
    if progress is not None:
        progress(event)


def settings_hash(settings: BakeSettings) -> str:
    return hashlib.sha256(json.dumps(settings.result_key(), sort_keys=True).encode()).hexdigest()


def read_manifest(out_dir) -> dict | None:
    try:
        with open(os.path.join(out_dir, MANIFEST), encoding="utf-8") as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


def _files_present(out_dir, files) -> bool:
    return all(os.path.isfile(os.path.join(out_dir, f)) for f in files)


def transfer_up_to_date(m: dict | None, out_dir, in_hash: str, set_hash: str) -> bool:
    """Does manifest ``m`` describe complete transfer outputs of these inputs?"""
    return bool(m and m.get("input_hash") == in_hash and m.get("settings_hash") == set_hash
                and _files_present(out_dir, m.get("transfer_files", m.get("files", []))))


def bounce_key(in_hash: str, set_hash: str, light: np.ndarray | None, mat_hash: str,
               st: BakeSettings) -> str:
    """Identity of the bounce textures: transfer, light, materials, bounce settings."""
    from .shading import light_hash
    h = hashlib.sha256("|".join([in_hash, set_hash, light_hash(light) if light is not None else "-",
                                 mat_hash, str(st.bounces), str(st.bounce_rays)]).encode())
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


def scene_face_data(sc: Scene, *, analytic: bool = True):
    """Per-triangle data every set of a bake needs.

    Returns (face normals (T, 3) turned to the shaded side (the mean corner
    normal), zero for degenerate faces; normal group (T,) int64, equal for
    faces whose oriented normals agree to 1e-9, -1 for degenerate ones;
    clear (T,) bool from hemisphere_clear; its stats).
    """
    fn, _ = face_normals(sc.positions)
    mean_n = sc.normals.astype(np.float64).sum(axis=1)
    fn = np.where((np.einsum("tc,tc->t", fn, mean_n) < 0)[:, None], -fn, fn)
    baked = np.flatnonzero((sc.set_id >= 0) & np.any(fn != 0, axis=1))
    normal_group = np.full(sc.n_triangles, -1, np.int64)
    if baked.size:
        _, inv = np.unique(np.round(fn[baked], 9), axis=0, return_inverse=True)
        normal_group[baked] = inv.reshape(-1)
    clear = np.zeros(sc.n_triangles, bool)
    stats = {}
    if analytic:
        clear, stats = clear_triangles(sc.positions, fn, candidates=np.flatnonzero(sc.set_id >= 0))
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


class _Bake:
    """One bake: shared state of its stages (see bake_scene)."""

    def __init__(self, sc, out_dir, st, light, progress, cancel, sets):
        self.sc, self.out_dir, self.st, self.progress, self.cancel = sc, out_dir, st, progress, cancel
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
            from .shading import prepare_light
            self.light = prepare_light(light, st.bands)
        # One more worker than cores: the first set's G-buffer is built from a
        # helper that then waits for its row bands on this same pool.
        self.helpers = cf.ThreadPoolExecutor(max_workers=max(2, st.n_threads) + 1)

    def emit(self, **event):
        _emit(self.progress, **event)

    def warn(self, msg):
        self.warnings.append(msg)
        self.emit(type="warning", message=msg)

    def gbuffer_of(self, s):
        return build_gbuffer(self.sc, s, normal_maps=self.st.normal_maps, executor=self.helpers,
                             bands=max(2, self.st.n_threads))

    # --- geometry shared by every stage -------------------------------------------------
    def prepare(self, first_set):
        st = self.st
        first_gb = self.helpers.submit(self.gbuffer_of, first_set) if first_set is not None else None
        if first_set is not None:
            self.helpers.submit(warm_tables, st)     # ray patterns, while the cores are not tracing
        self.emit(type="progress", stage="bvh", fraction=0.0)
        t = time.perf_counter()
        self.rs = RayScene(self.sc.positions)
        self.seconds["bvh"] = time.perf_counter() - t
        t = time.perf_counter()
        if st.analytic:
            self.emit(type="progress", stage="analytic-test", fraction=0.0)
        self.fn, self.normal_group, self.clear, self.clear_stats = scene_face_data(self.sc, analytic=st.analytic)
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
        from .bounce import (HALF_OPEN_TOLERANCE, OPEN_TOLERANCE, HitShader, IncidentSet, bake_bounce_set,
                             bounce_settings, open_texels)
        st, sc, K = self.st, self.sc, self.K
        bst = bounce_settings(st, st.bounce_rays)
        live = [r for r in results if r.incident is not None]
        incident = {r.index: r.incident for r in live}
        reports, files = [], []
        skip = {}
        for r in live:
            # Zero without rays: analytic texels, and texels no transfer ray saw geometry
            # from (tested against half-float rounding when read back from disk).
            tol = HALF_OPEN_TOLERANCE if r.storage == "half" else OPEN_TOLERANCE
            skip[r.index] = r.pts.analytic | open_texels(r.T_texels, r.gb.normal, st.bands, tol)
        for level in range(1, st.bounces + 1):
            shader = HitShader(sc, incident, self.light, st.bands, transfer=(level == 1),
                               normal_maps=st.normal_maps)
            nxt = {}
            for r in live:
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
                fname = f"{name}.bounce{level}.exr"
                attrs = dict(self.attrs_common, level=level, rays=st.bounce_rays,
                             light_hash=self.light_hash, materials_hash=self.materials_hash,
                             texels=int(r.gb.n))
                with numpy_hugepage_advice(False):      # fresh arrays, streamed once
                    dilate(tex, mask, st.dilate, executor=self.helpers)
                    half = self.write_planes(fname, tex, "bounce", attrs, rgb=True)
                files.append(fname)
                nxt[r.index] = IncidentSet(pixel_major(tex), r.gb.width, r.gb.height)
                stats.update(name=name, level=level, file=fname, storage="half" if half else "float")
                reports.append(stats)
                self.seconds["bounce_write"] += time.perf_counter() - t
            incident = nxt
            if not incident:
                break
        return reports, files

    def close(self):
        self.helpers.shutdown(wait=True, cancel_futures=True)


def bake_scene(sc: Scene, out_dir, settings: BakeSettings | None = None, *, light=None,
               progress=None, cancel: threading.Event | None = None,
               skip_if_unchanged: bool = True, sets: list[str] | None = None) -> dict:
    """Bake every texture set of ``sc`` into ``out_dir``.

    light : (K', 3) RGB SH of the environment in world coordinates, K' >= bands^2;
            needed for bounce textures (without it they are skipped with a warning).
    Returns the manifest dict (``manifest["skipped"]`` is True when an identical
    bake was already there). Raises BakeError / SceneError / MemoryLimitError
    for bad input and transfer.Cancelled when ``cancel`` is set.
    """
    from .materials import materials_hash
    from .shading import light_hash
    st = (settings or BakeSettings()).validate()
    out_dir = check_out_dir(out_dir)
    t_all = time.perf_counter()
    bk = _Bake(sc, out_dir, st, light, progress, cancel, sets)
    try:
        return _run(bk, sc, st, out_dir, t_all, skip_if_unchanged, light_hash, materials_hash)
    except BaseException:
        bk.stage.abort()
        raise
    finally:
        bk.close()


def _run(bk, sc, st, out_dir, t_all, skip_if_unchanged, light_hash, materials_hash):
    in_hash = geometry_hash(sc)
    set_hash = settings_hash(st)
    bouncing = st.bounces > 0 and st.textures
    if bouncing and bk.light is None:
        bk.warn("no light given: bounce textures (which bake the light in) are skipped")
        bouncing = False
    bk.light_hash = light_hash(bk.light) if bk.light is not None else None
    bk.materials_hash = materials_hash(sc)
    b_key = bounce_key(in_hash, set_hash, bk.light, bk.materials_hash, st) if bouncing else None
    old = read_manifest(out_dir)
    transfer_ok = skip_if_unchanged and transfer_up_to_date(old, out_dir, in_hash, set_hash)
    old_bounce = (old or {}).get("bounce") or {}
    bounce_ok = (not bouncing and not old_bounce.get("files")) or (
        bouncing and old_bounce.get("key") == b_key and _files_present(out_dir, old_bounce.get("files", [])))
    if transfer_ok and bounce_ok:
        old["skipped"] = True
        bk.emit(type="done", skipped=True, manifest=os.path.join(out_dir, MANIFEST))
        return old

    resident = 0
    for s in bk.set_ids:
        w, h = (int(v) for v in sc.set_resolution[s])
        check_fits(set_bytes(w, h, bk.K, threads=st.n_threads, chunk_rays=st.chunk_rays, rays=st.rays,
                             bounce=bouncing), f"texture set {sc.set_names[s]!r} at {w}x{h}, {st.bands} bands")
        resident += bounce_resident_bytes(w, h, bk.K) if bouncing else 0
    if resident:
        check_fits(resident, f"bouncing light between {len(bk.set_ids)} texture sets (all stay in memory)")
    bk.attrs_common = {"rays": st.rays, "seed": st.seed, "sampler": st.sampler,
                       "estimator": st.estimator, "input_hash": in_hash}
    bk.seconds.update(gbuffer=0.0, trace=0.0, dilate=0.0, write=0.0, vertex=0.0,
                      bounce_trace=0.0, bounce_write=0.0)
    todo = bk.set_ids if st.textures else []
    results = []
    old_reports = {r["name"]: r for r in (old or {}).get("sets", [])}
    # G-buffers, texel rows, planes, EXR channels: fresh arrays streamed once,
    # which fault in faster as normal pages (memory.numpy_hugepage_advice).
    with numpy_hugepage_advice(False):
        first_gb = bk.prepare(todo[0] if todo else None)
        for si, s in enumerate(todo):
            t = time.perf_counter()
            bk.emit(type="progress", stage="gbuffer", set=sc.set_names[s], fraction=0.0)
            gb = first_gb.result() if si == 0 else bk.gbuffer_of(s)
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
            bk.emit(type="progress", stage="vertex", set=name, fraction=0.0)
            pts = Points(vp, vn, vn, np.arange(vp.shape[0], dtype=np.int64) + (np.int64(s) << 40)
                         + (np.int64(1) << 62), np.zeros(vp.shape[0], bool))
            vc, info = bake_points(bk.rs, pts, dataclasses.replace(st, analytic=False), cancel=bk.cancel)
            vname = f"{name}.vertex.npz"
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
        reports, bfiles = bk.bounce_levels(results)
        bounce = {"key": b_key, "levels": st.bounces, "rays": st.bounce_rays,
                  "light_hash": bk.light_hash, "materials_hash": bk.materials_hash,
                  "files": bfiles, "sets": reports,
                  "rays_traced": sum(r["rays_traced"] for r in reports),
                  "hits_shaded": sum(r["hits_shaded"] for r in reports)}

    if transfer_ok:
        transfer_files = old.get("transfer_files", old.get("files", []))
        set_reports = old.get("sets", [])
        vertex_reports, vertex_files = old.get("vertex", []), [v["file"] for v in old.get("vertex", [])]
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
    from .. import __version__
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
    stale = [f for f in (old or {}).get("files", []) if f not in files and ".bounce" in f]
    bk.stage.commit()
    with atomic_write(os.path.join(out_dir, MANIFEST)) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(manifest, f, indent=1)
    for f in stale:                       # bounce levels no longer baked
        try:
            os.remove(os.path.join(out_dir, f))
        except OSError:
            pass
    bk.emit(type="done", skipped=False, manifest=os.path.join(out_dir, MANIFEST))
    return manifest
