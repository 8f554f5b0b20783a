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

A job file is untrusted input. :class:`JobFile` reads every array's header
(shape, dtype) without its data and checks it against the limits below, the
archive's own sizes and the memory available *before* anything is allocated;
validation then checks dtypes (integers must be integers: no silent casts),
shapes, ranges and finiteness. Every problem is a :class:`SceneError` naming
the file, the array and, where there is one, the first offending triangle.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import struct
import zipfile
import zlib

import numpy as np

from ..bake.memory import check_fits
from ..bake.parallel import Cancelled
from ..shading.materials import Material
from .atomic import atomic_write

FORMAT_NAME = "prtt-scene"
FORMAT_VERSION = 1

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
#: Characters of the JSON strings ``extra`` and ``materials`` (a 16-band light is
#: ~20 KB, a material ~200 B).
MAX_JSON_CHARS = 1 << 24
#: Materials per job.
MAX_MATERIALS = 1 << 16
#: Members of the .npz archive: every array above, with room to spare. Checked
#: from the archive's end record before the directory is read (each entry costs
#: memory to index).
MAX_MEMBERS = 2 * (MAX_NORMAL_MAPS + MAX_TEXTURES) + 64
#: Largest |coordinate| in metres: squared extents (areas, normal tests) stay far
#: from float64 overflow (a light year is 9.5e15 m).
MAX_COORDINATE = 1e15
#: .npy headers longer than this are refused (numpy's own default).
MAX_NPY_HEADER = 10000


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

_FLOAT_KINDS = "fiu"          # lossless enough to become float32/64; bool and complex are refused
_INT_KINDS = "iu"


def _kind_word(kinds: str) -> str:
    return "integers" if kinds == _INT_KINDS else "numbers"


def _check_kind(name: str, dtype: np.dtype, kinds: str) -> None:
    if dtype.kind not in kinds or dtype.fields is not None:
        raise SceneError(f"{name}: expected {_kind_word(kinds)}, got {dtype}")


def _shape_text(shape_tail, lead="T") -> str:
    return "(" + ", ".join([lead, *map(str, shape_tail)]) + ("" if shape_tail else ",") + ")"


def _as(name, a, shape_tail, dtype, ndim, kinds=_FLOAT_KINDS):
    """``a`` as a contiguous ``dtype`` array of shape (T, *shape_tail); refuses other
    kinds of values (e.g. floats where integers are expected) instead of casting."""
    a = np.asarray(a)
    _check_kind(name, a.dtype, kinds)
    if a.ndim != ndim or tuple(a.shape[1:]) != tuple(shape_tail):
        raise SceneError(f"{name}: expected shape {_shape_text(shape_tail)}, got {a.shape}")
    return np.ascontiguousarray(a, dtype=dtype)


def _as_index(name, a, lo: int, hi: int, message) -> np.ndarray:
    """(T,) integers checked to lie in lo..hi *before* the int32 cast (a wrapped
    2^32 + 1 must not pass as 1). ``message(i, value)`` words the error."""
    a = np.asarray(a)
    _check_kind(name, a.dtype, _INT_KINDS)
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


