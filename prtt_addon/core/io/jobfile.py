"""The job file: a :class:`~prtt_addon.core.model.scene.Scene` stored as one ``.npz``, read back from untrusted input.

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
import json
import lzma
import math
import os
import struct
import tokenize
import zipfile
import zlib

import numpy as np

from ..base.atomic import atomic_write
from ..base.errors import Cancelled
from ..base.memory import check_fits
from ..model.scene import (
    FLOAT_KINDS,
    INT_KINDS,
    MAX_IMAGE_CHANNELS,
    MAX_NAME_LENGTH,
    MAX_NORMAL_MAPS,
    MAX_OBJECT_NAME_LENGTH,
    MAX_OBJECTS,
    MAX_SETS,
    MAX_TEXTURES,
    MAX_TRIANGLES,
    NormalMap,
    Scene,
    SceneError,
    check_image_shape,
    check_kind,
)

FORMAT_NAME = "prtt-scene"
FORMAT_VERSION = 1

#: Characters of the JSON strings ``extra`` and ``materials`` (a 16-band light is
#: ~20 KB, a material ~200 B).
MAX_JSON_CHARS = 1 << 24
#: Members of the .npz archive: every array above, with room to spare. Checked
#: from the archive's end record before the directory is read (each entry costs
#: memory to index).
MAX_MEMBERS = 2 * (MAX_NORMAL_MAPS + MAX_TEXTURES) + 64
#: .npy headers longer than this are refused (numpy's own default).
MAX_NPY_HEADER = 10000


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
    "format": _Spec(_TEXT, (), None), "version": _Spec(INT_KINDS, (), np.int64),
    "extra": _Spec(_TEXT, (), None), "materials": _Spec(_TEXT, (), None),
    "tex_count": _Spec(INT_KINDS, (), np.int64),
    "positions": _Spec(FLOAT_KINDS, ("T", 3, 3), np.float64),
    "normals": _Spec(FLOAT_KINDS, ("T", 3, 3), np.float32),
    "uvs": _Spec(FLOAT_KINDS, ("T", 3, 2), np.float64),
    "set_id": _Spec(INT_KINDS, ("T",), None), "object_id": _Spec(INT_KINDS, ("T",), None),
    "nm_index": _Spec(INT_KINDS, ("T",), None), "material_id": _Spec(INT_KINDS, ("T",), None),
    "nm_uvs": _Spec(FLOAT_KINDS, ("T", 3, 2), np.float64),
    "tangents": _Spec(FLOAT_KINDS, ("T", 3, 4), np.float32),
    "mat_uvs": _Spec(FLOAT_KINDS, ("T", 3, 2), np.float64),
    "set_names": _Spec(_TEXT, ("S",), None), "object_names": _Spec(_TEXT, ("O",), None),
    "set_resolution": _Spec(INT_KINDS, ("S", 2), None),
    "nm_strength": _Spec(FLOAT_KINDS, ("M",), np.float32),
}
_IMAGE = _Spec(FLOAT_KINDS, ("*",), np.float32)
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


#: What zipfile and zlib raise for a damaged or unsupported archive (NotImplementedError:
#: a compression method or zip version it does not know; RuntimeError: an encrypted entry; found by the fuzzer;
#: lzma.LZMAError: a damaged LZMA entry, found by review).
ZIP_ERRORS = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, NotImplementedError, RuntimeError,
              lzma.LZMAError)


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
        except (*ZIP_ERRORS, struct.error) as exc:
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
        except (*ZIP_ERRORS, SyntaxError, KeyError, TypeError, tokenize.TokenError) as exc:
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
                check_kind(key, m.dtype, spec.kinds)
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
                    check_image_shape(key, shape, channels)
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
        except ZIP_ERRORS as exc:
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
