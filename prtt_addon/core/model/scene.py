"""The scene a bake works on: the domain types and their invariants.

A :class:`Scene` is a triangle soup in world space with everything a bake
needs per triangle corner (positions, shading normals, the bake's UVs, texture
sets, objects, optional normal maps and materials: the arrays are listed in
core/io/jobfile.py and docs/format.md). Constructing one validates it: dtypes
(integers must be integers: no silent casts), shapes, ranges, finiteness and
the limits below; every problem is a :class:`SceneError` naming the array
and, where there is one, the first offending triangle. How a scene is stored
and read back from untrusted files is core/io/jobfile.py's job.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json

import numpy as np

from .material import Material

#: UVs may exceed [0, 1] by this much (float noise from unwrappers).
UV_TOLERANCE = 1e-6
#: Largest texture side accepted (a 16384^2 x 25 float32 texture is 27 GB).
MAX_RESOLUTION = 16384

# --- limits of a job (docs/format.md, "Limits"); each with the reason for it ---------
#: Triangles: a job holds ~320 B of arrays per triangle and the BVH ~130 B more,
#: so 2^26 triangles are ~30 GB before any texture: beyond the machines this runs on.
MAX_TRIANGLES = 1 << 26
#: Texture sets: each is at least one file and one G-buffer pass.
MAX_SETS = 1024
#: Objects (names kept for statistics and overlap reports).
MAX_OBJECTS = 1 << 20
#: Bytes (UTF-8) of a set name. It becomes file names, the longest being the
#: staged ``.prtt-tmp-<pid>-<set>.transfer.mip<k>-<n>.exr`` (~50 bytes more),
#: which must fit the 255-byte name limit of common file systems.
MAX_NAME_LENGTH = 200
#: Characters of an object name (Blender's are at most 63 bytes).
MAX_OBJECT_NAME_LENGTH = 1024
#: Normal maps and material textures per job.
MAX_NORMAL_MAPS = 256
MAX_TEXTURES = 256
#: Side and pixel count of one normal map or material texture (16384^2 RGBA
#: float32 is 4 GB), and its channels.
MAX_IMAGE_SIDE = 16384
MAX_IMAGE_PIXELS = 1 << 28
MAX_IMAGE_CHANNELS = 4
#: Materials per job.
MAX_MATERIALS = 1 << 16
#: Largest |coordinate| in metres: squared extents (areas, normal tests) stay far
#: from float64 overflow (a light year is 9.5e15 m).
MAX_COORDINATE = 1e15


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

    def nbytes(self) -> int:
        """Bytes held by the scene's arrays, images included."""
        arrays = [self.positions, self.normals, self.uvs, self.set_id, self.set_resolution, self.object_id,
                  self.nm_index, self.nm_uvs, self.tangents, self.material_id, self.mat_uvs,
                  *[m.pixels for m in self.normal_maps], *self.textures]
        return sum(int(a.nbytes) for a in arrays if a is not None)


# --- validation --------------------------------------------------------------------------

FLOAT_KINDS = "fiu"          # lossless enough to become float32/64; bool and complex are refused
INT_KINDS = "iu"


def _kind_word(kinds: str) -> str:
    return "integers" if kinds == INT_KINDS else "numbers"


def check_kind(name: str, dtype: np.dtype, kinds: str) -> None:
    if dtype.kind not in kinds or dtype.fields is not None:
        raise SceneError(f"{name}: expected {_kind_word(kinds)}, got {dtype}")


def _shape_text(shape_tail, lead="T") -> str:
    return "(" + ", ".join([lead, *map(str, shape_tail)]) + ("" if shape_tail else ",") + ")"


def _as(name, a, shape_tail, dtype, ndim, kinds=FLOAT_KINDS):
    """``a`` as a contiguous ``dtype`` array of shape (T, *shape_tail); refuses other
    kinds of values (e.g. floats where integers are expected) instead of casting."""
    a = np.asarray(a)
    check_kind(name, a.dtype, kinds)
    if a.ndim != ndim or tuple(a.shape[1:]) != tuple(shape_tail):
        raise SceneError(f"{name}: expected shape {_shape_text(shape_tail)}, got {a.shape}")
    return np.ascontiguousarray(a, dtype=dtype)


