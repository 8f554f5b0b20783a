"""SH textures as OpenEXR files (format: docs/format.md).

One scanline EXR per texture: channels ``sh000 .. sh{K-1}`` (transfer, coefficient
order k = l^2 + l + m) or ``R.sh000 .. B.sh{K-1}`` (RGB bounce textures), half
(default) or float32, ZIP compressed (relightable bounces: PIZ, compression_of), with
``prtt_*`` header attributes.

The bake keeps textures channel-first, (C, H, W) with C = K (transfer) or 3K
(RGB, ordered R.sh000.., G.sh000.., B.sh000..), row 0 at the *bottom* (v up, like
UVs and Blender's Image.pixels); :func:`write_sh_planes` takes that layout.
:func:`write_sh_exr` and :func:`read_sh_exr` use the pixel-major (H, W, K) or
(H, W, 3, K) layout that is handier for tests and shaders. Files are written
top row first as usual for images, so an EXR viewer shows the UV layout the
right way up.

The OpenEXR Python binding silently writes garbage for non-contiguous array
views, so every channel is copied to a contiguous array first. Writes are
atomic (see atomic.py).
"""
from __future__ import annotations

import contextlib
import os
import subprocess

import numpy as np

from ..base.atomic import atomic_write
from ..base.child import child_env, python_executable
from ..base.memory import MemoryLimitError, check_fits, discard_pages
from ..sh.basis import bands_of

#: Version of the texture format described in docs/format.md.
TEXTURE_FORMAT_VERSION = 1
#: The SH convention string stored in every texture.
CONVENTION = "real-orthonormal,condon-shortley,z-up,k=l*l+l+m"
#: Largest finite float16 value; larger magnitudes need float32 storage.
HALF_MAX = 65504.0


def shown(value, limit: int = 80) -> str:
    """repr of an untrusted header value for a message: at most ``limit``
    characters, and never an exception (OpenEXR hands some damaged string
    attributes over as objects whose repr fails to decode them)."""
    try:
        text = repr(value)
    except Exception:                         # noqa: BLE001 - any failure: say so instead
        return f"<an unprintable {type(value).__name__}>"
    return text if len(text) <= limit else text[:limit - 3] + "..."


class TextureError(ValueError):
    """A texture file is missing, unreadable or not a PRTT texture."""


def channel_names(n_coeffs: int, rgb: bool = False) -> list[str]:
    names = [f"sh{k:03d}" for k in range(n_coeffs)]
    if rgb:
        return [f"{c}.{n}" for c in "RGB" for n in names]
    return names


HALF_MANTISSA_BITS = 10
#: Values quantize_half rounds at a time (its temporaries: ~14 bytes a value).
QUANTIZE_BLOCK = 1 << 20


def quantize_half(h: np.ndarray, keep: int) -> np.ndarray:
    """float16 values rounded to ``keep`` of half's 10 mantissa bits (round to
    nearest, ties to even; a carry moves into the exponent as it should).
    keep: 1 .. 10. Relative rounding error at most 2^-(keep+1) (absolute
    2^(-15-keep) for subnormals). A value that would round up past the
    largest half is left as it is.
    ZIP then compresses the zeroed low bits: noisy SH coefficients at 6 bits
    take ~0.73 of the bytes (docs/benchmarks.md)."""
    h = np.asarray(h, np.float16)
    if not 1 <= int(keep) <= HALF_MANTISSA_BITS:
        raise ValueError(f"keep {keep} mantissa bits: it must be 1..{HALF_MANTISSA_BITS}")
    drop = HALF_MANTISSA_BITS - int(keep)
    if drop <= 0:
        return h
    if h.size > QUANTIZE_BLOCK:
        # Elementwise, so in blocks: the uint32 temporaries stay a few MB whatever the texture's size.
        out = np.empty_like(h)
        flat_in, flat_out = h.reshape(-1), out.reshape(-1)
        for a in range(0, h.size, QUANTIZE_BLOCK):
            flat_out[a:a + QUANTIZE_BLOCK] = quantize_half(flat_in[a:a + QUANTIZE_BLOCK], keep)
        return out
    b = h.view(np.uint16).astype(np.uint32)
    r = (b + ((1 << (drop - 1)) - 1) + ((b >> drop) & 1)) & ~np.uint32((1 << drop) - 1)
    out = r.astype(np.uint16).view(np.float16)
    over = ~np.isfinite(out) & np.isfinite(h)
    out[over] = h[over]
    return out


