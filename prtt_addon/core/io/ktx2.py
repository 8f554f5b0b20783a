"""KTX 2.0 files of float 2D array textures: PRTT's SH planes for glTF and the web.

PyPI has no writer of float KTX2 arrays, so this is a small one: three formats,
``VK_FORMAT_R16G16B16A16_SFLOAT`` (RGBA16F, 8 bytes a texel: the SH values
themselves), ``VK_FORMAT_R8G8B8A8_UNORM`` (RGBA8, 4 bytes: the glTF
export's 8-bit encoding, each plane with its own scale and offset kept
beside the file, core/io/gltf_prtt.py) and ``VK_FORMAT_R8_UNORM`` (R8, one
byte: a sun mask, the visible fraction of the disc in 0 .. 1), a 2D array
texture of ``layers`` layers (four SH coefficients per layer: coefficient
k = 4 * layer + channel, k = l² + l + m), one or more mip levels, no
supercompression or Zstandard per level (scheme 2). Layout as the KTX 2.0
specification (Khronos, 2020-2023) gives it: identifier, header, index, level
index, the Data Format Descriptor (one basic block, four float samples, linear
transfer, BT.709 primaries), key/value data (``KTXorientation`` "rd": the
first row is the top, ``KTXwriter``, and the caller's keys), then the levels'
data, smallest level first, each level's layers in order, each layer's rows
top first. tests/test_ktx2.py checks files against ktx-parse (npm), an
independent parser.

:func:`read_ktx2` reads back what :func:`write_ktx2` writes, for tests and the
export's checks; it bounds every size before allocating (files from outside
are untrusted) and refuses any other format with :class:`KTX2Error`.
Levels are float16 arrays for RGBA16F and uint8 arrays for RGBA8 and R8
(channels last: 4, or 1 for R8).
"""
from __future__ import annotations

import math
import struct

import numpy as np

from ..base.atomic import atomic_write
from ..base.memory import MemoryLimitError, check_fits

IDENTIFIER = b"\xabKTX 20\xbb\r\n\x1a\n"
VK_FORMAT_R16G16B16A16_SFLOAT = 97
VK_FORMAT_R8G8B8A8_UNORM = 37
VK_FORMAT_R8_UNORM = 9
#: (dtype, channels) -> (vkFormat, typeSize, bytes a texel, name)
FORMATS = {(np.dtype(np.float16), 4): (VK_FORMAT_R16G16B16A16_SFLOAT, 2, 8, "RGBA16F"),
           (np.dtype(np.uint8), 4): (VK_FORMAT_R8G8B8A8_UNORM, 1, 4, "RGBA8"),
           (np.dtype(np.uint8), 1): (VK_FORMAT_R8_UNORM, 1, 1, "R8")}
SUPERCOMPRESSION = {"none": 0, "zstd": 2}
#: Largest side and layer count accepted (a 16384² array of 16 layers of
#: RGBA16F is 32 GiB: beyond what a browser or a GPU takes).
MAX_SIDE = 16384
MAX_LAYERS = 2048
MAX_LEVELS = 15
#: Key/value data and Data Format Descriptor sizes a reader accepts.
MAX_KVD_BYTES = 1 << 20
_HEADER = struct.Struct("<12s9I")          # identifier + 9 uint32: vkFormat ... supercompressionScheme
_INDEX = struct.Struct("<4I2Q")            # dfd offset/length, kvd offset/length, sgd offset/length
_LEVEL = struct.Struct("<3Q")              # byteOffset, byteLength, uncompressedByteLength


class KTX2Error(ValueError):
    """A KTX2 file this module cannot write or read; the message says why."""


