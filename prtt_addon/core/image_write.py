"""Write rendered previews: PNG (8-bit sRGB, alpha) or OpenEXR (float32 RGBA, linear).

Pixels come in as (H, W, 4) float32 linear RGBA with row 0 at the *bottom*
(as the GPU reads them back); files are written top row first. The PNG path
applies the sRGB transfer function (Blender's "Standard" view transform),
clipping to [0, 1]; EXR keeps linear values untouched. Writes are atomic.
No dependency beyond zlib and the OpenEXR binding PRTT already ships.
"""
from __future__ import annotations

import os
import struct
import zlib

import numpy as np

from .atomic import atomic_write


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

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 6, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw.tobytes(), 6)) + chunk(b"IEND", b""))


def write_image(path: str, rgba_bottom_first: np.ndarray, *, exposure: float = 1.0) -> str:
    """Write linear RGBA pixels to ``path`` (.png or .exr); returns the path.

    exposure multiplies the colour first (2**stops)."""
    a = np.asarray(rgba_bottom_first, np.float32)
    if a.ndim != 3 or a.shape[2] != 4:
        raise ValueError(f"expected (H, W, 4) RGBA pixels, got {a.shape}")
    img = a[::-1].copy()
    img[..., :3] *= exposure
    ext = os.path.splitext(path)[1].lower()
    if ext == ".png":
        out = np.empty(img.shape, np.uint8)
        out[..., :3] = np.round(srgb_encode(img[..., :3]) * 255.0)
        out[..., 3] = np.round(np.clip(img[..., 3], 0.0, 1.0) * 255.0)
        data = png_bytes(out)
        with atomic_write(path) as tmp, open(tmp, "wb") as f:
            f.write(data)
        return path
    if ext == ".exr":
        import OpenEXR
        channels = {c: np.ascontiguousarray(img[..., i]) for i, c in enumerate("RGBA")}
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        with atomic_write(path) as tmp, OpenEXR.File(header, channels) as f:
            f.write(tmp)
        return path
    raise ValueError(f"cannot write {path!r}: use a .png or .exr file name")


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