def value_range(values: np.ndarray, executor=None) -> tuple[float, float]:
    """(min, max) of ``values`` (NaN if any value is NaN; (0, 0) when empty).

    With an ``executor`` the leading axis (channels) is reduced in parallel.
    One range serves both :func:`check_finite` and :func:`half_overflow`.
    """
    a = np.asarray(values)
    if a.size == 0:
        return 0.0, 0.0
    if executor is None or a.ndim < 2 or a.shape[0] < 2:
        return float(np.min(a)), float(np.max(a))
    per = list(executor.map(lambda c: (np.min(c), np.max(c)), a))
    # np.min/np.max propagate NaN; Python's min() would depend on the order.
    return float(np.min([p[0] for p in per])), float(np.max([p[1] for p in per]))


def half_overflow(values: np.ndarray, rng: tuple[float, float] | None = None) -> int:
    """How many finite values would overflow float16 (|v| > 65504).
    ``rng``: the values' :func:`value_range`, if already known."""
    lo, hi = rng if rng is not None else value_range(values)
    if -HALF_MAX <= lo and hi <= HALF_MAX:
        return 0                         # two reductions, no temporaries
    return int(np.count_nonzero(np.abs(values) > HALF_MAX))


def check_finite(values: np.ndarray, what: str, rng: tuple[float, float] | None = None) -> None:
    """Raise if any value is NaN or Inf (min/max propagate both)."""
    lo, hi = rng if rng is not None else value_range(values)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise ValueError(f"refusing to write non-finite values to {what}")


def relight_channel_names(n_coeffs: int, glossy_coeffs: int = 0, shared: bool = False) -> list[str]:
    """Channels of a relightable bounce texture (kind "relight"): per colour
    ``c.dc.iNNN`` (the DC row over light coefficient i < K), then, with
    ``glossy_coeffs`` Kg > 0, per colour ``c.oNNN.iNNN`` for out coefficient
    1 <= o < Kg and light coefficient i < Kg; ``shared`` (header
    ``prtt_glossy_colour`` = "shared"): one set ``S.oNNN.iNNN`` for all
    colours instead (expand_shared_glossy)."""
    names = [f"{c}.dc.i{i:03d}" for c in "RGB" for i in range(n_coeffs)]
    colours = "S" if shared else "RGB"
    names += [f"{c}.o{o:03d}.i{i:03d}" for c in colours for o in range(1, glossy_coeffs) for i in range(glossy_coeffs)]
    return names


def expand_shared_glossy(dc: np.ndarray, shared: np.ndarray) -> np.ndarray:
    """Per-colour glossy rows (..., 3, Kg - 1, Kg) float32 from the shared rows
    ``shared`` (..., Kg - 1, Kg), the colour mean of the rows, tinted as the
    texel's DC response to the light's DC: R_c ~= kappa_c S with kappa_c =
    dc_c,0 / mean_c dc_c,0 (1 where that mean is zero or below 1e-3 of the
    largest colour's). Exact when the light bounced off grey surfaces only
    (every colour's rows are then equal)."""
    kappa = glossy_tint(dc[..., 0])
    # float32 product: the expanded rows are what a reader holds (no float64 copy of them).
    return kappa[..., None, None] * np.asarray(shared, np.float32)[..., None, :, :]


def glossy_tint(dc0: np.ndarray) -> np.ndarray:
    """(..., 3) float32 tints kappa_c of :func:`expand_shared_glossy` from the DC
    responses to the light's DC ``dc0`` (..., 3)."""
    d0 = np.asarray(dc0, np.float64)                                               # (..., 3)
    m = d0.mean(axis=-1, keepdims=True)
    # A mean far below its colours' size (signs that cancel) would blow the tint up: untinted there.
    ok = np.abs(m) > 1e-3 * np.abs(d0).max(axis=-1, keepdims=True)
    return np.divide(d0, m, out=np.ones_like(d0), where=ok).astype(np.float32)


def relight_full_bits(names: list[str]) -> list[bool]:
    """Which channels of a relightable texture keep all mantissa bits under a
    lossy storage (write_sh_planes' full_bits): the out-DC response to the
    light's DC, ``c.dc.i000``, as a transfer texture's DC keeps them; every
    other channel is a response to a band l >= 1 of the light or of the
    direction out."""
    return [n.endswith(".dc.i000") for n in names]


def compression_of(kind: str):
    """The EXR compression of a texture of ``kind``: ZIP, except relightable
    bounces (kind "relight"), PIZ. Both are lossless. On the room's relight
    texture (147 half channels, 512^2, 2 threads) ZIP wrote in 0.48 s and
    PIZ in 0.22 s, for 38.9 against 42.7 MB (reads 0.17 and 0.15 s): its
    write was the largest part of the relightable bake's write stage."""
    import OpenEXR
    return OpenEXR.PIZ_COMPRESSION if kind == "relight" else OpenEXR.ZIP_COMPRESSION