def _dfd(dtype, channels: int = 4) -> bytes:
    """The Data Format Descriptor of linear RGBA16F (float16), RGBA8 UNORM
    (uint8) or R8 UNORM (uint8, one channel): its total size, then one basic
    descriptor block (24 bytes) with a 16-byte sample per channel."""
    half = np.dtype(dtype) == np.float16
    bits = 16 if half else 8
    texel = bits // 8 * channels
    samples = b""
    for i, channel in enumerate((0, 1, 2, 15)[:channels]):  # KHR_DF_CHANNEL_RGBSDA_R, G, B, ALPHA
        if half:
            qualifiers = 0x80 | 0x40                        # FLOAT | SIGNED (a float's sign bit)
            lower, upper = 0xBF800000, 0x3F800000           # sampleLower -1.0f, sampleUpper 1.0f
        else:
            qualifiers, lower, upper = 0, 0, 255            # unsigned normalised: 0 .. 255 is 0 .. 1
        samples += struct.pack("<HBB4B2I", bits * i, bits - 1, channel | qualifiers, 0, 0, 0, 0, lower, upper)
    block = struct.pack("<IHH4B4B8B", 0, 2, 24 + len(samples),
                        1, 1, 1, 0,                         # RGBSDA model, BT.709 primaries, linear, straight alpha
                        0, 0, 0, 0,                         # one texel a block
                        texel, 0, 0, 0, 0, 0, 0, 0) + samples  # bytes in plane 0
    return struct.pack("<I", 4 + len(block)) + block


def _kvd(entries: dict) -> bytes:
    """Key/value data, keys sorted by their bytes, each entry padded to 4."""
    out = b""
    for key in sorted(entries, key=lambda k: k.encode("utf-8")):
        value = entries[key]
        value = value if isinstance(value, bytes) else str(value).encode("utf-8") + b"\0"
        kv = key.encode("utf-8") + b"\0" + value
        out += struct.pack("<I", len(kv)) + kv + b"\0" * (-len(kv) % 4)
    return out


def _check_levels(levels) -> list:
    """Levels as C-contiguous (layers, H, W, 4) float16 or uint8 arrays (or
    (layers, H, W, 1) uint8: R8), each half the one before (rounded down, at
    least 1)."""
    if not levels or len(levels) > MAX_LEVELS:
        raise KTX2Error(f"a KTX2 file needs 1..{MAX_LEVELS} mip levels, got {len(levels)}")
    out = []
    for i, lv in enumerate(levels):
        a = np.asarray(lv)
        if a.ndim != 4 or a.shape[3] not in (1, 4) or (a.shape[3] == 1 and a.dtype != np.uint8):
            raise KTX2Error(f"level {i}: expected (layers, height, width, 4), or (..., 1) of uint8, got {a.shape}")
        if (a.dtype, a.shape[3]) not in FORMATS:
            if not np.issubdtype(a.dtype, np.floating):
                raise KTX2Error(f"level {i}: expected floats or uint8, got {a.dtype}")
            a = a.astype(np.float16)
        if i and a.dtype != out[0].dtype:
            raise KTX2Error(f"level {i}: {a.dtype}, level 0 is {out[0].dtype}")
        out.append(np.ascontiguousarray(a))
    L, H, W, C = out[0].shape
    if not (1 <= L <= MAX_LAYERS and 1 <= H <= MAX_SIDE and 1 <= W <= MAX_SIDE):
        raise KTX2Error(f"{L} layers of {W}x{H}: at most {MAX_LAYERS} layers and {MAX_SIDE} texels a side")
    for i, a in enumerate(out[1:], 1):
        want = (L, max(1, H >> i), max(1, W >> i), C)
        if a.shape != want:
            raise KTX2Error(f"level {i}: expected shape {want}, got {a.shape}")
    return out


def write_ktx2(path, levels, **kw) -> dict:
    """Write :func:`ktx2_bytes` of ``levels`` at ``path``, atomically. Returns
    {"bytes": file size, "level_bytes": [(stored, uncompressed) per level]}."""
    blob, level_bytes = ktx2_bytes(levels, **kw)
    with atomic_write(str(path)) as tmp:
        with open(tmp, "wb") as f:
            f.write(blob)
    return {"bytes": len(blob), "level_bytes": level_bytes}