def _as_index(name, a, lo: int, hi: int, message) -> np.ndarray:
    """(T,) integers checked to lie in lo..hi *before* the int32 cast (a wrapped
    2^32 + 1 must not pass as 1). ``message(i, value)`` words the error."""
    a = np.asarray(a)
    check_kind(name, a.dtype, INT_KINDS)
    if a.ndim != 1:
        raise SceneError(f"{name}: expected shape (T,), got {a.shape}")
    if a.size:
        amin, amax = a.min(), a.max()
        if int(amin) < lo or int(amax) > hi:
            bad = (a < lo) | (a > hi)
            i = int(np.flatnonzero(bad)[0])
            raise SceneError(message(i, int(a[i])))
    return np.ascontiguousarray(a, dtype=np.int32)


def _check_count(name, a, T: int) -> np.ndarray:
    """``a`` as an array with one row per triangle (T rows), else SceneError."""
    a = np.asarray(a)
    if a.ndim == 0:
        raise SceneError(f"{name}: expected one value per triangle, got a scalar")
    if a.shape[0] != T:
        raise SceneError(f"{name}: has {a.shape[0]} triangles, positions has {T}")
    return a


def _first_bad(name, a):
    bad = ~np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise SceneError(f"{name}: triangle {i} has NaN/Inf values "
                         f"({int(bad.sum())} triangles in all)")


def check_image_shape(what: str, shape, channels: tuple[int, int]) -> None:
    """Bounds of a normal map or texture (H, W, C) before its pixels are touched."""
    if len(shape) != 3 or shape[0] < 1 or shape[1] < 1 or not channels[0] <= shape[2] <= channels[1]:
        lo, hi = channels
        raise SceneError(f"{what}: expected (H, W, C) pixels with C = {lo}..{hi}, got {tuple(shape)}")
    h, w = int(shape[0]), int(shape[1])
    if h > MAX_IMAGE_SIDE or w > MAX_IMAGE_SIDE or h * w > MAX_IMAGE_PIXELS:
        raise SceneError(f"{what}: {w}x{h} pixels; at most {MAX_IMAGE_SIDE} a side and "
                         f"{MAX_IMAGE_PIXELS} pixels")


def check_set_name(s: str) -> None:
    """Raise SceneError unless ``s`` can be a file stem on every platform we run on."""
    if not s or any(c in s for c in '/\\:*?"<>|') or s.startswith(".") \
            or any(ord(c) < 32 or ord(c) == 127 for c in s):
        raise SceneError(f"set_names: {s[:60]!r} is not usable as a file name "
                         f"(no / \\ : * ? \" < > |, control characters or leading dot)")
    n = len(s.encode("utf-8", "surrogatepass"))
    if n > MAX_NAME_LENGTH:
        raise SceneError(f"set_names: {s[:40]!r}... is {len(s)} characters ({n} bytes as UTF-8); "
                         f"set names become file names and may have at most {MAX_NAME_LENGTH} bytes")


def validate(sc: Scene) -> None:
    """Normalise dtypes in place and check every invariant (raises SceneError)."""
    sc.positions = _as("positions", sc.positions, (3, 3), np.float64, 3)
    T = sc.positions.shape[0]
    if T == 0:
        raise SceneError("the scene has no triangles")
    if T > MAX_TRIANGLES:
        raise SceneError(f"positions: {T} triangles; at most {MAX_TRIANGLES}")
    sc.normals = _as("normals", sc.normals, (3, 3), np.float32, 3)
    sc.uvs = _as("uvs", sc.uvs, (3, 2), np.float64, 3)
    sc.set_id = np.asarray(sc.set_id)
    check_kind("set_id", sc.set_id.dtype, INT_KINDS)
    for name in ("normals", "uvs", "set_id"):
        _check_count(name, getattr(sc, name), T)
    _first_bad("positions", sc.positions)
    big = max(-float(sc.positions.min()), float(sc.positions.max()))   # no |P| temporary
    if big > MAX_COORDINATE:
        raise SceneError(f"positions: a coordinate of {big:.3g} m; at most {MAX_COORDINATE:.0e} m")
    _first_bad("normals", sc.normals)
    _first_bad("uvs", sc.uvs)
    _validate_sets(sc, T)
    _validate_objects(sc, T)
    _validate_normal_maps(sc, T)
    _validate_materials(sc, T)


