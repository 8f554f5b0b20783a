"""Baking a scene's transfer textures: G-buffer -> rays -> dilation -> EXR files.

``bake_scene(scene, out_dir, settings)`` is the one code path behind the
worker, ``python -m prtt_addon bake-job`` and the Blender operator. Outputs
(docs/format.md), all staged as temporaries and renamed only when every set
is done, manifest last — a cancelled, failed or killed bake leaves the
previous outputs untouched:

* ``<set>.transfer.exr``        one per texture set (K channels sh000..)
* ``<set>.transfer.mip<k>.exr`` optional coverage-weighted mip levels
* ``<set>.vertex.npz``          optional per-vertex transfer (vertex mode)
* ``manifest.json``             settings, per-set stats, seconds per stage, hashes

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
from .memory import check_fits, set_bytes
from .raytrace import RayScene
from .scene import Scene, scene_hash
from .transfer import SAME_NORMAL, Cancelled, Points, TransferSettings, bake_points

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

    def validate(self) -> "BakeSettings":
        super().validate()
        if isinstance(self.dilate, bool) or not isinstance(self.dilate, (int, np.integer)) \
                or not 0 <= self.dilate <= 64:
            raise ValueError(f"dilate must be an integer 0..64 texels, got {self.dilate!r}")
        if self.overlap not in ("warn", "error"):
            raise ValueError(f"overlap must be 'warn' or 'error', got {self.overlap!r}")
        if not (self.textures or self.vertex_mode):
            raise ValueError("nothing to bake: enable textures or vertex mode")
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
        """Settings that change the result (threads and chunking do not)."""
        d = self.as_dict()
        for k in ("threads", "chunk_rays"):
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


def up_to_date(out_dir, in_hash: str, set_hash: str) -> bool:
    """Does ``out_dir`` hold a complete bake of exactly these inputs and settings?"""
    m = read_manifest(out_dir)
    if not m or m.get("input_hash") != in_hash or m.get("settings_hash") != set_hash:
        return False
    return all(os.path.isfile(os.path.join(out_dir, f)) for f in m.get("files", []))


def _check_out_dir(out_dir) -> str:
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


def bake_scene(sc: Scene, out_dir, settings: BakeSettings | None = None, *,
               progress=None, cancel: threading.Event | None = None,
               skip_if_unchanged: bool = True, sets: list[str] | None = None) -> dict:
    """Bake transfer for every texture set of ``sc`` into ``out_dir``.

    Returns the manifest dict (``manifest["skipped"]`` is True when an identical
    bake was already there). Raises BakeError / SceneError / MemoryLimitError
    for bad input and transfer.Cancelled when ``cancel`` is set.
    """
    st = (settings or BakeSettings()).validate()
    out_dir = _check_out_dir(out_dir)
    t_all = time.perf_counter()
    seconds: dict[str, float] = {}
    warnings: list[str] = []

    def warn(msg):
        warnings.append(msg)
        _emit(progress, type="warning", message=msg)

    in_hash = scene_hash(sc)
    set_hash = settings_hash(st)
    if skip_if_unchanged and up_to_date(out_dir, in_hash, set_hash):
        m = read_manifest(out_dir)
        m["skipped"] = True
        _emit(progress, type="done", skipped=True, manifest=os.path.join(out_dir, MANIFEST))
        return m

    set_ids = list(range(sc.n_sets))
    if sets is not None:
        unknown = set(sets) - set(sc.set_names)
        if unknown:
            raise BakeError(f"unknown texture sets {sorted(unknown)}; the scene has {sc.set_names}")
        set_ids = [sc.set_names.index(s) for s in sets]
    K = st.bands ** 2
    for s in set_ids:
        w, h = (int(v) for v in sc.set_resolution[s])
        check_fits(set_bytes(w, h, K, threads=st.n_threads, chunk_rays=st.chunk_rays, rays=st.rays),
                   f"texture set {sc.set_names[s]!r} at {w}x{h}, {st.bands} bands")

    # Helper threads for the stages between traces (G-buffer bands, dilation,
    # EXR conversion): one core would otherwise sit idle there.
    helpers = cf.ThreadPoolExecutor(max_workers=max(2, st.n_threads))
    todo = [s for s in set_ids] if st.textures else []

    def gbuffer_of(s):
        t0 = time.perf_counter()
        return build_gbuffer(sc, s, normal_maps=st.normal_maps, executor=helpers,
                             bands=max(2, st.n_threads)), time.perf_counter() - t0

    # The first G-buffer is built while the BVH and the analytic test run.
    first_gb = helpers.submit(gbuffer_of, todo[0]) if todo else None
    _emit(progress, type="progress", stage="bvh", fraction=0.0)
    t = time.perf_counter()
    rs = RayScene(sc.positions)
    seconds["bvh"] = time.perf_counter() - t

    t = time.perf_counter()
    if st.analytic:
        _emit(progress, type="progress", stage="analytic-test", fraction=0.0)
    fn, normal_group, clear, clear_stats = scene_face_data(sc, analytic=st.analytic)
    seconds["analytic_test"] = time.perf_counter() - t

    stage = _Stage(out_dir)
    set_reports = []
    files = []
    totals = {"rays_traced": 0, "rays_naive": 0, "texels": 0, "analytic_texels": 0,
              "rays_below_horizon_skipped": 0}
    seconds.update(gbuffer=0.0, trace=0.0, dilate=0.0, write=0.0, vertex=0.0)
    attrs_common = {"rays": st.rays, "seed": st.seed, "sampler": st.sampler,
                    "estimator": st.estimator, "input_hash": in_hash}
    try:
        for si, s in enumerate(set_ids if st.textures else []):
            name = sc.set_names[s]
            t = time.perf_counter()
            _emit(progress, type="progress", stage="gbuffer", set=name, fraction=0.0)
            if si == 0 and first_gb is not None:
                gb, _ = first_gb.result()
            else:
                gb, _ = gbuffer_of(s)
            seconds["gbuffer"] += time.perf_counter() - t
            rep = {"name": name, "resolution": [gb.width, gb.height], **gb.stats}
            if gb.stats["overlap_texels"]:
                msg = (f"set {name!r}: {gb.stats['overlap_texels']} texels are covered by overlapping "
                       f"UV islands (objects: {', '.join(gb.stats['overlap_objects'])}); each keeps "
                       f"one surface, the others are wrong there. Re-unwrap without overlaps.")
                if st.overlap == "error":
                    raise BakeError(msg)
                warn(msg)
            if gb.stats["zero_area_uv_triangles"]:
                warn(f"set {name!r}: {gb.stats['zero_area_uv_triangles']} triangles have zero UV area "
                     f"and get no texels (they still cast shadows)")
            if gb.n == 0:
                warn(f"set {name!r}: no texel is covered by its UV layout; skipped")
                rep["skipped"] = True
                set_reports.append(rep)
                continue
            pts = bake_points_input(sc, s, gb, fn, clear, normal_group)
            t = time.perf_counter()

            def on_progress(done, total, rays, name=name, si=si):
                _emit(progress, type="progress", stage="trace", set=name,
                      fraction=done / max(total, 1), rays=rays,
                      rays_per_s=rays / max(time.perf_counter() - t, 1e-9),
                      set_index=si, sets=len(set_ids))

            # Channel-first texture (K, H*W); chunks write their texels straight in.
            tex = np.zeros((K, gb.height * gb.width), np.float32)
            texel = gb.texel

            def sink(idx, values, tex=tex, texel=texel):
                tex[:, texel[idx]] = values.T

            _, info = bake_points(rs, pts, st, progress=on_progress, cancel=cancel, sink=sink)
            seconds["trace"] += time.perf_counter() - t
            t = time.perf_counter()
            tex = tex.reshape(K, gb.height, gb.width)
            mask = np.zeros(gb.height * gb.width, bool)
            mask[gb.texel] = True
            mask = mask.reshape(gb.height, gb.width)
            mips = []
            if st.mips:
                cov = np.zeros(gb.height * gb.width, np.float32)
                cov[gb.texel] = gb.coverage
                mips = mip_chain(tex, cov.reshape(gb.height, gb.width))
            dilate(tex, mask, st.dilate, executor=helpers)
            seconds["dilate"] += time.perf_counter() - t
            t = time.perf_counter()
            half = st.half
            over = exr_io.half_overflow(tex) if half else 0
            if over:
                warn(f"set {name!r}: {over} values exceed the half-float range; stored as float32")
                half = False
            attrs = dict(attrs_common, kind_detail="visibility*cosine", dilate=st.dilate,
                         texels=int(gb.n), analytic_texels=info["analytic_points"])
            fname = f"{name}.transfer.exr"
            exr_io.write_sh_planes(stage.path(fname), tex, kind="transfer", half=half,
                                   attrs=attrs, atomic=False, executor=helpers)
            files.append(fname)
            for lvl, (mt, _) in enumerate(mips, start=1):
                mname = f"{name}.transfer.mip{lvl}.exr"
                exr_io.write_sh_planes(stage.path(mname), mt, kind="transfer", half=half,
                                       attrs=dict(attrs, mip_level=lvl), atomic=False)
                files.append(mname)
            del tex
            seconds["write"] += time.perf_counter() - t
            rep.update(file=fname, storage="half" if half else "float",
                       analytic_texels=info["analytic_points"], traced_texels=info["traced_points"],
                       rays_traced=info["rays_traced"], rays_naive=info["rays_naive"],
                       rays_below_horizon_skipped=info["rays_below_horizon_skipped"],
                       adaptive_early_stops=info["adaptive_early_stops"],
                       threads=info["threads"], trace_seconds=info["seconds"])
            set_reports.append(rep)
            for k in ("rays_traced", "rays_naive", "rays_below_horizon_skipped"):
                totals[k] += info[k]
            totals["texels"] += gb.n
            totals["analytic_texels"] += info["analytic_points"]

        vertex_reports = []
        if st.vertex_mode:
            t = time.perf_counter()
            for s in set_ids:
                name = sc.set_names[s]
                tris = sc.triangles_of_set(s)
                vp, vn, corner = _vertex_points(sc, tris)
                _emit(progress, type="progress", stage="vertex", set=name, fraction=0.0)
                pts = Points(vp, vn, vn, np.arange(vp.shape[0], dtype=np.int64) + (np.int64(s) << 40)
                             + (np.int64(1) << 62), np.zeros(vp.shape[0], bool))
                vc, info = bake_points(rs, pts, dataclasses.replace(st, analytic=False), cancel=cancel)
                vname = f"{name}.vertex.npz"
                with open(stage.path(vname), "wb") as f:
                    np.savez(f, format=np.array("prtt-vertex-transfer"), version=np.array(1),
                             bands=np.array(st.bands), positions=vp.astype(np.float32),
                             normals=vn.astype(np.float32), coeffs=vc, corner_vertex=corner,
                             triangles=tris.astype(np.int64), input_hash=np.array(in_hash))
                files.append(vname)
                vertex_reports.append({"name": name, "file": vname, "vertices": int(vp.shape[0]),
                                       "rays_traced": info["rays_traced"]})
                totals["rays_traced"] += info["rays_traced"]
            seconds["vertex"] = time.perf_counter() - t

        if not files:
            raise BakeError("nothing was baked: no texture set has covered texels")
        seconds["total"] = time.perf_counter() - t_all
        trace_s = seconds["trace"] + seconds["vertex"]
        from .. import __version__
        manifest = {
            "format": "prtt-bake", "format_version": BAKE_FORMAT_VERSION,
            "prtt_version": __version__, "kind": "transfer",
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "input_hash": in_hash, "settings_hash": set_hash, "settings": st.as_dict(),
            "files": files, "sets": set_reports, "vertex": vertex_reports,
            "analytic_test": clear_stats, "totals": totals, "seconds": seconds,
            "rays_per_second_trace": totals["rays_traced"] / trace_s if trace_s > 0 else 0.0,
            "rays_per_second_end_to_end": totals["rays_traced"] / seconds["total"],
            "warnings": warnings, "skipped": False,
        }
        stage.commit()
        with atomic_write(os.path.join(out_dir, MANIFEST)) as tmp:
            with open(tmp, "w", encoding="utf-8") as f:
                json.dump(manifest, f, indent=1)
    except BaseException:
        stage.abort()
        raise
    finally:
        helpers.shutdown(wait=True, cancel_futures=True)
    _emit(progress, type="done", skipped=False, manifest=os.path.join(out_dir, MANIFEST))
    return manifest