def ktx2_bytes(levels, *, supercompression: str = "none", keys: dict | None = None,
               zstd_level: int = 10) -> tuple[bytes, list]:
    """Mip ``levels`` (level 0 first, each (layers, H, W, 4): float16 (or
    floats, converted) for RGBA16F, uint8 for RGBA8; (layers, H, W, 1)
    uint8 for R8) as the bytes of a KTX2
    2D array texture, and
    [(stored, uncompressed) bytes per level]. ``supercompression``: "none" or
    "zstd" (each level on its own, as KTX2 requires). ``keys``: extra
    key/value pairs (str -> str)."""
    if supercompression not in SUPERCOMPRESSION:
        raise KTX2Error(f"supercompression must be one of {sorted(SUPERCOMPRESSION)}, got {supercompression!r}")
    levels = _check_levels(levels)
    L, H, W = levels[0].shape[:3]
    # The levels' memory itself, not a bytes copy of it (a 2048² relightable
    # set's glossy rows are 0.6 GB of half floats).
    raw = [memoryview(lv).cast("B") for lv in levels]
    if supercompression == "zstd":
        import zstandard  # optional at import: only zstd files need it
        cctx = zstandard.ZstdCompressor(level=zstd_level)
        stored = [cctx.compress(b) for b in raw]
    else:
        stored = raw
    fmt = (levels[0].dtype, levels[0].shape[3])
    vk, type_size = FORMATS[fmt][:2]
    dfd = _dfd(*fmt)
    kvd = _kvd({"KTXorientation": "rd", "KTXwriter": "PRTT (prtt_addon.core.io.ktx2)", **(keys or {})})
    n = len(levels)
    level_index_at = _HEADER.size + _INDEX.size
    dfd_at = level_index_at + n * _LEVEL.size
    kvd_at = dfd_at + len(dfd)
    data_at = kvd_at + len(kvd)
    # Levels in the file smallest first; uncompressed ones aligned to lcm(texel bytes, 4).
    align = math.lcm(FORMATS[fmt][2], 4) if supercompression == "none" else 1
    offsets, pos, body = [0] * n, data_at, []
    for i in reversed(range(n)):
        pad = -pos % align
        body.append(b"\0" * pad)
        pos += pad
        offsets[i] = pos
        body.append(stored[i])
        pos += len(stored[i])
    header = _HEADER.pack(IDENTIFIER, vk, type_size, W, H, 0, L, 1, n,
                          SUPERCOMPRESSION[supercompression])
    index = _INDEX.pack(dfd_at, len(dfd), kvd_at, len(kvd), 0, 0)
    level_index = b"".join(_LEVEL.pack(offsets[i], len(stored[i]), len(raw[i])) for i in range(n))
    blob = b"".join([header, index, level_index, dfd, kvd, *body])      # one copy of the payload
    return blob, [(len(s), len(r)) for s, r in zip(stored, raw)]


def read_ktx2(path, *, max_bytes: int | None = None) -> tuple[list, dict]:
    """(levels [(layers, H, W, 4) float16 or uint8, or (layers, H, W, 1)
    uint8], key/value dict) of a KTX2 file in a format :func:`write_ktx2` writes. Every size is checked against
    the file's own length and the limits above before anything is allocated;
    anything else is a KTX2Error naming the file."""
    with open(path, "rb") as f:
        data = f.read(max_bytes + 1 if max_bytes else -1)
    if max_bytes and len(data) > max_bytes:
        raise KTX2Error(f"{path}: larger than {max_bytes} bytes")
    return parse_ktx2(data, str(path))