#: Most threads OpenEXR compresses with as write_sh_planes writes. Its scanline
#: writer keeps two line buffers a thread, each about three compression blocks of
#: the file's rows, resident until the file closes: 4 threads hold ~400 (ZIP) or
#: ~775 (PIZ) rows beside the band being written, where 32 cores would hold 3000 or
#: 6000 (a 4096^2 relightable texture's 2048-texel rows of 291 half channels: 1.2 MB a row).
WRITE_THREADS = 4
#: Lines of OpenEXR's compression block (ZIP 16, PIZ 32): what a line buffer holds.
BLOCK_LINES = {"ZIP": 16, "PIZ": 32}


def write_threads() -> int:
    """Threads OpenEXR compresses with while a texture is written (the
    machine's cores, at most WRITE_THREADS)."""
    return max(1, min(os.cpu_count() or 1, WRITE_THREADS))


def writer_bytes(channels: int, width: int, half: bool, kind: str, threads: int | None = None) -> int:
    """Resident bytes OpenEXR's scanline writer holds while a ``kind`` texture
    of ``channels`` x ``width`` texels a row is written with ``threads``
    (default :func:`write_threads`): 35 rows of the file plus, a thread, two
    line buffers of three compression blocks (the block, its compressed copy,
    the compressor's scratch). Measured (291 half channels, 1024 wide, peak RSS
    growth in rows of the file, threads 1 / 2 / 4): ZIP 126 / 216 / 398, PIZ
    220 / 405 / 775; this gives 131 / 227 / 419 and 227 / 419 / 803."""
    t = max(1, int(threads if threads is not None else write_threads()))
    block = BLOCK_LINES["PIZ" if kind == "relight" else "ZIP"]
    row = int(channels) * int(width) * (2 if half else 4)
    return row * (35 + t * 2 * 3 * block)


#: Bytes of the file's channels one band of rows holds as write_sh_planes converts and
#: writes it (the float32 band it is made from is twice that for half files).
WRITE_BAND_BYTES = 32 << 20
#: Band heights are whole multiples of this: the line blocks of ZIP (16) and PIZ (32).
WRITE_BAND_BLOCK = 32
#: Header attribute value types the scanline writer takes (anything else is refused
#: before the file is opened: the deprecated writer crashes on a list).
ATTRIBUTE_TYPES = (str, int, float)


