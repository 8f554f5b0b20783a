"""The bake's .npz side files, read as untrusted input (a folder can be shared,
copied, edited or truncated): ``<set>.vertex.npz`` and ``generated_uvs.npz``
(docs/format.md).

Every member's .npy header is read and checked before its data: plain
numbers of the expected kind and number of dimensions, at most
MAX_ELEMENTS values, and exactly the bytes the archive records for the
member (a header that promises more than the file holds is refused before
anything is allocated). Values are checked after: indices in range, UVs and
coefficients finite. Every failure is a :class:`SidecarError` naming the
file.
"""
from __future__ import annotations

import math
import os
import tokenize
import zipfile

import numpy as np

from .jobfile import ZIP_ERRORS

#: Values in one member (float32: 1 GB): 10M vertices x 25 coefficients is 2.5e8.
MAX_ELEMENTS = 1 << 28
#: Archive members (generated_uvs.npz holds one per UV group, plus its keys).
MAX_MEMBERS = 4096
#: .npy header bytes (numpy's own default).
MAX_NPY_HEADER = 10000
#: Characters of a UV group's name.
MAX_KEY = 1024

_FLOAT = "f"
_INT = "iu"


class SidecarError(ValueError):
    """A side file could not be read; the message names the file and says why."""


def _open(path) -> zipfile.ZipFile:
    path = os.fspath(path)
    try:
        zf = zipfile.ZipFile(path)
    except FileNotFoundError:
        raise SidecarError(f"{path}: no such file") from None
    except (*ZIP_ERRORS, OverflowError) as exc:
        raise SidecarError(f"{path}: not a readable .npz file ({exc})") from exc
    if len(zf.infolist()) > MAX_MEMBERS:
        zf.close()
        raise SidecarError(f"{path}: {len(zf.infolist())} archive members, at most {MAX_MEMBERS}")
    return zf


#: Bytes of one member's data (1 GiB: 2^28 float32 values).
MAX_BYTES = 1 << 30
#: Bytes of one number: the side files hold float32 and int32/int64.
MAX_ITEMSIZE = 8


def _header(zf: zipfile.ZipFile, path: str, name: str, kinds: str, ndim: int):
    """(info, open member positioned at its data, shape, dtype, fortran) of
    member ``name`` (without .npy), its header checked: kind, dimensions,
    sizes, and the archive's byte count."""
    fmt = np.lib.format
    try:
        info = zf.getinfo(name + ".npy")
    except KeyError:
        raise SidecarError(f"{path}: no array {name!r}") from None
    fp = zf.open(info)
    try:
        version = fmt.read_magic(fp)
        if version not in ((1, 0), (2, 0)):
            raise ValueError(f".npy version {version} is not supported")
        read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape, fortran, dtype = read(fp, max_header_size=MAX_NPY_HEADER)
        what = "text" if kinds == "U" else "float" if kinds == _FLOAT else "integer"
        if dtype.hasobject or dtype.fields is not None or dtype.subdtype is not None or dtype.kind not in kinds:
            raise SidecarError(f"{path}: {name}: {dtype} is not a {what} array")
        limit = 4 * MAX_KEY if kinds == "U" else MAX_ITEMSIZE
        if not 0 < dtype.itemsize <= limit:
            raise SidecarError(f"{path}: {name}: {dtype} has {dtype.itemsize}-byte items, 1..{limit} expected")
        if len(shape) != ndim or any(d < 0 for d in shape):
            raise SidecarError(f"{path}: {name}: shape {shape}, expected {ndim} dimensions of 0 or more")
        count = math.prod(shape)
        if count > MAX_ELEMENTS or count * dtype.itemsize > MAX_BYTES:
            raise SidecarError(f"{path}: {name}: {count} values of {dtype.itemsize} bytes, at most {MAX_ELEMENTS} "
                               f"and {MAX_BYTES} bytes")
        if info.file_size != fp.tell() + count * dtype.itemsize:
            raise SidecarError(f"{path}: {name}: its header declares {shape} {dtype} but the archive member "
                               f"holds {info.file_size - fp.tell()} bytes of data (truncated or corrupt)")
        return fp, shape, dtype, fortran
    except BaseException:
        fp.close()
        raise