def parse_ktx2(data: bytes, path: str = "<bytes>") -> tuple[list, dict]:
    """:func:`read_ktx2` of bytes in memory (``path`` names them in errors)."""

    def fail(why):
        raise KTX2Error(f"{path}: {why}")

    if len(data) < _HEADER.size + _INDEX.size or not data.startswith(IDENTIFIER):
        fail("not a KTX 2.0 file")
    _, vk, type_size, W, H, depth, L, faces, n, scheme = _HEADER.unpack_from(data)
    fmt = next((d for d, f in FORMATS.items() if f[:2] == (vk, type_size)), None)
    if fmt is None:
        fail(f"vkFormat {vk} (typeSize {type_size}); only RGBA16F ({VK_FORMAT_R16G16B16A16_SFLOAT}), "
             f"RGBA8 ({VK_FORMAT_R8G8B8A8_UNORM}) and R8 ({VK_FORMAT_R8_UNORM}) are read")
    dtype, channels = fmt
    fmt_name = FORMATS[fmt][3]
    if depth != 0 or faces != 1 or not (1 <= L <= MAX_LAYERS) or not (1 <= W <= MAX_SIDE and 1 <= H <= MAX_SIDE):
        fail(f"{W}x{H}x{depth}, {L} layers, {faces} faces: not a 2D array within the limits")
    if not 1 <= n <= MAX_LEVELS or n > 1 + max(W, H).bit_length():
        fail(f"{n} mip levels for {W}x{H}")
    if scheme not in SUPERCOMPRESSION.values():
        fail(f"supercompression scheme {scheme} (only none and zstd)")
    dfd_at, dfd_len, kvd_at, kvd_len, sgd_at, sgd_len = _INDEX.unpack_from(data, _HEADER.size)
    if sgd_len:
        fail("supercompression global data is not expected for these schemes")
    for what, at, ln in (("DFD", dfd_at, dfd_len), ("key/value data", kvd_at, kvd_len)):
        if ln > MAX_KVD_BYTES or at + ln > len(data):
            fail(f"{what} of {ln} bytes at {at} runs past the file")
    if data[dfd_at:dfd_at + dfd_len] != _dfd(*fmt):
        fail(f"its Data Format Descriptor is not linear {fmt_name}")
    keys, p, end = {}, kvd_at, kvd_at + kvd_len
    while p + 4 <= end:
        (ln,) = struct.unpack_from("<I", data, p)
        if ln == 0 or p + 4 + ln > end:
            fail("a key/value entry runs past its data")
        kv = data[p + 4:p + 4 + ln]
        key, sep, value = kv.partition(b"\0")
        if not sep:
            fail("a key without its terminating NUL")
        keys[key.decode("utf-8", "replace")] = value.rstrip(b"\0").decode("utf-8", "replace")
        p += 4 + ln + (-ln % 4)
    level_index_at = _HEADER.size + _INDEX.size
    if level_index_at + n * _LEVEL.size > len(data):
        fail("its level index runs past the file")
    # Every level's place and size against the file first: only then memory.
    index = []
    for i in range(n):
        off, ln, raw_len = _LEVEL.unpack_from(data, level_index_at + i * _LEVEL.size)
        shape = (L, max(1, H >> i), max(1, W >> i), channels)
        want = int(np.prod(shape)) * type_size
        if raw_len != want or off + ln > len(data) or (scheme == 0 and ln != want):
            fail(f"level {i}: {ln} bytes at {off} ({raw_len} uncompressed) for {shape} {fmt_name}")
        index.append((off, ln, shape, want))
    try:
        check_fits(2 * sum(want for *_, want in index), f"reading {path}")
    except MemoryLimitError as exc:
        fail(str(exc))
    levels = []
    for i, (off, ln, shape, want) in enumerate(index):
        chunk = data[off:off + ln]
        if scheme == 2:
            import zstandard  # optional at import: only zstd files need it
            try:
                # a frame may declare its size: python-zstandard trusts it over max_output_size
                declared = zstandard.frame_content_size(chunk)
                if declared not in (want, -1):
                    fail(f"level {i}: its Zstandard frame declares {declared} bytes, {want} expected")
                chunk = zstandard.ZstdDecompressor().decompress(chunk, max_output_size=want)
            except (zstandard.ZstdError, MemoryError) as exc:
                fail(f"level {i}: its Zstandard data is corrupt ({type(exc).__name__}: {exc})")
            if len(chunk) != want:
                fail(f"level {i}: {len(chunk)} bytes after Zstandard, {want} expected")
        levels.append(np.frombuffer(chunk, dtype).reshape(shape).copy())
    return levels, keys


def sh_layers(planes: np.ndarray) -> np.ndarray:
    """(K, H, W) SH planes (k = l² + l + m, rows top first) as (ceil(K/4), H, W, 4)
    layers: coefficient k in layer k // 4, channel k % 4; the last layer's
    unused channels are 0."""
    K, H, W = planes.shape
    out = np.zeros(((K + 3) // 4 * 4, H, W), planes.dtype)
    out[:K] = planes
    return np.ascontiguousarray(out.reshape(-1, 4, H, W).transpose(0, 2, 3, 1))
