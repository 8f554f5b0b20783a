"""The bpy-free scene description a bake works on (the worker's job file).

A :class:`Scene` is a triangle soup in world space with everything a bake
needs per triangle corner. Saved as one ``.npz`` (format in docs/format.md):

=================  ===============  ===============================================
array              shape, dtype     meaning
=================  ===============  ===============================================
positions          (T, 3, 3) f64    world-space corner positions (metres, Z up)
normals            (T, 3, 3) f32    per-corner (split) shading normals, unit
uvs                (T, 3, 2) f64    per-corner UVs of the bake's UV map, in [0, 1]
set_id             (T,) i32         texture set of each triangle (0..S-1); -1 = occluder
                                    only (casts shadows, gets no texels)
set_names          (S,) str         texture set names (file stems)
set_resolution     (S, 2) i32       (width, height) texels per set
object_id          (T,) i32         object of each triangle (for stats/vertex mode)
object_names       (O,) str         object names
-- optional: tangent-space normal maps (paper, "Normal maps") --
nm_index           (T,) i32         normal map of each triangle, -1 = none
nm_uvs             (T, 3, 2) f64    UVs the normal map is sampled with
tangents           (T, 3, 4) f32    per-corner MikkTSpace tangent xyz + bitangent sign
nm_strength        (M,) f32         Normal Map node strength per map
nm_<i>             (H, W, 3) f32    normal map i, file order (row 0 = top), 0..1 encoded
-- optional: materials (bounce bakes, reference shading; see materials.py) --
material_id        (T,) i32         material of each triangle, -1 = default
materials          JSON string      list of material dicts
mat_uvs            (T, 3, 2) f64    UVs material textures are sampled with
tex_<i>            (H, W, C) f32    material texture i, linear, file order
=================  ===============  ===============================================

Loading validates shapes, dtypes and finiteness and raises :class:`SceneError`
naming the array and the first offending triangle.
"""
from __future__ import annotations

import dataclasses
import json
import os
import zipfile

import numpy as np

FORMAT_NAME = "prtt-scene"
FORMAT_VERSION = 1

#: UVs may exceed [0, 1] by this much (float noise from unwrappers).
UV_TOLERANCE = 1e-6
#: Largest texture side accepted (a 16384^2 x 25 float32 texture is 27 GB).
MAX_RESOLUTION = 16384


class SceneError(ValueError):
    """The scene/job is malformed; the message names the array and the problem."""


@dataclasses.dataclass
class NormalMap:
    """A tangent-space normal map: pixels in file order (row 0 = top), 0..1."""

    pixels: np.ndarray          # (H, W, 3) float32
    strength: float = 1.0


