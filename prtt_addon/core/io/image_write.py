"""Write rendered previews: PNG (8-bit display-encoded, alpha) or OpenEXR (float32 RGBA, linear).

Pixels come in as (H, W, 4) float32 linear RGBA with row 0 at the *bottom*
(as the GPU reads them back); files are written top row first. The PNG path
applies the sRGB transfer function (Blender's "Standard" view transform),
clipping to [0, 1], or the scene's view transform as a sampled table
(core/shading/display.py); EXR keeps linear values untouched. Writes are atomic:
a failed write leaves no file and an older file at the path untouched, and
raises :class:`ImageWriteError` naming the path the caller gave (not the
temporary beside it). The memory needed beyond the pixels themselves stays
small (:data:`WRITE_BYTES_PER_PIXEL`): PNG is encoded in bands of rows, EXR's
channel planes are made straight from the pixels.
No dependency beyond zlib and the OpenEXR binding PRTT already ships.
"""
from __future__ import annotations

import os
import struct
import zlib

import numpy as np

from ..base.atomic import atomic_write

#: Rows encoded at once: bounds the float64 temporaries of the sRGB encode.
BAND_ROWS = 256

#: Peak bytes per pixel that write_image allocates beside the (H, W, 4)
#: float32 input, measured at 4096^2 (VmHWM over the resident size before the
#: write): PNG 7.8 (the uint8 image and its compressed stream), EXR 16.2 (the
#: four float32 channel planes; OpenEXR compresses chunk by chunk). Rounded up.
#: (Before the row bands: PNG 139, EXR 56.)
WRITE_BYTES_PER_PIXEL = {".png": 12, ".exr": 20}


class ImageWriteError(OSError):
    """The image file cannot be written; the message names the caller's path."""


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear -> sRGB-encoded values in [0, 1] (IEC 61966-2-1)."""
    x = np.clip(np.nan_to_num(np.asarray(linear, np.float64), nan=0.0), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def png_bytes(rgba8_top_first: np.ndarray) -> bytes:
    """Encode (H, W, 4) uint8 as a PNG file."""
    h, w, c = rgba8_top_first.shape
    if c != 4 or rgba8_top_first.dtype != np.uint8:
        raise ValueError("png_bytes wants (H, W, 4) uint8")
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rgba8_top_first.reshape(h, w * 4)], axis=1)
    return _png_file(w, h, zlib.compress(raw.tobytes(), 6))


def srgb8(rgba_top_first: np.ndarray, exposure: float = 1.0, display=None) -> np.ndarray:
    """(h, W, 4) linear float -> (h, W, 4) uint8: display-encoded colour
    (sRGB, or ``display``: a core.shading.display.DisplayTransform), linear alpha."""
    encode = srgb_encode if display is None else display.encode
    out = np.empty(rgba_top_first.shape, np.uint8)
    out[..., :3] = np.round(encode(rgba_top_first[..., :3] * np.float32(exposure)) * 255.0)
    out[..., 3] = np.round(np.clip(np.nan_to_num(rgba_top_first[..., 3]), 0.0, 1.0) * 255.0)
    return out


def _png_stream(rgba_bottom_first: np.ndarray, exposure: float, display=None) -> bytes:
    """The PNG file of linear pixels, encoded and compressed BAND_ROWS rows at a time."""
    h, w, _ = rgba_bottom_first.shape
    z = zlib.compressobj(6)
    parts = []
    for top in range(0, h, BAND_ROWS):
        # File rows top..top+n are input rows h-1-top down to h-top-n.
        band = srgb8(rgba_bottom_first[h - 1 - top::-1][:BAND_ROWS], exposure, display)
        raw = np.zeros((band.shape[0], 1 + 4 * w), np.uint8)   # filter byte 0 ("None") per row
        raw[:, 1:] = band.reshape(band.shape[0], 4 * w)
        parts.append(z.compress(raw.tobytes()))
    parts.append(z.flush())
    return _png_file(w, h, b"".join(parts))


def _png_file(w: int, h: int, idat: bytes) -> bytes:
    """Signature and chunks around an RGBA8 image's compressed scanlines."""
    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 6, 0, 0, 0))
            + chunk(b"IDAT", idat) + chunk(b"IEND", b""))


def _write_png(path: str, a: np.ndarray, exposure: float, display) -> None:
    data = _png_stream(a, exposure, display)
    with atomic_write(path) as tmp, open(tmp, "wb") as f:
        f.write(data)


def _write_exr(path: str, a: np.ndarray, exposure: float, display) -> None:
    del display       # EXR keeps scene-linear radiance, as Blender writes it
    import OpenEXR
    # One contiguous top-first plane per channel, made directly from the
    # input: no full flipped RGBA copy on the way.
    channels = {}
    for i, c in enumerate("RGBA"):
        plane = np.ascontiguousarray(a[::-1, :, i])
        if i < 3 and exposure != 1.0:
            plane *= np.float32(exposure)
        channels[c] = plane
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_write(path) as tmp, OpenEXR.File(header, channels) as f:
        f.write(tmp)


def write_image(path: str, rgba_bottom_first: np.ndarray, *, exposure: float = 1.0, display=None) -> str:
    """Write linear RGBA pixels to ``path`` (.png or .exr); returns the path.

    exposure multiplies the colour first (2**stops). A PNG is encoded with
    ``display`` (a core.shading.display.DisplayTransform: the scene's view
    transform) or, when None, with sRGB (Standard); an EXR stays linear. Raises ValueError for a
    bad shape or extension, ImageWriteError (an OSError) when the file cannot
    be written: then no partial file is left behind and an existing file at
    ``path`` is untouched."""
    a = np.asarray(rgba_bottom_first, np.float32)
    if a.ndim != 3 or a.shape[2] != 4:
        raise ValueError(f"expected (H, W, 4) RGBA pixels, got {a.shape}")
    ext = os.path.splitext(path)[1].lower()
    writer = {".png": _write_png, ".exr": _write_exr}.get(ext)
    if writer is None:
        raise ValueError(f"cannot write {path!r}: use a .png or .exr file name")
    try:
        writer(path, a, exposure, display)
    except OSError as exc:
        # The error names the temporary file; say it about the caller's path.
        raise ImageWriteError(f"cannot write {path}: {exc.strerror or exc}") from exc
    except RuntimeError as exc:     # the OpenEXR binding reports I/O failures so
        raise ImageWriteError(f"cannot write {path}: {exc}") from exc
    return path


def read_exr_rgba(path: str) -> np.ndarray:
    """(H, W, 4) float32 of an RGBA EXR, row 0 at the bottom (tests, docs)."""
    import OpenEXR
    with OpenEXR.File(path) as f:
        ch = f.channels()
        if "RGBA" in ch:                     # the binding groups R, G, B, A into one entry
            img = np.array(ch["RGBA"].pixels, np.float32)
        else:
            img = np.stack([np.array(ch[c].pixels, np.float32) for c in "RGBA"], axis=-1)
    return img[::-1].copy()