def _member(zf: zipfile.ZipFile, path: str, name: str, kinds: str, ndim: int, *,
            header_only: bool = False):
    """Member ``name`` (without .npy) as an array, its header checked before
    its data is read; ``header_only``: its shape alone."""
    try:
        fp, shape, dtype, fortran = _header(zf, path, name, kinds, ndim)
        with fp:
            if header_only:
                return shape
            count = math.prod(shape)
            data = fp.read(count * dtype.itemsize)
            if len(data) != count * dtype.itemsize:
                raise SidecarError(f"{path}: {name}: cut short")
            a = np.frombuffer(data, dtype, count)
            return a.reshape(shape[::-1]).T if fortran else a.reshape(shape)
    except SidecarError:
        raise
    except (*ZIP_ERRORS, SyntaxError, TypeError, MemoryError, tokenize.TokenError) as exc:
        raise SidecarError(f"{path}: {name}: unreadable array ({exc})") from exc


def _vertex_count(zf, path: str, bands: int | None) -> tuple[int, int]:
    """(V, K) of the file's ``coeffs``, from its header: K a square (bands² when given)."""
    V, K = _member(zf, path, "coeffs", _FLOAT, 2, header_only=True)
    b = math.isqrt(K)
    if b * b != K or K == 0 or (bands is not None and b != bands):
        raise SidecarError(f"{path}: coeffs has {K} columns, not " + (f"{bands}² = {bands * bands}" if bands
                                                                       else "a square number of SH coefficients"))
    return V, K


def _corners(zf, path: str, V: int) -> np.ndarray:
    corner = _member(zf, path, "corner_vertex", _INT, 2)
    if corner.shape[1] != 3:
        raise SidecarError(f"{path}: corner_vertex has shape {corner.shape}, expected (T, 3)")
    if corner.size and (int(corner.min()) < 0 or int(corner.max()) >= V):
        raise SidecarError(f"{path}: corner_vertex holds indices outside [0, {V})")
    return corner.astype(np.int64)


def _coeffs(zf, path: str, bands: int | None) -> np.ndarray:
    """The file's ``coeffs`` (V, K) as float32, its header checked first (_vertex_count), finite."""
    _vertex_count(zf, path, bands)
    with np.errstate(over="ignore"):          # an overflow is refused below, as a non-finite value
        coeffs = _member(zf, path, "coeffs", _FLOAT, 2).astype(np.float32)
    if not np.isfinite(coeffs).all():
        raise SidecarError(f"{path}: coeffs holds NaN or infinite values (as float32)")
    return coeffs


def read_vertex_transfer(path, bands: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(coeffs (V, K) float32, corner_vertex (T, 3) int64) of a ``<set>.vertex.npz``:
    K a square (bands² when ``bands`` is given), every index in [0, V), the
    coefficients finite as float32."""
    path = os.fspath(path)
    with _open(path) as zf:
        coeffs = _coeffs(zf, path, bands)
        return coeffs, _corners(zf, path, coeffs.shape[0])


def read_vertex_coeffs(path, bands: int | None = None) -> np.ndarray:
    """coeffs (V, K) float32 of a ``<set>.vertex.npz`` (finite as float32),
    without its corner_vertex (what the preview's vertex mode uploads)."""
    path = os.fspath(path)
    with _open(path) as zf:
        return _coeffs(zf, path, bands)


def read_corner_vertex(path) -> np.ndarray:
    """corner_vertex (T, 3) int64 of a ``<set>.vertex.npz``, checked against
    the vertex count in the coeffs header, without reading the coefficients."""
    path = os.fspath(path)
    with _open(path) as zf:
        V, _ = _vertex_count(zf, path, None)
        return _corners(zf, path, V)


def read_generated_uvs(path) -> dict[str, np.ndarray]:
    """{uv group: (T, 3, 2) float32 finite UVs} of a ``generated_uvs.npz``
    (members ``keys`` (n,) text and ``uv_<i>`` for each key)."""
    path = os.fspath(path)
    with _open(path) as zf:
        keys = _member(zf, path, "keys", "U", 1)
        if keys.size > MAX_MEMBERS:
            raise SidecarError(f"{path}: keys: {keys.size} names, at most {MAX_MEMBERS}")
        out = {}
        for i, k in enumerate(keys.tolist()):
            with np.errstate(over="ignore"):
                uv = _member(zf, path, f"uv_{i}", _FLOAT, 3).astype(np.float32)
            if uv.shape[1:] != (3, 2):
                raise SidecarError(f"{path}: uv_{i} has shape {uv.shape}, expected (T, 3, 2)")
            if not np.isfinite(uv).all():
                raise SidecarError(f"{path}: uv_{i} holds NaN or infinite values (as float32)")
            out[str(k)] = uv
    return out
