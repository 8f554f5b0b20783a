"""Blender's colour management as a table: what turns radiance into pixels.

A view transform (AgX, Filmic, Khronos PBR Neutral, Standard with a look,
...) with its look and display device is sampled from Blender itself, on a
lattice of scene-linear colours (blender/preview/colour_management.py), and applied here
by trilinear interpolation; ``shaders/prtt_display.glsl`` is this module's GLSL
twin (tests/test_display.py holds them together, and both against Blender's
own colour management of the same linear images).

Conventions:

- input: scene-linear Rec.709 radiance, already times the exposure
  (2 ** stops: Blender applies exposure before the view transform);
- shaper, per channel: ``s = (log2(x + 2**LO) - LO) / (log2(2**HI + 2**LO) - LO)``
  clamped to [0, 1] (x = 0 -> s = 0 exactly; 2**HI the brightest value held,
  4096: every view transform Blender ships is white well below it);
- ``lut[b, g, r]``, shape (N, N, N, 3): display code values in [0, 1] at the
  lattice point s = (r, g, b) / (N - 1), red index fastest as a 3D
  texture's x, so GLSL samples it at ``(s * (N - 1) + 0.5) / N``;
- the display gamma comes after: pixel = lut(s) ** (1 / gamma) (Blender's
  order, tested against Blender).

Standard on an sRGB display without a look needs no table: the exact sRGB
encode (core.io.image_write.srgb_encode) draws it, as before tables existed.
Interpolation error against Blender at N = 65 (tests/test_display.py, random
log-uniform colours): AgX mean 0.14/255, p99 1.4/255; worst on colours with
one channel 1000x below the others.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib

import numpy as np

#: Lattice points per axis: 65 keeps AgX within 1.4/255 (p99) of Blender.
LUT_SIZE = 65
#: Smallest and largest lattice sizes a file may carry (untrusted input).
MIN_LUT_SIZE, MAX_LUT_SIZE = 2, 129
#: The shaper's range in stops: an offset of 2**LO keeps 0 on the lattice.
SHAPER_LO, SHAPER_HI = -12.0, 12.0
#: Colours encoded at once (each holds ~200 bytes of float64 temporaries).
ENCODE_CHUNK = 1 << 16
#: How a glTF file stores the table: one Zstandard frame of uint16
#: little-endian RGB (65^3: 1.65 MB raw, 0.49 MB compressed).
LUT_ENCODING = "uint16-zstd"


class DisplayError(ValueError):
    """A display table is malformed (a file's, or a sample's)."""


def shaper(linear: np.ndarray, lo: float = SHAPER_LO, hi: float = SHAPER_HI) -> np.ndarray:
    """Scene-linear values -> lattice coordinates in [0, 1] (float64)."""
    x = np.nan_to_num(np.asarray(linear, np.float64), nan=0.0, posinf=2.0 ** hi)
    c = 2.0 ** lo
    s = (np.log2(np.maximum(x, 0.0) + c) - lo) / (np.log2(2.0 ** hi + c) - lo)
    return np.clip(s, 0.0, 1.0)


def lattice(size: int = LUT_SIZE, lo: float = SHAPER_LO, hi: float = SHAPER_HI) -> np.ndarray:
    """(size**3, 3) float64: the scene-linear colours at the lattice points,
    in the table's order (red fastest, blue slowest)."""
    c = 2.0 ** lo
    s = np.linspace(0.0, 1.0, size)
    axis = np.maximum(np.exp2(s * (np.log2(2.0 ** hi + c) - lo) + lo) - c, 0.0)
    axis[0] = 0.0
    b, g, r = np.meshgrid(axis, axis, axis, indexing="ij")
    return np.stack([r.ravel(), g.ravel(), b.ravel()], axis=1)