def write_band_rows(channels: int, width: int, half: bool) -> int:
    """Rows of one band write_sh_planes writes at a time: WRITE_BAND_BYTES of
    the file's channels, in whole WRITE_BAND_BLOCK-row blocks (at least one)."""
    per_row = max(1, int(channels) * int(width) * (2 if half else 4))
    return max(1, WRITE_BAND_BYTES // per_row // WRITE_BAND_BLOCK) * WRITE_BAND_BLOCK


def _legacy_header(width: int, height: int, names: list[str], half: bool, kind: str, attrs: dict):
    """The scanline writer's header: the same attributes, in the same file
    bytes, as ``OpenEXR.File`` writes for the header dict write_sh_planes made
    (checked by tests/test_exr_write.py against a whole-file write)."""
    import Imath
    import OpenEXR
    h = OpenEXR.Header(int(width), int(height))
    pt = Imath.PixelType(Imath.PixelType.HALF if half else Imath.PixelType.FLOAT)
    h["channels"] = {n: Imath.Channel(pt) for n in names}
    h["compression"] = Imath.Compression(int(compression_of(kind)))
    h["type"] = b"scanlineimage"
    for k, v in attrs.items():
        # str is written as bytes by the scanline API; bool and numpy scalars are converted by the caller.
        h[k] = v.encode("utf-8") if isinstance(v, str) else v
    return h


def write_sh_planes(path, planes, *, kind: str, half: bool = True,
                    rgb: bool = False, attrs: dict | None = None, atomic: bool = True,
                    executor=None, rng: tuple[float, float] | None = None,
                    names: list[str] | None = None, bands: int | None = None,
                    mantissa_bits: int = HALF_MANTISSA_BITS, full_bits=None, consume: bool = False,
                    visit=None) -> str:
    """Write an SH texture from channel-first ``planes`` (C, H, W), row 0 at the bottom.

    C = K for kind "transfer", 3K when ``rgb`` (bounce; R.sh000.., G.., B..).
    half : store float16 (the caller checks :func:`half_overflow` first).
    attrs : extra header attributes (str/int/float); keys get a
            ``prtt_`` prefix if they lack one.
    rng : the planes' :func:`value_range`, if the caller has it.
    names, bands : the channel names and the header's band count, for layouts
            other than C = K or 3K (relightable bounces: relight_channel_names).
    mantissa_bits : half storage of the coefficients of bands l >= 1 rounded to
            this many mantissa bits (:func:`quantize_half`; the DC channels keep
            all 10); the header records it as ``prtt_mantissa_bits``.
    full_bits : with ``names``, one bool per channel: which keep all 10 bits
            under ``mantissa_bits`` (the layout's DC-to-DC channels; relight_full_bits).
    consume : ``planes`` (a C-contiguous array the caller is done with) gives
            each band's pages back to the OS once it is written
            (base/memory.discard_pages), so the float32 texture shrinks as the
            file grows; the planes read as zeros afterwards. The bytes written
            are the same.
    visit : called as visit(y0, band) with each band of float32 planes
            (C, rows, W), rows y0.. (row 0 at the bottom), before it is
            converted (and, with ``consume``, given back): what else the
            caller takes of the planes on the way.
    ``planes`` may instead be made a band of rows at a time: an object with
    ``shape`` (C, H, W) and ``band(y0, y1)`` -> (C, y1 - y0, W) float32
    (texels.dilate.DilatedRows, the relightable bounce's spilled columns),
    given with its ``rng``.

    The file is written a band of rows at a time (write_band_rows: 32 MiB of
    its channels) through OpenEXR's scanline writer: only one band of the
    file's channels is ever in memory, where the whole-file API held all of
    them (#35); the bytes are the same as that API's.
    Returns the path written.
    """
    import OpenEXR

    # ZIP compression runs on OpenEXR's thread pool (~1.6x faster on 2 cores); its
    # line buffers grow with the threads (writer_bytes), so at most WRITE_THREADS.
    OpenEXR.set_global_thread_count(write_threads())
    made = hasattr(planes, "band")         # planes made a band at a time
    if made and rng is None:
        raise ValueError("planes made a band at a time need their value range (rng)")
    a = planes if made else np.asarray(planes)
    if len(a.shape) != 3:
        raise ValueError(f"SH planes must be (C, H, W), got {a.shape}")
    custom_names = names is not None
    if names is not None:
        if len(names) != a.shape[0] or bands is None:
            raise ValueError(f"{len(names)} channel names (and the bands) for {a.shape[0]} planes")
    else:
        K = a.shape[0] // 3 if rgb else a.shape[0]
        if rgb and a.shape[0] != 3 * K:
            raise ValueError(f"RGB SH planes need 3K channels, got {a.shape[0]}")
        bands = bands_of(K)
        names = channel_names(K, rgb)
    rng = rng if rng is not None else value_range(a, executor)
    check_finite(a, os.fspath(path), rng)
    if half and (made and not (-HALF_MAX <= rng[0] and rng[1] <= HALF_MAX) or not made and half_overflow(a, rng)):
        raise ValueError("values exceed the half-float range; write float32")
    dtype = np.float16 if half else np.float32
    C, H, W = (int(v) for v in a.shape)
    lossy = half and mantissa_bits < HALF_MANTISSA_BITS
    K = bands * bands
    if custom_names:
        if lossy and (full_bits is None or len(full_bits) != len(names)):
            raise ValueError("mantissa_bits with custom channel names needs full_bits, one per channel")
        exact = [bool(f) for f in full_bits] if lossy else None
    else:
        exact = [c % K == 0 for c in range(len(names))]
    header = {
        "prtt_format_version": TEXTURE_FORMAT_VERSION,
        "prtt_kind": kind,
        "prtt_bands": bands,
        "prtt_convention": CONVENTION,
        "prtt_resolution": f"{W}x{H}",
        "prtt_storage": "half" if half else "float",
    }
    if lossy:
        header["prtt_mantissa_bits"] = int(mantissa_bits)
    for k, v in (attrs or {}).items():
        key = k if k.startswith("prtt_") else "prtt_" + k
        if isinstance(v, (bool, np.bool_)):
            v = int(v)
        elif isinstance(v, np.integer):
            v = int(v)
        elif isinstance(v, np.floating):
            v = float(v)
        if not isinstance(v, ATTRIBUTE_TYPES):
            raise TypeError(f"header attribute {key}: {type(v).__name__} is not one of str, int, float")
        header[key] = v
    legacy = _legacy_header(W, H, names, half, kind, header)
    consume = consume and not made and a.flags.c_contiguous
    mapper = executor.map if executor is not None else map
    step = write_band_rows(C, W, half)

    def convert(src, c):
        # Rows flipped to file order (top first); each channel contiguous (the writer reads raw bytes).
        plane = np.ascontiguousarray(src[c, ::-1], dtype=dtype)
        return quantize_half(plane, mantissa_bits) if lossy and not exact[c] else plane

    def write(out):
        f = OpenEXR.OutputFile(out, legacy)
        ok = False
        try:
            for f0 in range(0, H, step):
                f1 = min(H, f0 + step)
                y0, y1 = H - f1, H - f0             # the band's rows, bottom-up
                src = a.band(y0, y1) if made else a[:, y0:y1]
                if visit is not None:
                    visit(y0, src)
                conv = list(mapper(convert, [src] * C, range(C)))
                f.writePixels({n: memoryview(p) for n, p in zip(names, conv)}, f1 - f0)
                conv = src = None
                if consume:
                    for c in range(C):
                        discard_pages(a[c, y0:y1])
            ok = True
        finally:
            if ok:
                f.close()
            else:
                # A cancelled or failed write: the caller's (atomic) file is discarded; the
                # writer's own complaint about missing lines must not hide the cause.
                with contextlib.suppress(Exception):
                    f.close()

    path = os.fspath(path)
    if atomic:
        with atomic_write(path) as tmp:
            write(tmp)
    else:
        write(path)
    return path


def write_sh_exr(path, data: np.ndarray, *, kind: str, half: bool = True,
                 rgb: bool = False, attrs: dict | None = None, atomic: bool = True) -> str:
    """Write an SH texture given pixel-major data: (H, W, K), or (H, W, 3, K)
    when ``rgb``; row 0 at the bottom. See :func:`write_sh_planes`."""
    a = np.asarray(data)
    if rgb:
        if a.ndim != 4 or a.shape[2] != 3:
            raise ValueError(f"RGB SH texture must be (H, W, 3, K), got {a.shape}")
        planes = a.reshape(a.shape[0], a.shape[1], -1)
    else:
        if a.ndim != 3:
            raise ValueError(f"SH texture must be (H, W, K), got {a.shape}")
        planes = a
    return write_sh_planes(path, np.moveaxis(planes, 2, 0), kind=kind, half=half, rgb=rgb,
                           attrs=attrs, atomic=atomic)


#: Channels a texture file may declare: the largest relightable texture PRTT
#: writes, 16 bands with 16-band glossy rows per colour (3 K + 3 (K - 1) K, K = 256).
MAX_FILE_CHANNELS = 3 * 256 + 3 * 255 * 256


def checked_header(path: str, decoded: int | None = None) -> tuple[dict, int, int]:
    """The header of the EXR at ``path``, read without its pixels and checked
    before anything is decoded: a PRTT texture (prtt_bands, prtt_kind), a
    data window of 1..MAX_FILE_SIDE texels a side, at most MAX_FILE_CHANNELS
    channels, none subsampled, and pixels that fit in the memory available once decoded (a
    small damaged file may declare a huge window: OpenEXR would allocate and
    fill it; ``decoded``: how many channels the caller decodes, default all,
    at their stored size, plus a float32 copy of each). Returns (header, H,
    W). TextureError otherwise, naming the file."""
    import OpenEXR

    if not os.path.isfile(path):
        raise TextureError(f"{path}: no such texture")
    try:
        with OpenEXR.File(path, header_only=True) as hf:
            header = dict(hf.header())
    except Exception as exc:
        raise TextureError(f"{path}: unreadable EXR ({exc})") from exc
    if "prtt_bands" not in header or "prtt_kind" not in header:
        raise TextureError(f"{path}: not a PRTT texture (no prtt_bands/prtt_kind header)")
    box = header.get("dataWindow")
    try:
        (x0, y0), (x1, y1) = (int(v) for v in box[0]), (int(v) for v in box[1])
    except (TypeError, ValueError, IndexError) as exc:
        raise TextureError(f"{path}: unreadable EXR (data window {shown(box)})") from exc
    H, W = y1 - y0 + 1, x1 - x0 + 1
    if not (0 < H <= MAX_FILE_SIDE and 0 < W <= MAX_FILE_SIDE):
        raise TextureError(f"{path}: a {W}x{H} texture; PRTT writes 1..{MAX_FILE_SIDE} texels a side")
    chans = header.get("channels") or []
    if len(chans) > MAX_FILE_CHANNELS:
        raise TextureError(f"{path}: {len(chans)} channels; a PRTT texture has at most {MAX_FILE_CHANNELS}")
    try:
        # OpenEXR's binding decodes a name when it is read: a damaged one is not UTF-8
        names = [str(getattr(c, "name", "?")) for c in chans]
    except UnicodeDecodeError as exc:
        raise TextureError(f"{path}: a channel name is not UTF-8 text (byte {exc.object[exc.start]:#04x}); "
                           f"not a texture PRTT wrote") from None
    sub = [n for n, c in zip(names, chans) if (getattr(c, "xSampling", 1), getattr(c, "ySampling", 1)) != (1, 1)]
    if sub:
        raise TextureError(f"{path}: channels {sub[:4]} are subsampled; PRTT textures have every channel at "
                           f"full resolution")
    n = len(chans) if decoded is None else decoded
    try:
        check_fits(6 * H * W * max(1, n), f"reading {path} ({W}x{H}, {n} channels)")
    except MemoryLimitError as exc:
        raise TextureError(str(exc)) from None
    return header, H, W


#: The child that decodes one channel with OpenEXR's legacy InputFile (argv: path, channel).
_DC_CHILD = ("import sys, Imath, OpenEXR\n"
             "f = OpenEXR.InputFile(sys.argv[1])\n"
             "sys.stdout.buffer.write(f.channel(sys.argv[2], Imath.PixelType(Imath.PixelType.FLOAT)))\n")
#: Seconds the child may take (a 16384² channel decodes in a few).
DC_CHILD_TIMEOUT = 300


def read_dc_plane(path) -> np.ndarray:
    """(H, W) float32, row 0 at the bottom: a PRTT transfer texture's DC
    channel ``sh000`` alone (what the add-on's AO image shows).

    OpenEXR's legacy scanline reader decodes one channel block by block (the
    full read of a 4096² texture holds 0.8 GB of half channels for it), but
    it trusts damaged files: crafted ones crashed it with a segmentation
    fault (tests/fuzz_corpus/exr). So the header is read and checked here
    with the current API, and the channel is decoded in a child process whose
    crash is a TextureError, not the end of Blender."""
    path = os.fspath(path)
    header, H, W = checked_header(path, decoded=1)
    if not any(getattr(c, "name", None) == "sh000" for c in header["channels"]):
        raise TextureError(f"{path}: missing channels ['sh000']")
    try:
        r = subprocess.run([python_executable(), "-c", _DC_CHILD, path, "sh000"], capture_output=True,
                           env=child_env(), timeout=DC_CHILD_TIMEOUT)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise TextureError(f"{path}: unreadable EXR (its decoder did not finish: {exc})") from exc
    if r.returncode != 0 or len(r.stdout) != 4 * H * W:
        how = f"crashed (signal {-r.returncode})" if r.returncode < 0 else "failed"
        tail = r.stderr.decode("utf-8", "replace").strip().splitlines()[-1:] or [""]
        raise TextureError(f"{path}: unreadable EXR (OpenEXR's decoder {how}{': ' + tail[0] if tail[0] else ''})")
    return np.frombuffer(r.stdout, np.float32).reshape(H, W)[::-1].copy()


@contextlib.contextmanager
def open_sh_channels(path):
    """A PRTT texture's channels as the file stores them, without copies:
    yields (name -> (H, W) half or float32 array, rows in file order (top
    first), attrs (``prtt_*`` headers without the prefix)), valid inside the
    block only (the binding empties them when the file closes). For readers
    that take a few channels at a time (core/preview/pack.LayerSource)."""
    import OpenEXR

    path = os.fspath(path)
    checked_header(path)
    try:
        f = OpenEXR.File(path)
    except Exception as exc:
        raise TextureError(f"{path}: unreadable EXR ({exc})") from exc
    with f:
        try:
            header = dict(f.header())
            chans = {n: c.pixels for n, c in f.channels().items()}
        except Exception as exc:
            raise TextureError(f"{path}: unreadable EXR ({exc})") from exc
        # checked_header made sure prtt_bands and prtt_kind are there.
        attrs = {k[5:]: v for k, v in header.items() if k.startswith("prtt_")}
        yield chans, attrs


def texture_header(path: str) -> tuple:
    """(channel names (set), attrs (``prtt_*`` headers without the prefix), H, W,
    bytes per stored value) of a PRTT texture, from its checked header alone
    (nothing decoded)."""
    header, H, W = checked_header(path, decoded=0)
    attrs = {k[5:]: v for k, v in header.items() if k.startswith("prtt_")}
    try:
        names = {c.name for c in header.get("channels") or []}
    except (UnicodeDecodeError, AttributeError) as exc:      # names are bytes from the file
        raise TextureError(f"{path}: unreadable EXR (its channel names: {exc})") from None
    return names, attrs, H, W, 2 if attrs.get("storage") == "half" else 4


def _read_channels(path) -> tuple[dict, dict]:
    """(name -> (H, W) array copied out of the file, attrs): :func:`open_sh_channels`'
    channels, kept after the file closes."""
    with open_sh_channels(path) as (chans, attrs):
        try:
            return {n: np.array(c, copy=True) for n, c in chans.items()}, attrs
        except Exception as exc:
            raise TextureError(f"{os.fspath(path)}: unreadable EXR ({exc})") from exc


#: The most SH bands a texture file may declare (the bake's own limit): a
#: header is untrusted input, and channel names are listed from it.
MAX_FILE_BANDS = 16
#: Texels a side a texture file may declare (the bake's own limit).
MAX_FILE_SIDE = 16384


def bands_of_header(path, attrs: dict, key: str = "bands", lo: int = 1, hi: int = MAX_FILE_BANDS) -> int:
    """The header's band count ``key`` as an int in [lo, hi], or TextureError (a header is untrusted)."""
    return _bands(path, attrs, key, lo, hi)


def _bands(path, attrs: dict, key: str, lo: int, hi: int = MAX_FILE_BANDS) -> int:
    """The header's band count ``key`` as an int in [lo, hi], or TextureError."""
    try:
        n = int(attrs.get(key, 0))
    except (TypeError, ValueError):
        n = -1
    if not lo <= n <= hi:
        raise TextureError(f"{path}: header prtt_{key} = {shown(attrs.get(key))} is not a band count "
                           f"from {lo} to {hi}")
    return n


def _stack(path, chans: dict, names: list[str]) -> np.ndarray:
    """(H, W, len(names)) float32, row 0 at the bottom."""
    missing = [n for n in names if n not in chans]
    if missing:
        raise TextureError(f"{path}: missing channels {missing[:4]}{'...' if len(missing) > 4 else ''}")
    H, W = chans[names[0]].shape
    # One pass per channel into the interleaved result, rows flipped as they
    # go (stacking, then flipping, then re-laying out made three copies of
    # what is 100 MB for a 1024² band-5 texture).
    data = np.empty((H, W, len(names)), np.float32)
    for i, n in enumerate(names):
        data[:, :, i] = chans[n][::-1]
    return data


def read_relight_exr(path, *, expand: bool = True) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """Read a relightable bounce texture (kind "relight"): (dc (H, W, 3, K),
    glossy (H, W, 3, Kg - 1, Kg) or None, attrs), float32, row 0 at the bottom.
    Shared glossy rows (``prtt_glossy_colour`` "shared") come back per colour
    (expand_shared_glossy), so every reader sees one layout; with
    ``expand=False`` they come back as stored, (H, W, Kg - 1, Kg) (the glTF
    export carries them so, and the viewer tints them as expand_shared_glossy
    does)."""
    chans, attrs = _read_channels(path)
    if attrs["kind"] != "relight":
        raise TextureError(f"{path}: a {shown(attrs['kind'])} texture, not a relightable bounce texture")
    bands = _bands(path, attrs, "bands", 1)
    K, kg = bands * bands, _bands(path, attrs, "glossy_bands", 0, bands) ** 2
    colour = attrs.get("glossy_colour", "per-colour")
    if colour not in ("per-colour", "shared"):
        raise TextureError(f"{path}: unknown prtt_glossy_colour {shown(colour)} (per-colour or shared)")
    shared = colour == "shared"
    names = relight_channel_names(K, kg, shared)
    data = _stack(path, chans, names)
    H, W = data.shape[:2]
    dc = np.ascontiguousarray(data[..., :3 * K].reshape(H, W, 3, K))
    glossy = None
    if kg and shared:
        glossy = data[..., 3 * K:].reshape(H, W, kg - 1, kg)
        glossy = expand_shared_glossy(dc, glossy) if expand else np.ascontiguousarray(glossy)
    elif kg:
        glossy = np.ascontiguousarray(data[..., 3 * K:].reshape(H, W, 3, kg - 1, kg))
    return dc, glossy, attrs


def read_sh_exr(path) -> tuple[np.ndarray, dict]:
    """Read a PRTT SH texture. Returns (data float32, attrs).

    data is (H, W, K) or (H, W, 3, K) for RGB textures, row 0 at the bottom.
    attrs holds the ``prtt_*`` header entries without the prefix.
    """
    chans, attrs = _read_channels(path)
    K = _bands(path, attrs, "bands", 1) ** 2
    rgb = any(n.startswith("R.") for n in chans)
    data = _stack(path, chans, channel_names(K, rgb))
    H, W = data.shape[:2]
    if rgb:
        data = data.reshape(H, W, 3, K)
    return data, attrs


#: The channel of a sun mask texture (kind "sun_mask", core/bake/estimators/sun_mask.py).
SUN_MASK_CHANNEL = "sun"


def write_mask_exr(path, mask: np.ndarray, *, attrs: dict | None = None, atomic: bool = True) -> str:
    """Write a sun mask, (H, W) float32 in [0, 1], row 0 at the bottom, as one
    half channel ``sun`` (kind "sun_mask", prtt_bands 1). A mask of R rays is
    made of multiples of 1 / R, which half stores exactly for R <= 2048."""
    m = np.asarray(mask, np.float32)
    if m.ndim != 2:
        raise ValueError(f"a sun mask is (H, W), got {m.shape}")
    return write_sh_planes(path, m[None], kind="sun_mask", half=True, attrs=attrs, atomic=atomic,
                           names=[SUN_MASK_CHANNEL], bands=1, full_bits=[True])


def read_mask_exr(path) -> tuple[np.ndarray, dict]:
    """(mask (H, W) float32, row 0 at the bottom, attrs) of a sun mask texture;
    TextureError for any other file."""
    chans, attrs = _read_channels(path)
    if attrs.get("kind") != "sun_mask":
        raise TextureError(f"{path}: a {shown(attrs.get('kind'))} texture, not a sun mask")
    data = _stack(path, chans, [SUN_MASK_CHANNEL])[..., 0]
    if not np.isfinite(data).all() or data.min() < 0.0 or data.max() > 1.0:
        raise TextureError(f"{path}: sun mask values outside [0, 1]")
    return data, attrs


#: Channels of a lamp mask texture: lamp i of the manifest's "lamps" in channel ``l<i>``.
LAMP_CHANNELS = ["l0", "l1", "l2", "l3"]


def write_lamp_exr(path, masks: np.ndarray, *, attrs: dict | None = None, atomic: bool = True) -> str:
    """Write a set's lamp masks, (L, H, W) float32 in [0, 1] (L <= 4: the
    visible fraction of lamp i's sphere; core.bake.estimators.lamp_mask), row
    0 at the bottom, as L half channels l0.. (kind "lamp_mask", prtt_bands 1)."""
    m = np.asarray(masks, np.float32)
    if m.ndim != 3 or not 1 <= m.shape[0] <= len(LAMP_CHANNELS):
        raise ValueError(f"lamp masks are (L, H, W) with 1 <= L <= {len(LAMP_CHANNELS)}, got {m.shape}")
    return write_sh_planes(path, m, kind="lamp_mask", half=True, attrs=attrs, atomic=atomic,
                           names=LAMP_CHANNELS[:m.shape[0]], bands=1, full_bits=[True] * m.shape[0])


def read_lamp_exr(path, lamps: int) -> tuple[np.ndarray, dict]:
    """((H, W, lamps) float32, row 0 at the bottom, attrs) of a lamp mask
    texture of ``lamps`` channels; TextureError for any other file."""
    chans, attrs = _read_channels(path)
    if attrs.get("kind") != "lamp_mask":
        raise TextureError(f"{path}: a {shown(attrs.get('kind'))} texture, not lamp masks")
    if not 1 <= lamps <= len(LAMP_CHANNELS):
        raise TextureError(f"{path}: {lamps} lamps, a mask texture holds 1 to {len(LAMP_CHANNELS)}")
    data = _stack(path, chans, LAMP_CHANNELS[:lamps])
    if not np.isfinite(data).all() or data.min() < 0.0 or data.max() > 1.0:
        raise TextureError(f"{path}: lamp mask values outside [0, 1]")
    return data, attrs


#: Channels of a sun edge texture (core.bake.estimators.sun_edge.CHANNELS).
SUN_EDGE_CHANNELS = ["d", "h", "valid"]


def write_edge_exr(path, planes: np.ndarray, *, attrs: dict | None = None, atomic: bool = True) -> str:
    """Write a sun's sub-texel shadow edges, (3, H, W) float32 (d, h in
    texels of the set, valid in [0, 1]; core.bake.estimators.sun_edge), row 0
    at the bottom, as three half channels (kind "sun_edge", prtt_bands 1)."""
    p = np.asarray(planes, np.float32)
    if p.ndim != 3 or p.shape[0] != 3:
        raise ValueError(f"sun edges are (3, H, W), got {p.shape}")
    return write_sh_planes(path, p, kind="sun_edge", half=True, attrs=attrs, atomic=atomic,
                           names=SUN_EDGE_CHANNELS, bands=1, full_bits=[True] * 3)


def read_edge_exr(path) -> tuple[np.ndarray, dict]:
    """((H, W, 3) float32 (d, h, valid), row 0 at the bottom, attrs) of a sun
    edge texture; TextureError for any other file or values out of range
    (|d| or h above 64, valid outside [0, 1], not finite)."""
    chans, attrs = _read_channels(path)
    if attrs.get("kind") != "sun_edge":
        raise TextureError(f"{path}: a {shown(attrs.get('kind'))} texture, not sun edges")
    data = _stack(path, chans, SUN_EDGE_CHANNELS)
    if not np.isfinite(data).all() or np.abs(data[..., 0]).max(initial=0.0) > 64.0 \
            or data[..., 1].min(initial=0.0) < 0.0 or data[..., 1].max(initial=0.0) > 64.0 \
            or data[..., 2].min(initial=0.0) < 0.0 or data[..., 2].max(initial=0.0) > 1.0:
        raise TextureError(f"{path}: sun edge values out of range")
    return data, attrs
