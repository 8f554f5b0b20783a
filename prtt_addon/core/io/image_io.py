"""Reading HDR images (OpenEXR and Radiance .hdr) into float32 RGB arrays.

Returned arrays are (H, W, 3) float32 in *file order*: row 0 is the top of the
image (for an equirect environment that is +Z, see envmap.py). Blender's
``Image.pixels`` runs the other way (row 0 at the bottom); callers that take
pixels from Blender flip them.
"""
from __future__ import annotations

import os
import re

import numpy as np

from ..base.memory import check_fits

# Environment images come from users and the web: their headers are checked
# against these before any pixel memory is allocated.
#: Bytes of a Radiance header before its resolution line (real ones are < 1 KB).
MAX_HDR_HEADER = 1 << 16
#: Pixels per side and in all of an environment image (a 32K x 16K equirect is 2^29;
#: SH projection needs nothing near that: 2^28 keeps the float64 copy at 6 GB).
MAX_ENV_SIDE = 1 << 15
MAX_ENV_PIXELS = 1 << 28
#: Peak bytes a pixel costs while reading and converting (RGBE bytes, exponents,
#: scale, float64 RGB and its product, the float32 result, the float64 copy
#: envmap.as_environment_image makes): checked against available memory.
BYTES_PER_PIXEL = 4 + 4 + 8 + 24 + 24 + 12 + 24


class ImageReadError(ValueError):
    """An image could not be read as an HDR image; the message says why."""