@dataclasses.dataclass(frozen=True, eq=False)
class DisplayTransform:
    """A sampled view transform: ``lut`` (N, N, N, 3) float32 display code
    values (see the module's conventions), ``gamma`` Blender's display gamma,
    ``name`` what it is ("AgX, look None, display sRGB")."""

    lut: np.ndarray
    gamma: float = 1.0
    name: str = ""
    lo: float = SHAPER_LO
    hi: float = SHAPER_HI

    def __post_init__(self):
        check_lut(self.lut)
        if not (np.isfinite(self.gamma) and 0.0 < self.gamma <= 10.0):
            raise DisplayError(f"display gamma {self.gamma!r} is not in (0, 10]")
        if not (np.isfinite(self.lo) and np.isfinite(self.hi) and -30.0 <= self.lo < self.hi <= 30.0):
            raise DisplayError(f"shaper range [{self.lo!r}, {self.hi!r}] stops is not within [-30, 30]")

    @property
    def size(self) -> int:
        return int(self.lut.shape[0])

    @functools.cached_property
    def lut_digest(self) -> str:
        """sha256 of the table (not the gamma): what the GPU's 3D texture is
        cached by, hashed once per instance."""
        return hashlib.sha256(np.ascontiguousarray(self.lut).tobytes()).hexdigest()

    def with_gamma(self, gamma: float) -> "DisplayTransform":
        return dataclasses.replace(self, gamma=float(gamma))

    def encode(self, linear: np.ndarray) -> np.ndarray:
        """(..., 3) scene-linear (times the exposure) -> display code values
        in [0, 1], float64: trilinear in the table, then the gamma.
        ENCODE_CHUNK colours at a time (bounded temporaries)."""
        x = np.asarray(linear)
        flat = x.reshape(-1, 3)
        table = self.lut.reshape(-1, 3).astype(np.float64)     # once per call, not per chunk
        out = np.empty(flat.shape, np.float64)
        for a in range(0, flat.shape[0], ENCODE_CHUNK):
            out[a:a + ENCODE_CHUNK] = self._encode(flat[a:a + ENCODE_CHUNK], table)
        return out.reshape(x.shape)

    def _encode(self, x: np.ndarray, flat: np.ndarray) -> np.ndarray:
        s = shaper(x, self.lo, self.hi) * (self.size - 1)
        i0 = np.minimum(s.astype(np.int64), self.size - 2)
        f = s - i0
        n = self.size
        base = i0[:, 0] + n * (i0[:, 1] + n * i0[:, 2])
        out = np.zeros((s.shape[0], 3))
        for dr in (0, 1):
            wr = f[:, 0] if dr else 1.0 - f[:, 0]
            for dg in (0, 1):
                wg = wr * (f[:, 1] if dg else 1.0 - f[:, 1])
                for db in (0, 1):
                    w = wg * (f[:, 2] if db else 1.0 - f[:, 2])
                    out += w[:, None] * flat[base + dr + n * dg + n * n * db]
        out = np.clip(out, 0.0, 1.0)
        if self.gamma != 1.0:
            out = np.power(out, 1.0 / self.gamma)
        return out

    def lut_bytes(self) -> bytes:
        """The table as uint16 little-endian, (N, N, N, 3)."""
        return np.round(np.clip(self.lut, 0.0, 1.0) * 65535.0).astype("<u2").tobytes()

    def payload(self) -> bytes:
        """The table as a file carries it (LUT_ENCODING)."""
        import zstandard  # optional at import: only files with a table need it
        return zstandard.ZstdCompressor(level=19).compress(self.lut_bytes())

    def block(self) -> np.ndarray:
        """(N, N, N, 4) float32 RGBA for a 3D texture (alpha 1)."""
        out = np.ones(self.lut.shape[:3] + (4,), np.float32)
        out[..., :3] = self.lut
        return out


def check_lut(lut) -> None:
    """Raise DisplayError unless ``lut`` is an (N, N, N, 3) float32 table of
    finite values in [0, 1] with MIN_LUT_SIZE <= N <= MAX_LUT_SIZE."""
    if not isinstance(lut, np.ndarray) or lut.dtype != np.float32:
        raise DisplayError("a display table must be a float32 array")
    n = lut.shape[0] if lut.ndim == 4 else -1
    if lut.shape != (n, n, n, 3) or not MIN_LUT_SIZE <= n <= MAX_LUT_SIZE:
        raise DisplayError(f"a display table must be (N, N, N, 3) with N in {MIN_LUT_SIZE}..{MAX_LUT_SIZE}, "
                           f"not {lut.shape}")
    if not np.isfinite(lut).all() or lut.min() < 0.0 or lut.max() > 1.0:
        raise DisplayError("a display table's values must be finite and within [0, 1]")


def from_payload(data: bytes, size: int, **kw) -> DisplayTransform:
    """A table from a file's payload (LUT_ENCODING), read as untrusted input:
    it may not unpack beyond a ``size``^3 table."""
    import zstandard  # optional at import: only files with a table need it
    if not (isinstance(size, int) and MIN_LUT_SIZE <= size <= MAX_LUT_SIZE):
        raise DisplayError(f"a display table's size must be {MIN_LUT_SIZE}..{MAX_LUT_SIZE}, not {size!r}")
    want = size ** 3 * 6
    try:
        # a frame may declare its size: python-zstandard trusts it over max_output_size
        declared = zstandard.frame_content_size(bytes(data))
        if declared not in (-1, want):
            raise DisplayError(f"the display table unpacks to {declared} bytes; a {size}^3 table has {want}")
        raw = zstandard.ZstdDecompressor().decompress(bytes(data), max_output_size=want)
    except zstandard.ZstdError as exc:
        raise DisplayError(f"the display table is not a Zstandard frame of {size}^3 values: {exc}") from None
    return from_lut_bytes(raw, size, **kw)


def from_lut_bytes(data: bytes, size: int, *, gamma: float = 1.0, name: str = "",
                   lo: float = SHAPER_LO, hi: float = SHAPER_HI) -> DisplayTransform:
    """A table read from a file (uint16 little-endian, ``size``**3 RGB)."""
    if not (isinstance(size, int) and MIN_LUT_SIZE <= size <= MAX_LUT_SIZE):
        raise DisplayError(f"a display table's size must be {MIN_LUT_SIZE}..{MAX_LUT_SIZE}, not {size!r}")
    if len(data) != size ** 3 * 3 * 2:
        raise DisplayError(f"a {size}^3 display table has {size ** 3 * 6} bytes, not {len(data)}")
    lut = (np.frombuffer(data, "<u2").reshape(size, size, size, 3) / 65535.0).astype(np.float32)
    return DisplayTransform(lut, gamma=gamma, name=name, lo=lo, hi=hi)