def _check_image_shape(what: str, shape, channels: tuple[int, int]) -> None:
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
    _check_kind("set_id", sc.set_id.dtype, _INT_KINDS)
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
    if res.shape != (S, 2) or res.dtype.kind not in _INT_KINDS:
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
        _check_kind(f"normal map {i}", px.dtype, _FLOAT_KINDS)
        _check_image_shape(f"normal map {i}", px.shape, (3, MAX_IMAGE_CHANNELS))
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
        _check_kind(f"texture {i}", t.dtype, _FLOAT_KINDS)
        _check_image_shape(f"texture {i}", t.shape, (1, MAX_IMAGE_CHANNELS))
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
    with atomic_write(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


@dataclasses.dataclass(frozen=True)
class _Spec:
    """What a job array must be: kinds of values, shape pattern, dtype it becomes.
    Shape entries: an int (exact), "T" (triangles), "S" (sets), "O" (objects),
    "M" (normal maps) or "*" (checked elsewhere)."""

    kinds: str
    shape: tuple
    dtype: object


_TEXT = "U"
_SPECS = {
    "format": _Spec(_TEXT, (), None), "version": _Spec(_INT_KINDS, (), np.int64),
    "extra": _Spec(_TEXT, (), None), "materials": _Spec(_TEXT, (), None),
    "tex_count": _Spec(_INT_KINDS, (), np.int64),
    "positions": _Spec(_FLOAT_KINDS, ("T", 3, 3), np.float64),
    "normals": _Spec(_FLOAT_KINDS, ("T", 3, 3), np.float32),
    "uvs": _Spec(_FLOAT_KINDS, ("T", 3, 2), np.float64),
    "set_id": _Spec(_INT_KINDS, ("T",), None), "object_id": _Spec(_INT_KINDS, ("T",), None),
    "nm_index": _Spec(_INT_KINDS, ("T",), None), "material_id": _Spec(_INT_KINDS, ("T",), None),
    "nm_uvs": _Spec(_FLOAT_KINDS, ("T", 3, 2), np.float64),
    "tangents": _Spec(_FLOAT_KINDS, ("T", 3, 4), np.float32),
    "mat_uvs": _Spec(_FLOAT_KINDS, ("T", 3, 2), np.float64),
    "set_names": _Spec(_TEXT, ("S",), None), "object_names": _Spec(_TEXT, ("O",), None),
    "set_resolution": _Spec(_INT_KINDS, ("S", 2), None),
    "nm_strength": _Spec(_FLOAT_KINDS, ("M",), np.float32),
}
_IMAGE = _Spec(_FLOAT_KINDS, ("*",), np.float32)
_REQUIRED = ("positions", "normals", "uvs", "set_id", "set_names", "set_resolution")


@dataclasses.dataclass
class _Member:
    info: zipfile.ZipInfo
    shape: tuple
    dtype: np.dtype
    header_bytes: int

    @property
    def nbytes(self) -> int:
        return math.prod(self.shape) * self.dtype.itemsize     # Python ints: never overflows


def _zip_member_count(path: str, f) -> int:
    """Entries in the zip's end-of-central-directory record (the last 22..65557
    bytes), read before zipfile indexes the directory."""
    size = f.seek(0, os.SEEK_END)
    tail = min(size, 22 + 0xFFFF)
    f.seek(size - tail)
    data = f.read(tail)
    at = data.rfind(b"PK\x05\x06")
    if at < 0 or at + 22 > len(data):
        raise SceneError(f"{path}: not a readable .npz scene (no zip directory: truncated, or not "
                         f"a zip archive)")
    return struct.unpack("<H", data[at + 10:at + 12])[0]


class JobFile:
    """A job/scene .npz opened for checking: headers read, data not yet loaded.

    Opening reads the archive's directory and every known array's .npy header
    (shape, dtype) and checks them against the format, each other and the
    limits above; nothing large is allocated. :attr:`extra` (the parsed JSON)
    and :meth:`peak_bytes` are then available, and :meth:`load` reads and
    validates the scene. Use as a context manager.
    """

    def __init__(self, path):
        self.path = os.fspath(path)
        self._zf = None
        if not os.path.isfile(self.path):
            raise SceneError(f"{self.path}: no such job/scene file")
        try:
            self._open()
        except BaseException:
            self.close()
            raise

    # --- opening --------------------------------------------------------------------------
    def _err(self, msg: str) -> SceneError:
        return SceneError(f"{self.path}: {msg}")

    def _open(self) -> None:
        try:
            f = open(self.path, "rb")
        except OSError as exc:
            raise self._err(f"cannot be read ({exc.strerror})") from exc
        try:
            if os.fstat(f.fileno()).st_size == 0:
                raise self._err("the file is empty (0 bytes)")
            n = _zip_member_count(self.path, f)
            if n > MAX_MEMBERS:
                raise self._err(f"{n} archive members; a job has at most {MAX_MEMBERS}")
            self._zf = zipfile.ZipFile(f)
        except (OSError, zipfile.BadZipFile, EOFError, ValueError, struct.error) as exc:
            f.close()
            if isinstance(exc, SceneError):
                raise
            raise self._err(f"not a readable .npz scene ({exc})") from exc
        self.members: dict[str, _Member] = {}
        for info in self._zf.infolist():
            key = info.filename[:-4] if info.filename.endswith(".npy") else None
            if key is not None and self._spec(key) is not None:
                self.members[key] = self._header(key, info)
        self._check_layout()
        self._check_sizes()
        self.extra = self._json("extra", dict, {})
        self.materials = self._json("materials", list, [])

    def _spec(self, key: str) -> _Spec | None:
        if key in _SPECS:
            return _SPECS[key]
        head, _, idx = key.partition("_")
        if head in ("nm", "tex") and idx.isdigit() and len(idx) <= 6:
            return _IMAGE
        return None      # unknown members are never read

    def _header(self, key: str, info: zipfile.ZipInfo) -> _Member:
        fmt = np.lib.format
        try:
            with self._zf.open(info) as fp:
                version = fmt.read_magic(fp)
                if version == (1, 0):
                    shape, fortran, dtype = fmt.read_array_header_1_0(fp, max_header_size=MAX_NPY_HEADER)
                elif version == (2, 0):
                    shape, fortran, dtype = fmt.read_array_header_2_0(fp, max_header_size=MAX_NPY_HEADER)
                else:
                    raise ValueError(f".npy version {version} is not supported")
                header_bytes = fp.tell()
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, SyntaxError,
                KeyError, TypeError) as exc:
            raise self._err(f"{key}: unreadable array header ({exc})") from exc
        if dtype.hasobject or dtype.fields is not None or dtype.subdtype is not None:
            raise self._err(f"{key}: dtype {dtype} is not a plain number or text array")
        if dtype.itemsize < 0:       # numpy wraps the size of e.g. "<U1000000000" to a negative int
            raise self._err(f"{key}: its header declares an element type of over 2 GB (text of "
                            f"10^9 characters or more)")
        return _Member(info, tuple(int(s) for s in shape), dtype, header_bytes)

    def _check_sizes(self) -> None:
        """Each header's data size must be what the archive says the member holds
        (checked before any data is read; a member that lies to both is caught as
        truncated when read)."""
        for key, m in self.members.items():
            if m.info.file_size != m.header_bytes + m.nbytes:
                raise self._err(f"{key}: its header declares {m.shape} {m.dtype} ({m.nbytes} bytes) but "
                                f"the archive member holds {m.info.file_size - m.header_bytes} bytes of "
                                f"data (truncated or corrupt)")

    def _check_member(self, key: str, dims: dict) -> None:
        """Kind of values and shape of one member against its spec and ``dims``."""
        m, spec = self.members[key], self._spec(key)
        if spec.kinds == _TEXT:
            if m.dtype.kind != "U":
                raise self._err(f"{key}: expected text, got {m.dtype}")
        else:
            try:
                _check_kind(key, m.dtype, spec.kinds)
            except SceneError as exc:
                raise self._err(str(exc)) from None
        if spec is _IMAGE:
            return
        want = tuple(dims.get(d, d) for d in spec.shape)
        if m.shape != want:
            text = "(" + ", ".join(f"{d}={dims[d]}" if d in dims else str(d) for d in spec.shape) \
                + ("," if len(spec.shape) == 1 else "") + ")"
            raise self._err(f"{key}: expected shape {text}, got {m.shape}")

    def _check_layout(self) -> None:
        has = self.members
        if "format" not in has or self._text("format", 64) != FORMAT_NAME:
            raise self._err(f"not a PRTT scene (missing format={FORMAT_NAME!r})")
        if "version" in has:
            self._check_member("version", {})
            version = int(self._small("version"))
            if version > FORMAT_VERSION:
                raise self._err(f"scene format version {version} is newer than this PRTT "
                                f"({FORMAT_VERSION}); update the add-on")
        missing = [k for k in _REQUIRED if k not in has]
        if missing:
            raise self._err(f"missing arrays {sorted(missing)}")
        # The counts (T, S, O, M) come from the arrays that define them, checked
        # against their limits first; every other shape is checked against them.
        dims = {}
        for key, dim, ndim, limit, what in (("positions", "T", 3, MAX_TRIANGLES, "triangles"),
                                            ("set_names", "S", 1, MAX_SETS, "texture sets"),
                                            ("object_names", "O", 1, MAX_OBJECTS, "objects"),
                                            ("nm_strength", "M", 1, MAX_NORMAL_MAPS, "normal maps")):
            shape = has[key].shape if key in has else ()
            if len(shape) != ndim:
                continue                  # reported by the shape check below
            if shape[0] > limit:
                raise self._err(f"{key}: {shape[0]} {what}; a job has at most {limit}")
            dims[dim] = shape[0]
        self._check_member("positions", dims)
        for key in has:
            self._check_member(key, dims)
        for key in ("set_names", "object_names"):
            if key in has and has[key].dtype.itemsize // 4 > MAX_OBJECT_NAME_LENGTH:
                raise self._err(f"{key}: names of up to {has[key].dtype.itemsize // 4} characters; "
                                f"at most {MAX_OBJECT_NAME_LENGTH} (set names: {MAX_NAME_LENGTH} bytes)")
        for key in ("extra", "materials"):
            if key in has and has[key].dtype.itemsize // 4 > MAX_JSON_CHARS:
                raise self._err(f"{key}: {has[key].dtype.itemsize // 4} characters of JSON; "
                                f"at most {MAX_JSON_CHARS}")
        self.n_maps = dims.get("M", 0)
        self.n_textures = 0
        if "tex_count" in has:
            n = int(self._small("tex_count"))
            if not 0 <= n <= MAX_TEXTURES:
                raise self._err(f"tex_count: {n} textures; must be 0..{MAX_TEXTURES}")
            self.n_textures = n
        for prefix, count, channels in (("nm", self.n_maps, (3, MAX_IMAGE_CHANNELS)),
                                        ("tex", self.n_textures, (1, MAX_IMAGE_CHANNELS))):
            for i in range(count):
                key = f"{prefix}_{i}"
                if key not in has:
                    what = "normal map" if prefix == "nm" else "textures"
                    raise self._err(f"{what} {key} is missing" if prefix == "nm"
                                    else f"{what} {[key]} are missing")
                shape = has[key].shape
                if prefix == "tex" and len(shape) == 2:
                    shape = (*shape, 1)
                try:
                    _check_image_shape(key, shape, channels)
                except SceneError as exc:
                    raise self._err(str(exc)) from None
        # Images no count refers to are never read: they take no memory.
        for key in [k for k in has if self._spec(k) is _IMAGE]:
            head, _, idx = key.partition("_")
            if int(idx) >= (self.n_maps if head == "nm" else self.n_textures):
                del has[key]

    # --- reading --------------------------------------------------------------------------
    def _read(self, key: str) -> np.ndarray:
        """The member's data as stored (its size was checked against the header)."""
        try:
            with self._zf.open(self.members[key].info) as fp:
                return np.lib.format.read_array(fp, allow_pickle=False, max_header_size=MAX_NPY_HEADER)
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
            raise self._err(f"{key}: unreadable data ({exc})") from exc

    def _small(self, key: str):
        return self._read(key).reshape(()).item() if self.members[key].shape == () else self._read(key)

    def _text(self, key: str, max_chars: int) -> str:
        m = self.members[key]
        if m.dtype.kind != "U" or m.shape != () or m.dtype.itemsize // 4 > max_chars:
            raise self._err(f"{key}: expected a text scalar of at most {max_chars} characters, "
                            f"got {m.shape} {m.dtype}")
        return str(self._read(key).reshape(()).item())

    def _json(self, key: str, kind: type, default):
        if key not in self.members:
            return default
        raw = self._text(key, MAX_JSON_CHARS)
        try:
            value = json.loads(raw)
        except (ValueError, RecursionError) as exc:
            raise self._err(f"{key}: not valid JSON ({str(exc)[:200]})") from None
        if not isinstance(value, kind):
            raise self._err(f"{key}: expected a JSON {'object' if kind is dict else 'list'}, "
                            f"got {type(value).__name__}")
        return value

    def array(self, key: str) -> np.ndarray:
        """A member read and converted to its scene dtype (kinds already checked)."""
        a = self._read(key)
        dtype = self._spec(key).dtype
        return a if dtype is None else np.ascontiguousarray(a, dtype=dtype)

    def set_resolution(self) -> np.ndarray:
        """(S, 2) resolutions as stored (small): for memory checks before :meth:`load`."""
        return self._read("set_resolution")

    def settings(self) -> dict:
        """The job's bake settings (``extra["settings"]``), a dict."""
        st = self.extra.get("settings", {})
        if not isinstance(st, dict):
            raise self._err(f"extra.settings: expected a JSON object, got {type(st).__name__}")
        return st

    def peak_bytes(self) -> int:
        """Bytes loading takes at its peak: every array in its scene dtype, plus the
        largest one as stored (each is converted right after it is read)."""
        held = src = 0
        for key, m in self.members.items():
            dtype = self._spec(key).dtype
            size = math.prod(m.shape) * (np.dtype(dtype).itemsize if dtype is not None else m.dtype.itemsize)
            held += size
            src = max(src, m.nbytes)
        return held + src

    def load(self, cancel=None) -> Scene:
        """Read every array (checking ``cancel`` between them) and validate the scene."""
        def get(key):
            if cancel is not None and cancel.is_set():
                raise Cancelled()
            return self.array(key) if key in self.members else None

        arrays = {k: get(k) for k in ("positions", "normals", "uvs", "set_id", "set_resolution",
                                      "object_id", "nm_index", "nm_uvs", "tangents", "material_id",
                                      "mat_uvs")}
        names = get("set_names")
        objects = get("object_names")
        maps = []
        if self.n_maps:
            strength = get("nm_strength")
            maps = [NormalMap(get(f"nm_{i}"), float(strength[i])) for i in range(self.n_maps)]
        textures = [get(f"tex_{i}") for i in range(self.n_textures)]
        try:
            return Scene(set_names=list(names), object_names=None if objects is None else list(objects),
                         normal_maps=maps, materials=self.materials, textures=textures, **arrays)
        except SceneError as exc:
            raise self._err(str(exc)) from None

    def close(self) -> None:
        if self._zf is not None:
            fp = self._zf.fp
            self._zf.close()
            if fp is not None:
                fp.close()
            self._zf = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def load_scene(path, *, cancel=None, check_memory: bool = True) -> tuple[Scene, dict]:
    """Read and validate a scene .npz. Returns (scene, extra dict).

    Every array header is checked against the limits before any data is read,
    and (``check_memory``) the loaded arrays must fit in the available memory
    (:class:`memory.MemoryLimitError` otherwise). ``cancel`` (a threading.Event)
    is checked between arrays.
    """
    with JobFile(path) as job:
        if check_memory:
            check_fits(job.peak_bytes(), f"loading {job.path}")
        return job.load(cancel), job.extra


def _hash_array(h, a) -> None:
    # A memoryview of the contiguous array: no copy (tobytes() doubled the memory).
    h.update(str(a.shape).encode())
    h.update(memoryview(np.ascontiguousarray(a)).cast("B"))


def scene_hash(sc: Scene) -> str:
    """sha256 over every array and list of the scene (the bake's input identity)."""
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