def read_hdr_image(path) -> np.ndarray:
    """Read an EXR or Radiance HDR file. Returns (H, W, 3) float32, top row first."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ImageReadError(f"{path}: no such file")
    with open(path, "rb") as f:
        magic = f.read(10)
    if magic[:4] == b"\x76\x2f\x31\x01":
        return _read_exr(path)
    if magic.startswith(b"#?"):
        return _read_radiance(path)
    kind = _sniff_ldr(magic)
    if kind:
        raise ImageReadError(
            f"{path}: a {kind} image is not HDR; use an OpenEXR (.exr) or Radiance (.hdr) environment"
        )
    raise ImageReadError(f"{path}: not an OpenEXR or Radiance HDR file")


def _sniff_ldr(magic: bytes) -> str | None:
    if magic.startswith(b"\x89PNG"):
        return "PNG"
    if magic.startswith(b"\xff\xd8"):
        return "JPEG"
    if magic[:2] in (b"II", b"MM"):
        return "TIFF"
    if magic.startswith(b"BM"):
        return "BMP"
    return None


def check_image_size(path: str, width: int, height: int, channels: int = 3) -> None:
    """Refuse (ImageReadError, or memory.MemoryLimitError) an image too large to
    read, from its header's size alone."""
    if not (1 <= width <= MAX_ENV_SIDE and 1 <= height <= MAX_ENV_SIDE and width * height <= MAX_ENV_PIXELS):
        raise ImageReadError(f"{path}: {width}x{height} pixels; an environment image may have 1..{MAX_ENV_SIDE} "
                             f"pixels a side and at most {MAX_ENV_PIXELS} in all")
    check_fits(width * height * max(channels, 3) * BYTES_PER_PIXEL // 3, f"reading {path} ({width}x{height})")


def _read_exr(path: str) -> np.ndarray:
    import OpenEXR

    try:
        with OpenEXR.File(path, header_only=True) as f:
            (x0, y0), (x1, y1) = (tuple(int(v) for v in c) for c in f.header()["dataWindow"])
            n_chan = len(f.header().get("channels", [])) or 3
    except Exception as exc:  # the binding raises plain Exceptions
        raise ImageReadError(f"{path}: unreadable EXR header ({exc})") from exc
    check_image_size(path, x1 - x0 + 1, y1 - y0 + 1, n_chan)
    try:
        # Copy inside the block: the binding empties its dicts when the file closes.
        with OpenEXR.File(path) as f:
            channels = {name: np.array(ch.pixels, copy=True) for name, ch in f.channels().items()}
    except Exception as exc:  # the binding raises plain Exceptions
        raise ImageReadError(f"{path}: unreadable EXR ({exc})") from exc
    for packed in ("RGB", "RGBA"):
        if packed in channels:
            return np.ascontiguousarray(channels[packed][..., :3], dtype=np.float32)
    # Separate channels, possibly inside a layer ("Image.R").
    for prefix in ("", *sorted({n.rsplit(".", 1)[0] + "." for n in channels if "." in n})):
        names = [prefix + c for c in "RGB"]
        if all(n in channels for n in names):
            return np.ascontiguousarray(np.stack([channels[n] for n in names], axis=-1), dtype=np.float32)
    for grey in ("Y", "R", "V"):
        if grey in channels and channels[grey].ndim == 2:
            return np.repeat(channels[grey][..., None], 3, axis=-1).astype(np.float32)
    raise ImageReadError(f"{path}: EXR has no R, G, B channels (found {sorted(channels)})")


_RES_RE = re.compile(rb"^([-+])Y\s+(\d+)\s+([-+])X\s+(\d+)\s*$")


def _radiance_header(path: str, f) -> tuple[bytes, int, int]:
    """Read the header and resolution line (at most MAX_HDR_HEADER bytes).
    Returns (y sign, height, width)."""
    fmt = None
    used = 0
    while True:
        line = f.readline(MAX_HDR_HEADER - used + 1)
        used += len(line)
        if used > MAX_HDR_HEADER:
            raise ImageReadError(f"{path}: Radiance header longer than {MAX_HDR_HEADER} bytes (corrupt)")
        if not line.endswith(b"\n"):
            raise ImageReadError(f"{path}: truncated Radiance header")
        line = line.strip()
        if not line:
            break
        if line.startswith(b"FORMAT="):
            fmt = line[7:]
    if fmt not in (None, b"32-bit_rle_rgbe"):
        raise ImageReadError(f"{path}: unsupported Radiance format {fmt[:40].decode(errors='replace')}")
    m = _RES_RE.match(f.readline(256))
    if not m or len(m.group(2)) > 18 or len(m.group(4)) > 18:
        raise ImageReadError(f"{path}: unsupported Radiance resolution line")
    if m.group(3) != b"+":
        raise ImageReadError(f"{path}: Radiance images stored right-to-left are not supported")
    return m.group(1), int(m.group(2)), int(m.group(4))


def _read_radiance(path: str) -> np.ndarray:
    """Radiance RGBE (.hdr) with flat or new-style run-length scanlines. The
    header and the size it declares are checked before pixels are allocated,
    and no more bytes are read than such an image can take."""
    with open(path, "rb") as f:
        ysign, h, w = _radiance_header(path, f)
        check_image_size(path, w, h)
        # A scanline takes at most 4 + 8 w bytes (run-length runs of one byte cost
        # two); read no more than that, nor than the file holds (read(n) would
        # allocate n bytes first).
        left = os.fstat(f.fileno()).st_size - f.tell()
        data = f.read(max(0, min(h * (4 + 8 * w), left)))
    pos = 0
    rgbe = np.empty((h, w, 4), dtype=np.uint8)
    buf = memoryview(data)
    for row in range(h):
        pos = _read_scanline(buf, pos, w, rgbe[row], path)
    e = rgbe[..., 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)
    img = ((rgbe[..., :3].astype(np.float64) + 0.5) * scale[..., None]).astype(np.float32)
    if ysign == b"+":          # stored bottom-to-top
        img = img[::-1].copy()
    return img


def _read_scanline(buf, pos: int, w: int, out: np.ndarray, path: str) -> int:
    n = len(buf)
    if pos + 4 > n:
        raise ImageReadError(f"{path}: truncated Radiance pixel data")
    b0, b1, b2, b3 = buf[pos], buf[pos + 1], buf[pos + 2], buf[pos + 3]
    if not (8 <= w < 0x8000 and b0 == 2 and b1 == 2 and not (b2 & 0x80)):
        # Flat (uncompressed) scanline.
        if pos + 4 * w > n:
            raise ImageReadError(f"{path}: truncated Radiance pixel data")
        out[:] = np.frombuffer(buf[pos:pos + 4 * w], dtype=np.uint8).reshape(w, 4)
        return pos + 4 * w
    if (b2 << 8 | b3) != w:
        raise ImageReadError(f"{path}: Radiance scanline width mismatch")
    pos += 4
    for c in range(4):
        x = 0
        while x < w:
            if pos >= n:
                raise ImageReadError(f"{path}: truncated Radiance run-length data")
            count = buf[pos]
            pos += 1
            if count > 128:
                count -= 128
                if x + count > w or pos >= n:
                    raise ImageReadError(f"{path}: corrupt Radiance run-length data")
                out[x:x + count, c] = buf[pos]
                pos += 1
            else:
                if count == 0 or x + count > w or pos + count > n:
                    raise ImageReadError(f"{path}: corrupt Radiance run-length data")
                out[x:x + count, c] = np.frombuffer(buf[pos:pos + count], dtype=np.uint8)
                pos += count
            x += count
    return pos