def _validate_sets(sc: Scene, T: int) -> None:
    sc.set_names = [str(s) for s in sc.set_names]
    S = len(sc.set_names)
    if S == 0:
        raise SceneError("set_names: the scene has no texture sets")
    if S > MAX_SETS:
        raise SceneError(f"set_names: {S} texture sets; at most {MAX_SETS}")
    if len(set(sc.set_names)) != S:
        raise SceneError(f"set_names: duplicate names in {sc.set_names[:20]}")
    for s in sc.set_names:
        check_set_name(s)
    res = np.asarray(sc.set_resolution)
    if res.shape != (S, 2) or res.dtype.kind not in INT_KINDS:
        raise SceneError(f"set_resolution: expected ({S}, 2) integers, got {res.shape} {res.dtype}")
    for s in range(S):
        w, h = (int(v) for v in res[s])          # Python ints: no wrap-around
        if not (1 <= w <= MAX_RESOLUTION and 1 <= h <= MAX_RESOLUTION):
            raise SceneError(f"set_resolution: set {sc.set_names[s]!r} asks for {w}x{h} texels; "
                             f"each side must be 1..{MAX_RESOLUTION}")
    sc.set_resolution = res.astype(np.int32)
    sc.set_id = _as_index("set_id", sc.set_id, -1, S - 1, lambda i, v: (
        f"set_id: triangle {i} refers to set {v}, there are {S} (-1 marks an occluder-only triangle)"))
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


def _validate_objects(sc: Scene, T: int) -> None:
    if sc.object_id is None:
        sc.object_id = np.zeros(T, np.int32)
        sc.object_names = sc.object_names or ["object"]
    sc.object_names = [str(s) for s in (sc.object_names or [])]
    O = len(sc.object_names)
    if O > MAX_OBJECTS:
        raise SceneError(f"object_names: {O} objects; at most {MAX_OBJECTS}")
    long = [s for s in sc.object_names if len(s) > MAX_OBJECT_NAME_LENGTH]
    if long:
        raise SceneError(f"object_names: {long[0][:40]!r}... is {len(long[0])} characters; "
                         f"at most {MAX_OBJECT_NAME_LENGTH}")
    _check_count("object_id", sc.object_id, T)
    sc.object_id = _as_index("object_id", sc.object_id, 0, O - 1, lambda i, v: (
        f"object_id: values must index object_names ({O} names); triangle {i} has {v}"))