@dataclasses.dataclass
class Scene:
    positions: np.ndarray                 # (T, 3, 3) float64
    normals: np.ndarray                   # (T, 3, 3) float32
    uvs: np.ndarray                       # (T, 3, 2) float64
    set_id: np.ndarray                    # (T,) int32
    set_names: list
    set_resolution: np.ndarray            # (S, 2) int32 (width, height)
    object_id: np.ndarray | None = None   # (T,) int32
    object_names: list | None = None
    nm_index: np.ndarray | None = None    # (T,) int32
    nm_uvs: np.ndarray | None = None      # (T, 3, 2) float64
    tangents: np.ndarray | None = None    # (T, 3, 4) float32
    normal_maps: list = dataclasses.field(default_factory=list)
    material_id: np.ndarray | None = None  # (T,) int32
    materials: list = dataclasses.field(default_factory=list)
    mat_uvs: np.ndarray | None = None      # (T, 3, 2) float64
    textures: list = dataclasses.field(default_factory=list)  # (H, W, C) float32, file order

    def __post_init__(self):
        validate(self)

    @property
    def n_triangles(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_sets(self) -> int:
        return len(self.set_names)

    def triangles_of_set(self, s: int) -> np.ndarray:
        return np.flatnonzero(self.set_id == s)


def _as(name, a, shape_tail, dtype, ndim):
    a = np.asarray(a)
    if a.dtype.kind not in "fiub":
        raise SceneError(f"{name}: expected numbers, got dtype {a.dtype}")
    if a.ndim != ndim or tuple(a.shape[1:]) != tuple(shape_tail):
        want = "(T, " + ", ".join(map(str, shape_tail)) + ")" if shape_tail else "(T,)"
        raise SceneError(f"{name}: expected shape {want}, got {a.shape}")
    return np.ascontiguousarray(a, dtype=dtype)


def _first_bad(name, a):
    bad = ~np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise SceneError(f"{name}: triangle {i} has NaN/Inf values "
                         f"({int(bad.sum())} triangles in all)")


def validate(sc: Scene) -> None:
    """Normalise dtypes in place and check every invariant (raises SceneError)."""
    sc.positions = _as("positions", sc.positions, (3, 3), np.float64, 3)
    T = sc.positions.shape[0]
    if T == 0:
        raise SceneError("the scene has no triangles")
    sc.normals = _as("normals", sc.normals, (3, 3), np.float32, 3)
    sc.uvs = _as("uvs", sc.uvs, (3, 2), np.float64, 3)
    sc.set_id = _as("set_id", sc.set_id, (), np.int32, 1)
    for name in ("normals", "uvs", "set_id"):
        if getattr(sc, name).shape[0] != T:
            raise SceneError(f"{name}: has {getattr(sc, name).shape[0]} triangles, positions has {T}")
    _first_bad("positions", sc.positions)
    _first_bad("normals", sc.normals)
    _first_bad("uvs", sc.uvs)
    sc.set_names = [str(s) for s in sc.set_names]
    S = len(sc.set_names)
    if S == 0:
        raise SceneError("set_names: the scene has no texture sets")
    if len(set(sc.set_names)) != S:
        raise SceneError(f"set_names: duplicate names in {sc.set_names}")
    for s in sc.set_names:
        if not s or any(c in s for c in '/\\:*?"<>|') or s.startswith("."):
            raise SceneError(f"set_names: {s!r} is not usable as a file name")
    sc.set_resolution = np.asarray(sc.set_resolution)
    if sc.set_resolution.shape != (S, 2) or sc.set_resolution.dtype.kind not in "iu":
        raise SceneError(f"set_resolution: expected ({S}, 2) integers, got "
                         f"{sc.set_resolution.shape} {sc.set_resolution.dtype}")
    sc.set_resolution = sc.set_resolution.astype(np.int32)
    for s in range(S):
        w, h = (int(v) for v in sc.set_resolution[s])
        if not (1 <= w <= MAX_RESOLUTION and 1 <= h <= MAX_RESOLUTION):
            raise SceneError(f"set_resolution: set {sc.set_names[s]!r} asks for {w}x{h} texels; "
                             f"each side must be 1..{MAX_RESOLUTION}")
    if sc.set_id.min() < -1 or sc.set_id.max() >= S:
        i = int(np.flatnonzero((sc.set_id < -1) | (sc.set_id >= S))[0])
        raise SceneError(f"set_id: triangle {i} refers to set {sc.set_id[i]}, there are {S} "
                         f"(-1 marks an occluder-only triangle)")
    baked = sc.set_id >= 0
    if not baked.any():
        raise SceneError("set_id: every triangle is occluder-only (-1); nothing to bake")
    lo = (sc.uvs.min(axis=(1, 2)) < -UV_TOLERANCE) & baked
    hi = (sc.uvs.max(axis=(1, 2)) > 1.0 + UV_TOLERANCE) & baked
    if (lo | hi).any():
        out = lo | hi
        sets = sorted({sc.set_names[i] for i in sc.set_id[out]})
        raise SceneError(f"uvs: {int(out.sum())} triangles of set(s) {', '.join(sets)} have UVs outside "
                         f"[0, 1] (first: triangle {int(np.flatnonzero(out)[0])}); a transfer texture "
                         f"needs a non-overlapping layout inside the unit square: re-unwrap")
    if sc.object_id is None:
        sc.object_id = np.zeros(T, np.int32)
        sc.object_names = sc.object_names or ["object"]
    sc.object_id = _as("object_id", sc.object_id, (), np.int32, 1)
    if sc.object_id.shape[0] != T:
        raise SceneError(f"object_id: has {sc.object_id.shape[0]} triangles, positions has {T}")
    sc.object_names = [str(s) for s in (sc.object_names or [])]
    if sc.object_id.min() < 0 or sc.object_id.max() >= len(sc.object_names):
        raise SceneError(f"object_id: values must index object_names ({len(sc.object_names)} names)")
    _validate_normal_maps(sc, T)
    _validate_materials(sc, T)


def _validate_normal_maps(sc: Scene, T: int) -> None:
    maps = []
    for i, nm in enumerate(sc.normal_maps):
        if not isinstance(nm, NormalMap):
            nm = NormalMap(np.asarray(nm))
        px = np.asarray(nm.pixels)
        if px.ndim != 3 or px.shape[2] < 3 or px.shape[0] < 1 or px.shape[1] < 1:
            raise SceneError(f"normal map {i}: expected (H, W, 3) pixels, got {px.shape}")
        px = np.ascontiguousarray(px[..., :3], dtype=np.float32)
        if not np.isfinite(px).all():
            raise SceneError(f"normal map {i}: has NaN/Inf pixels")
        if not np.isfinite(nm.strength):
            raise SceneError(f"normal map {i}: strength {nm.strength} is not finite")
        # float32 like the file stores it, so hashes survive a save/load.
        maps.append(NormalMap(px, float(np.float32(nm.strength))))
    sc.normal_maps = maps
    if sc.nm_index is None:
        if maps:
            raise SceneError("normal maps given without nm_index")
        return
    sc.nm_index = _as("nm_index", sc.nm_index, (), np.int32, 1)
    if sc.nm_index.shape[0] != T:
        raise SceneError(f"nm_index: has {sc.nm_index.shape[0]} triangles, positions has {T}")
    if sc.nm_index.min() < -1 or sc.nm_index.max() >= len(maps):
        raise SceneError(f"nm_index: values must be -1 or index one of {len(maps)} normal maps")
    if (sc.nm_index >= 0).any():
        if sc.nm_uvs is None or sc.tangents is None:
            raise SceneError("normal-mapped triangles need nm_uvs and tangents")
        sc.nm_uvs = _as("nm_uvs", sc.nm_uvs, (3, 2), np.float64, 3)
        sc.tangents = _as("tangents", sc.tangents, (3, 4), np.float32, 3)
        for name in ("nm_uvs", "tangents"):
            if getattr(sc, name).shape[0] != T:
                raise SceneError(f"{name}: has {getattr(sc, name).shape[0]} triangles, positions has {T}")
        _first_bad("nm_uvs", sc.nm_uvs)
        _first_bad("tangents", sc.tangents)


def _validate_materials(sc: Scene, T: int) -> None:
    texs = []
    for i, t in enumerate(sc.textures):
        t = np.asarray(t)
        if t.ndim == 2:
            t = t[..., None]
        if t.ndim != 3 or t.shape[0] < 1 or t.shape[1] < 1 or t.dtype.kind not in "fiu":
            raise SceneError(f"texture {i}: expected (H, W, C) numbers, got {t.shape} {t.dtype}")
        t = np.ascontiguousarray(t, dtype=np.float32)
        if not np.isfinite(t).all():
            raise SceneError(f"texture {i}: has NaN/Inf pixels")
        texs.append(t)
    sc.textures = texs
    if sc.material_id is None:
        return
    sc.material_id = _as("material_id", sc.material_id, (), np.int32, 1)
    if sc.material_id.shape[0] != T:
        raise SceneError(f"material_id: has {sc.material_id.shape[0]} triangles, positions has {T}")
    if sc.material_id.min() < -1 or sc.material_id.max() >= len(sc.materials):
        raise SceneError(f"material_id: values must be -1 or index one of {len(sc.materials)} materials")
    from .materials import Material
    for i, m in enumerate(sc.materials):
        try:
            mat = Material.from_dict(m)
        except (TypeError, ValueError) as exc:
            raise SceneError(f"materials[{i}]: {exc}") from exc
        for tex in (mat.base_color_texture, mat.roughness_texture):
            if tex >= len(texs):
                raise SceneError(f"materials[{i}] ({mat.name!r}): texture {tex} does not exist "
                                 f"({len(texs)} textures)")
    if any(Material.from_dict(m).textured for m in sc.materials):
        if sc.mat_uvs is None:
            raise SceneError("textured materials need mat_uvs")
        sc.mat_uvs = _as("mat_uvs", sc.mat_uvs, (3, 2), np.float64, 3)
        if sc.mat_uvs.shape[0] != T:
            raise SceneError(f"mat_uvs: has {sc.mat_uvs.shape[0]} triangles, positions has {T}")
        _first_bad("mat_uvs", sc.mat_uvs)


# --- .npz I/O -------------------------------------------------------------------

def save_scene(sc: Scene, path, *, extra: dict | None = None) -> None:
    """Write ``sc`` (and JSON-able ``extra``, e.g. bake settings) to ``path`` (.npz)."""
    arrays = {
        "format": np.array(FORMAT_NAME), "version": np.array(FORMAT_VERSION),
        "positions": sc.positions, "normals": sc.normals, "uvs": sc.uvs,
        "set_id": sc.set_id, "set_names": np.array(sc.set_names, dtype=str),
        "set_resolution": sc.set_resolution, "object_id": sc.object_id,
        "object_names": np.array(sc.object_names, dtype=str),
        "extra": np.array(json.dumps(extra or {})),
    }
    if sc.nm_index is not None:
        arrays["nm_index"] = sc.nm_index
        if sc.nm_uvs is not None:
            arrays["nm_uvs"] = sc.nm_uvs
            arrays["tangents"] = sc.tangents
        arrays["nm_strength"] = np.array([m.strength for m in sc.normal_maps], np.float32)
        for i, m in enumerate(sc.normal_maps):
            arrays[f"nm_{i}"] = m.pixels
    if sc.material_id is not None:
        arrays["material_id"] = sc.material_id
        arrays["materials"] = np.array(json.dumps(sc.materials))
    if sc.mat_uvs is not None:
        arrays["mat_uvs"] = sc.mat_uvs
    arrays["tex_count"] = np.array(len(sc.textures))
    for i, t in enumerate(sc.textures):
        arrays[f"tex_{i}"] = t
    from .atomic import atomic_write
    with atomic_write(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


def load_scene(path) -> tuple[Scene, dict]:
    """Read and validate a scene .npz. Returns (scene, extra dict)."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise SceneError(f"{path}: no such job/scene file")
    try:
        z = np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise SceneError(f"{path}: not a readable .npz scene ({exc})") from exc
    with z:
        keys = set(z.files)
        if "format" not in keys or str(z["format"]) != FORMAT_NAME:
            raise SceneError(f"{path}: not a PRTT scene (missing format={FORMAT_NAME!r})")
        version = int(z["version"])
        if version > FORMAT_VERSION:
            raise SceneError(f"{path}: scene format version {version} is newer than this "
                             f"PRTT ({FORMAT_VERSION}); update the add-on")
        missing = {"positions", "normals", "uvs", "set_id", "set_names", "set_resolution"} - keys
        if missing:
            raise SceneError(f"{path}: missing arrays {sorted(missing)}")
        get = lambda k: z[k] if k in keys else None  # noqa: E731
        maps = []
        if "nm_strength" in keys:
            for i, s in enumerate(z["nm_strength"]):
                if f"nm_{i}" not in keys:
                    raise SceneError(f"{path}: normal map nm_{i} is missing")
                maps.append(NormalMap(z[f"nm_{i}"], float(s)))
        extra = json.loads(str(z["extra"])) if "extra" in keys else {}
        materials = json.loads(str(z["materials"])) if "materials" in keys else []
        n_tex = int(z["tex_count"]) if "tex_count" in keys else 0
        missing_tex = [f"tex_{i}" for i in range(n_tex) if f"tex_{i}" not in keys]
        if missing_tex:
            raise SceneError(f"{path}: textures {missing_tex} are missing")
        textures = [z[f"tex_{i}"] for i in range(n_tex)]
        sc = Scene(
            positions=z["positions"], normals=z["normals"], uvs=z["uvs"], set_id=z["set_id"],
            set_names=list(z["set_names"]), set_resolution=z["set_resolution"],
            object_id=get("object_id"),
            object_names=list(z["object_names"]) if "object_names" in keys else None,
            nm_index=get("nm_index"), nm_uvs=get("nm_uvs"), tangents=get("tangents"),
            normal_maps=maps, material_id=get("material_id"), materials=materials,
            mat_uvs=get("mat_uvs"), textures=textures)
    return sc, extra


def scene_hash(sc: Scene) -> str:
    """sha256 over every array and list of the scene (the bake's input identity)."""
    import hashlib
    h = hashlib.sha256()
    for a in (sc.positions, sc.normals, sc.uvs, sc.set_id, sc.set_resolution, sc.object_id,
              sc.nm_index, sc.nm_uvs, sc.tangents, sc.material_id, sc.mat_uvs):
        if a is not None:
            h.update(str(a.shape).encode())
            h.update(np.ascontiguousarray(a).tobytes())
        h.update(b"|")
    h.update(json.dumps([sc.set_names, sc.object_names, sc.materials], sort_keys=True).encode())
    for m in sc.normal_maps:
        h.update(m.pixels.tobytes())
        h.update(str(m.strength).encode())
    for t in sc.textures:
        h.update(str(t.shape).encode())
        h.update(t.tobytes())
    return h.hexdigest()


def geometry_hash(sc: Scene) -> str:
    """sha256 of what the *transfer* depends on (geometry, UVs, sets, normals,
    normal maps) - not materials, which only bounce textures bake in."""
    import hashlib
    h = hashlib.sha256()
    for a in (sc.positions, sc.normals, sc.uvs, sc.set_id, sc.set_resolution, sc.object_id,
              sc.nm_index, sc.nm_uvs, sc.tangents):
        if a is not None:
            h.update(str(a.shape).encode())
            h.update(np.ascontiguousarray(a).tobytes())
        h.update(b"|")
    h.update(json.dumps([sc.set_names, sc.object_names], sort_keys=True).encode())
    for m in sc.normal_maps:
        h.update(m.pixels.tobytes())
        h.update(str(m.strength).encode())
    return h.hexdigest()
