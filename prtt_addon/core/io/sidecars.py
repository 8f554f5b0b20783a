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
import zlib

import numpy as np

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
    except (OSError, zipfile.BadZipFile, EOFError, ValueError, NotImplementedError, OverflowError) as exc:
        raise SidecarError(f"{path}: not a readable .npz file ({exc})") from exc
    if len(zf.infolist()) > MAX_MEMBERS:
        zf.close()
        raise SidecarError(f"{path}: {len(zf.infolist())} archive members, at most {MAX_MEMBERS}")
    return zf


def _member(zf: zipfile.ZipFile, path: str, name: str, kinds: str, ndim: int) -> np.ndarray:
    """Member ``name`` (without .npy): headers checked before its data is read."""
    fmt = np.lib.format
    try:
        info = zf.getinfo(name + ".npy")
    except KeyError:
        raise SidecarError(f"{path}: no array {name!r}") from None
    try:
        with zf.open(info) as fp:
            version = fmt.read_magic(fp)
            if version not in ((1, 0), (2, 0)):
                raise ValueError(f".npy version {version} is not supported")
            read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
            shape, fortran, dtype = read(fp, max_header_size=MAX_NPY_HEADER)
            if dtype.hasobject or dtype.fields is not None or dtype.subdtype is not None or dtype.kind not in kinds:
                raise SidecarError(f"{path}: {name}: {dtype} is not a {'float' if kinds == _FLOAT else 'integer'} "
                                   f"array")
            if len(shape) != ndim:
                raise SidecarError(f"{path}: {name}: {len(shape)} dimensions, expected {ndim}")
            count = math.prod(shape)
            if count > MAX_ELEMENTS:
                raise SidecarError(f"{path}: {name}: {count} values, at most {MAX_ELEMENTS}")
            if info.file_size != fp.tell() + count * dtype.itemsize:
                raise SidecarError(f"{path}: {name}: its header declares {shape} {dtype} but the archive member "
                                   f"holds {info.file_size - fp.tell()} bytes of data (truncated or corrupt)")
            data = fp.read(count * dtype.itemsize)
    except SidecarError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, SyntaxError, TypeError,
            NotImplementedError, RuntimeError, MemoryError, tokenize.TokenError) as exc:
        raise SidecarError(f"{path}: {name}: unreadable array ({exc})") from exc
    if len(data) != count * dtype.itemsize:
        raise SidecarError(f"{path}: {name}: cut short")
    a = np.frombuffer(data, dtype, count)
    return a.reshape(shape[::-1]).T if fortran else a.reshape(shape)


def read_vertex_transfer(path, bands: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(coeffs (V, K) float32, corner_vertex (T, 3) int64) of a ``<set>.vertex.npz``:
    K a square (bands² when ``bands`` is given), every index in [0, V), the
    coefficients finite."""
    path = os.fspath(path)
    with _open(path) as zf:
        coeffs = _member(zf, path, "coeffs", _FLOAT, 2)
        corner = _member(zf, path, "corner_vertex", _INT, 2)
    V, K = coeffs.shape
    b = math.isqrt(K)
    if b * b != K or K == 0 or (bands is not None and b != bands):
        raise SidecarError(f"{path}: coeffs has {K} columns, not " + (f"{bands}² = {bands * bands}" if bands
                                                                       else "a square number of SH coefficients"))
    if corner.shape[1] != 3:
        raise SidecarError(f"{path}: corner_vertex has shape {corner.shape}, expected (T, 3)")
    if corner.size and (int(corner.min()) < 0 or int(corner.max()) >= V):
        raise SidecarError(f"{path}: corner_vertex holds indices outside [0, {V})")
    if not np.isfinite(coeffs).all():
        raise SidecarError(f"{path}: coeffs holds NaN or infinite values")
    return coeffs.astype(np.float32), corner.astype(np.int64)


def read_generated_uvs(path) -> dict[str, np.ndarray]:
    """{uv group: (T, 3, 2) float32 finite UVs} of a ``generated_uvs.npz``
    (members ``keys`` (n,) text and ``uv_<i>`` for each key)."""
    path = os.fspath(path)
    with _open(path) as zf:
        keys = _member(zf, path, "keys", "U", 1)
        if keys.size > MAX_MEMBERS or (keys.size and keys.dtype.itemsize // 4 > MAX_KEY):
            raise SidecarError(f"{path}: keys: {keys.size} names of up to {keys.dtype.itemsize // 4} characters")
        out = {}
        for i, k in enumerate(keys.tolist()):
            uv = _member(zf, path, f"uv_{i}", _FLOAT, 3)
            if uv.shape[1:] != (3, 2):
                raise SidecarError(f"{path}: uv_{i} has shape {uv.shape}, expected (T, 3, 2)")
            if not np.isfinite(uv).all():
                raise SidecarError(f"{path}: uv_{i} holds NaN or infinite values")
            out[str(k)] = uv.astype(np.float32)
    return out