def _validate_normal_maps(sc: Scene, T: int) -> None:
    if len(sc.normal_maps) > MAX_NORMAL_MAPS:
        raise SceneError(f"normal maps: {len(sc.normal_maps)}; at most {MAX_NORMAL_MAPS}")
    maps = []
    for i, nm in enumerate(sc.normal_maps):
        if not isinstance(nm, NormalMap):
            nm = NormalMap(np.asarray(nm))
        px = np.asarray(nm.pixels)
        check_kind(f"normal map {i}", px.dtype, FLOAT_KINDS)
        check_image_shape(f"normal map {i}", px.shape, (3, MAX_IMAGE_CHANNELS))
        px = np.ascontiguousarray(px[..., :3], dtype=np.float32)
        if not np.isfinite(px).all():
            raise SceneError(f"normal map {i}: has NaN/Inf pixels")
        if isinstance(nm.strength, (bool, np.bool_)) or not isinstance(nm.strength, (int, float, np.number)) \
                or not np.isfinite(nm.strength):
            raise SceneError(f"normal map {i}: strength {nm.strength!r} is not a finite number")
        # float32 like the file stores it, so hashes survive a save/load.
        maps.append(NormalMap(px, float(np.float32(nm.strength))))
    sc.normal_maps = maps
    if sc.nm_index is None:
        if maps:
            raise SceneError("normal maps given without nm_index")
        return
    _check_count("nm_index", sc.nm_index, T)
    M = len(maps)
    sc.nm_index = _as_index("nm_index", sc.nm_index, -1, M - 1, lambda i, v: (
        f"nm_index: values must be -1 or index one of {M} normal maps; triangle {i} has {v}"))
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
    if len(sc.textures) > MAX_TEXTURES:
        raise SceneError(f"textures: {len(sc.textures)}; at most {MAX_TEXTURES}")
    texs = []
    for i, t in enumerate(sc.textures):
        t = np.asarray(t)
        if t.ndim == 2:
            t = t[..., None]
        check_kind(f"texture {i}", t.dtype, FLOAT_KINDS)
        check_image_shape(f"texture {i}", t.shape, (1, MAX_IMAGE_CHANNELS))
        t = np.ascontiguousarray(t, dtype=np.float32)
        if not np.isfinite(t).all():
            raise SceneError(f"texture {i}: has NaN/Inf pixels")
        texs.append(t)
    sc.textures = texs
    if not isinstance(sc.materials, list):
        raise SceneError(f"materials: expected a list of material dicts, got {type(sc.materials).__name__}")
    if len(sc.materials) > MAX_MATERIALS:
        raise SceneError(f"materials: {len(sc.materials)}; at most {MAX_MATERIALS}")
    if sc.material_id is None:
        return
    _check_count("material_id", sc.material_id, T)
    n_mat = len(sc.materials)
    sc.material_id = _as_index("material_id", sc.material_id, -1, n_mat - 1, lambda i, v: (
        f"material_id: values must be -1 or index one of {n_mat} materials; triangle {i} has {v}"))
    mats = []
    for i, m in enumerate(sc.materials):
        if not isinstance(m, dict):
            raise SceneError(f"materials[{i}]: expected a dict, got {type(m).__name__}")
        try:
            mat = Material.from_dict(m)
        except (TypeError, ValueError) as exc:
            raise SceneError(f"materials[{i}]: {exc}") from exc
        for tex in (mat.base_color_texture, mat.roughness_texture):
            if tex >= len(texs):
                raise SceneError(f"materials[{i}] ({mat.name!r}): texture {tex} does not exist "
                                 f"({len(texs)} textures)")
        mats.append(mat)
    if any(m.textured for m in mats):
        if sc.mat_uvs is None:
            raise SceneError("textured materials need mat_uvs")
        sc.mat_uvs = _as("mat_uvs", sc.mat_uvs, (3, 2), np.float64, 3)
        if sc.mat_uvs.shape[0] != T:
            raise SceneError(f"mat_uvs: has {sc.mat_uvs.shape[0]} triangles, positions has {T}")
        _first_bad("mat_uvs", sc.mat_uvs)


# --- .npz I/O -------------------------------------------------------------------

def _hash_array(h, a) -> None:
    # A memoryview of the contiguous array: no copy (tobytes() doubled the memory).
    h.update(str(a.shape).encode())
    h.update(memoryview(np.ascontiguousarray(a)).cast("B"))


def scene_hash(sc: Scene) -> str:
    """sha256 over every array of the scene: equal for equal scenes (a job
    file's round trip). A bake's identity starts from :func:`geometry_hash`."""
    h = hashlib.sha256()
    for a in (sc.positions, sc.normals, sc.uvs, sc.set_id, sc.set_resolution, sc.object_id,
              sc.nm_index, sc.nm_uvs, sc.tangents, sc.material_id, sc.mat_uvs):
        if a is not None:
            _hash_array(h, a)
        h.update(b"|")
    h.update(json.dumps([sc.set_names, sc.object_names, sc.materials], sort_keys=True).encode())
    for m in sc.normal_maps:
        h.update(memoryview(m.pixels).cast("B"))
        h.update(str(m.strength).encode())
    for t in sc.textures:
        _hash_array(h, t)
    return h.hexdigest()


def geometry_hash(sc: Scene) -> str:
    """sha256 of what the *transfer* depends on (geometry, UVs, sets, normals,
    normal maps) - not materials, which only bounce textures bake in."""
    h = hashlib.sha256()
    for a in (sc.positions, sc.normals, sc.uvs, sc.set_id, sc.set_resolution, sc.object_id,
              sc.nm_index, sc.nm_uvs, sc.tangents):
        if a is not None:
            _hash_array(h, a)
        h.update(b"|")
    h.update(json.dumps([sc.set_names, sc.object_names], sort_keys=True).encode())
    for m in sc.normal_maps:
        h.update(memoryview(m.pixels).cast("B"))
        h.update(str(m.strength).encode())
    return h.hexdigest()
