"""The ``PRTT_radiance_transfer`` glTF extension: what goes into a .glb besides
Blender's own glTF (docs/gltf.md; its JSON schema is
docs/schema/PRTT_radiance_transfer.schema.json).

The root extension holds the SH convention, the frame, the light, the
display (exposure, view transform), the World's environment (its image file
in a buffer view) and one entry per texture set; each set's transfer planes
(and bounce textures: relightable DC and glossy rows, or baked bounce light)
travel as KTX2 2D array textures (core/io/ktx2.py: RGBA16F, four SH
coefficients per layer) in buffer views of the .glb. A node names its texture
set, a mesh primitive the TEXCOORD set that holds its PRTT UVs, a material
the parameters the preview shades it with.

Frame: the textures and the light are in Blender's world frame (Z up), as
baked. glTF is Y up: Blender's exporter writes (x, y, z) as (x, z, -y). A
viewer turns a glTF world direction d into the bake frame with
``gltfToBakeFrame`` (d_bake = M d) before evaluating the SH basis.
"""
from __future__ import annotations

import json
import os
import struct

import numpy as np

from ..shading.display import LUT_ENCODING
from .exr_bands import channel_groups, read_layers
from .exr_io import TextureError, bands_of_header, channel_names, relight_channel_names, texture_header
from .ktx2 import ktx2_bytes, sh_layers

NAME = "PRTT_radiance_transfer"
#: Zstandard level of the payloads: on the demo's 1024^2 transfer, level 3
#: writes 26.7 MB in 0.44 s where level 10 writes 25.9 MB in 3.1 s (half
#: floats barely compress further; the export's time was mostly zstd).
ZSTD_LEVEL = 3
VERSION = 1
#: glTF world direction -> Blender world direction (the inverse of the
#: exporter's Y-up conversion (x, y, z) -> (x, z, -y)).
GLTF_TO_BAKE_FRAME = ((1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0))


#: The largest JSON chunk :func:`read_glb_json` reads (the JSON of a glb PRTT
#: writes is a few hundred KB; the textures are in the binary chunk).
MAX_GLB_JSON_BYTES = 64 << 20


def read_glb_json(path) -> dict:
    """The JSON chunk of the .glb at ``path``. ValueError (naming the file)
    when it is not a .glb whose first chunk is a JSON object, or that chunk
    is over MAX_GLB_JSON_BYTES, truncated or not JSON."""
    with open(path, "rb") as f:
        head = f.read(20)
        if len(head) < 20:
            raise ValueError(f"{path}: not a .glb (shorter than its header)")
        magic, _, _, n, kind = struct.unpack("<4sIIII", head)
        if magic != b"glTF" or kind != 0x4E4F534A:
            raise ValueError(f"{path}: not a .glb with a JSON chunk first")
        if n > MAX_GLB_JSON_BYTES:
            raise ValueError(f"{path}: a {n}-byte JSON chunk, over {MAX_GLB_JSON_BYTES}")
        data = f.read(n)
    if len(data) != n:
        raise ValueError(f"{path}: its JSON chunk is cut short")
    try:
        doc = json.loads(data)
    except (ValueError, RecursionError) as exc:       # UnicodeDecodeError and JSONDecodeError are ValueErrors
        raise ValueError(f"{path}: its JSON chunk is not JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: its JSON chunk is a {type(doc).__name__}, not a glTF object")
    return doc


def transfer_payload(planes: np.ndarray, *, supercompression: str = "zstd",
                     encoding: str = "half") -> tuple[bytes, dict]:
    """A set's transfer planes (K, H, W), rows top first, as KTX2 bytes and
    the JSON that describes them (coefficients, layers, the half-float error)."""
    K = planes.shape[0]
    return _payload(sh_layers(np.asarray(planes, np.float32)), "transfer", K, supercompression, encoding)


#: The payload encodings: "half" RGBA16F, the SH values themselves (lossless
#: against the half EXRs); "u8" RGBA8, each plane (layer, channel) its own
#: ``offset`` + ``scale`` * q, q = 0 .. 255 (a quarter of the raw bytes,
#: error at most scale / 2 per plane, measured and written as ``maxError``).
ENCODINGS = ("half", "u8")


def encode_u8(layers: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(L, H, W, 4) floats -> (uint8 layers, scale (4 L,), offset (4 L,)):
    plane p = 4 * layer + channel decodes as offset[p] + scale[p] * q. A
    constant plane gets scale 0 (q = 0)."""
    a = np.asarray(layers, np.float32)
    L = a.shape[0]
    # Plane by plane: a transposed copy of the layers would double them.
    lo = np.array([a[p // 4, :, :, p % 4].min() for p in range(4 * L)], np.float64)
    hi = np.array([a[p // 4, :, :, p % 4].max() for p in range(4 * L)], np.float64)
    scale = (hi - lo) / 255.0
    q = np.zeros(a.shape, np.uint8)
    for p in range(4 * L):                   # one plane at a time: no float64 copy of the whole payload
        if scale[p] > 0:
            q[p // 4, :, :, p % 4] = np.clip(np.rint((a[p // 4, :, :, p % 4] - lo[p]) / scale[p]), 0, 255)
    return q, scale, lo


def decode_u8(q: np.ndarray, scale, offset) -> np.ndarray:
    """The float32 values (L, H, W, 4) of :func:`encode_u8`'s planes."""
    s = np.asarray(scale, np.float64).reshape(-1, 4)[:, None, None, :]
    o = np.asarray(offset, np.float64).reshape(-1, 4)[:, None, None, :]
    return (o + s * q).astype(np.float32)


def _payload(layers: np.ndarray, kind: str, K: int, supercompression: str, encoding: str = "half",
             **meta) -> tuple[bytes, dict]:
    """(layers, H, W, 4) as KTX2 bytes in ``encoding`` and the JSON every payload carries."""
    if encoding not in ENCODINGS:
        raise ValueError(f"encoding must be one of {', '.join(ENCODINGS)}, got {encoding!r}")
    L, H, W = layers.shape[:3]
    extra = {}
    if encoding == "u8":
        q, scale, offset = encode_u8(layers)
        err = max((float(np.abs(decode_u8(q[i:i + 1], scale[4 * i:4 * i + 4], offset[4 * i:4 * i + 4])
                                - np.asarray(layers[i:i + 1], np.float32)).max()) for i in range(L)), default=0.0)
        extra = {"encoding": "u8", "scale": scale.tolist(), "offset": offset.tolist(), "maxError": err}
        stored, fmt = q, "RGBA8"
    else:
        stored, fmt = layers, "RGBA16F"
    blob, level_bytes = ktx2_bytes([stored], supercompression=supercompression, zstd_level=ZSTD_LEVEL,
                                   keys={"PRTTkind": kind, "PRTTcoefficients": str(K)})
    return blob, {"coefficients": int(K), **meta, "layers": int(L), "width": int(W), "height": int(H),
                  "format": fmt, "supercompression": supercompression, "bytes": len(blob),
                  "uncompressedBytes": int(level_bytes[0][1]), **extra}


def _row_layers(rows: np.ndarray) -> np.ndarray:
    """(R, K, H, W) rows of K coefficients each as (R * ceil(K / 4), H, W, 4)
    layers: row r from layer r * ceil(K / 4), coefficient i in layer i // 4,
    channel i % 4 of them."""
    return np.concatenate([sh_layers(np.asarray(r, np.float32)) for r in rows])


def relight_dc_payload(dc: np.ndarray, *, supercompression: str = "zstd",
                       encoding: str = "half") -> tuple[bytes, dict]:
    """A set's relightable bounce, its DC rows (3, K, H, W): colour c's row over
    light coefficient i, rows top first, as KTX2 bytes (colour c's rows from
    layer c * ceil(K / 4), coefficient i in layer i // 4, channel i % 4 of
    them) and their JSON. The bounce's diffuse radiance under a light L is
    sqrt(4 pi) * sum_i DC_c,i L_c,i per colour c (docs/shading.md)."""
    return _dc_payload(_row_layers(dc), dc.shape[0], dc.shape[1], supercompression, encoding)


def _dc_payload(layers, C: int, K: int, supercompression: str, encoding: str) -> tuple[bytes, dict]:
    return _payload(layers, "relight-dc", K, supercompression, encoding, colours=int(C),
                    layersPerColour=int(layers.shape[0] // C))


def relight_glossy_payload(glossy: np.ndarray, K: int, *, supercompression: str = "zstd",
                           encoding: str = "half") -> tuple[bytes, dict]:
    """A set's relightable bounce, its glossy rows, as KTX2 bytes and their
    JSON, rows top first, in one of the EXRs' two layouts:

    * per colour, (3, Kg - 1, Kg, H, W): for colour c and out coefficient
      o = 1 .. Kg - 1 the row over light coefficient i: the tail of
      core.preview.pack.pack_relight_operator after its DC layers, row (c, o)
      from layer (c * (Kg - 1) + o - 1) * ceil(Kg / 4), coefficient i in layer
      i // 4, channel i % 4 of them (``glossyColour`` "per-colour");
    * shared, (Kg - 1, Kg, H, W): one set of rows for every colour, row o from
      layer (o - 1) * ceil(Kg / 4) (``glossyColour`` "shared", a third of the
      bytes); colour c's rows are kappa_c times them, kappa_c = DC_c,0 /
      mean_c DC_c,0 per texel (1 where that mean is below 1e-3 of the largest
      colour's magnitude): core.io.exr_io.expand_shared_glossy.

    The bounce's SH coefficient o (1 .. Kg - 1) under a light L is
    sum_i G_c,o,i L_c,i (core.shading.relit.apply_light; coefficient 0 is the
    DC rows' sum). ``K``: the bake's coefficients."""
    g = np.asarray(glossy)
    shared = g.ndim == 4
    if shared:
        g = g[None]
    C, O, Kg = g.shape[:3]
    if O != Kg - 1 or C not in (1, 3):
        raise ValueError(f"glossy rows: expected (3, Kg - 1, Kg, H, W) or (Kg - 1, Kg, H, W), got {glossy.shape}")
    return _glossy_payload(_row_layers(g.reshape(C * O, Kg, *g.shape[3:])), shared, Kg, K, supercompression,
                           encoding)


def _glossy_payload(layers, shared: bool, Kg: int, K: int, supercompression: str,
                    encoding: str) -> tuple[bytes, dict]:
    return _payload(layers, "relight-glossy", K, supercompression, encoding, colours=3,
                    glossyColour="shared" if shared else "per-colour",
                    glossyBands=int(round(Kg ** 0.5)), glossyCoefficients=int(Kg),
                    layersPerRow=int((Kg + 3) // 4))


def bounce_payload(bounce: np.ndarray, levels: int, *, supercompression: str = "zstd",
                   encoding: str = "half") -> tuple[bytes, dict]:
    """A set's baked bounce light (3, K, H, W), its levels summed, rows top
    first, as KTX2 bytes and their JSON (core.preview.pack.pack_bounce's
    layout: colour c's coefficient k in layer c * ceil(K / 4) + k // 4,
    channel k % 4). The bounce radiance's SH coefficients, added to the
    incident light before shading (docs/shading.md)."""
    return _bounce_payload(_row_layers(bounce), bounce.shape[0], bounce.shape[1], levels, supercompression,
                           encoding)


def _bounce_payload(layers, C: int, K: int, levels: int, supercompression: str,
                    encoding: str) -> tuple[bytes, dict]:
    return _payload(layers, "bounce", K, supercompression, encoding, colours=int(C),
                    layersPerColour=int(layers.shape[0] // C), levels=int(levels))


# --- payloads read from the bake's files ------------------------------------------------
#
# The same bytes as the functions above on the arrays exr_io reads, made
# from the files' channels a band of rows at a time (exr_bands: decoded in a
# child): what this process holds is the payload's layers (half floats, or
# float32 for "u8") and one band, instead of the whole texture as float32,
# its transposed copy, its padded layers and their bytes (a 2048²
# relightable set's export peaked at 21.6 GB that way).

def _row_groups(names: list, rows: int, per_row: int) -> list:
    """exr_bands.channel_groups of each of ``rows`` consecutive rows of
    ``per_row`` names (_row_layers' layout)."""
    return [g for r in range(rows) for g in channel_groups(names[r * per_row:(r + 1) * per_row])]


def _layer_dtype(encoding: str):
    return np.float32 if encoding == "u8" else np.float16


def _file_plan(path: str) -> tuple[int, int, set, list]:
    """(H, W, the channels the file has, [(payload key, its layers' channel
    groups, a function (layers, supercompression, encoding) -> (blob,
    meta))]) of a bake texture, from its checked header alone."""
    have, attrs, H, W, _ = texture_header(path)
    K = bands_of_header(path, attrs) ** 2
    if attrs["kind"] != "relight":
        return H, W, have, [("transfer", channel_groups(channel_names(K)),
                             lambda lay, sc, enc: _payload(lay, "transfer", K, sc, enc))]
    kg = bands_of_header(path, attrs, "glossy_bands", 0, int(round(K ** 0.5))) ** 2
    colour = attrs.get("glossy_colour", "per-colour")
    if colour not in ("per-colour", "shared"):
        raise TextureError(f"{path}: unknown prtt_glossy_colour {colour!r:.40} (per-colour or shared)")
    shared = colour == "shared"
    names = relight_channel_names(K, kg, shared)
    plan = [("relightDC", _row_groups(names, 3, K), lambda lay, sc, enc: _dc_payload(lay, 3, K, sc, enc))]
    if kg:
        rows = (1 if shared else 3) * (kg - 1)
        plan.append(("relightGlossy", _row_groups(names[3 * K:], rows, kg),
                     lambda lay, sc, enc: _glossy_payload(lay, shared, kg, K, sc, enc)))
    return H, W, have, plan


#: Bytes a payload value costs while it is made, by encoding: the layers
#: (half floats; "u8": float32 and the 8-bit copy) and the compressed bytes
#: beside them (:data:`STORED_BYTES`).
MAKING_BYTES = {"half": 2 + 2.02, "u8": 4 + 1 + 1.01}
#: Bytes a payload value costs at most once compressed: the stored value and
#: 1 % for data zstd cannot compress.
STORED_BYTES = {"half": 2.02, "u8": 1.01}


def file_payload_values(path) -> int:
    """Values (layers x 4 x H x W) of the payloads :func:`file_payloads` makes
    of the texture at ``path``, from its checked header alone."""
    H, W, _, plan = _file_plan(os.fspath(path))
    return sum(len(groups) for _, groups, _ in plan) * 4 * H * W


def file_payloads(path, encoding: str = "half", supercompression: str = "zstd") -> dict:
    """{"transfer": (blob, meta)} of a transfer texture, or {"relightDC": ...,
    "relightGlossy": ...} of a relightable bounce texture, from its file:
    the bytes :func:`transfer_payload`, :func:`relight_dc_payload` and
    :func:`relight_glossy_payload` make of what read_sh_exr /
    read_relight_exr(expand=False) return, rows top first."""
    if encoding not in ENCODINGS:
        raise ValueError(f"encoding must be one of {', '.join(ENCODINGS)}, got {encoding!r}")
    path = os.fspath(path)
    H, W, have, plan = _file_plan(path)
    out = {}
    for key, groups, make in plan:
        missing = [n for g in groups for n in g if n is not None and n not in have]
        if missing:
            raise TextureError(f"{path}: missing channels {missing[:4]}{'...' if len(missing) > 4 else ''}")
        out[key] = make(read_layers(path, groups, H, W, dtype=_layer_dtype(encoding), error=TextureError),
                        supercompression, encoding)
    return out


def _bounce_plan(paths: list, K: int) -> tuple[int, int, list] | int:
    """(H, W, [(path, channel groups)]) of baked bounce levels summed to K
    coefficients (a band-limited level padded with zeros, as
    PreviewSet.load_bounce pads it), or the coefficients a level holds
    instead of K (left out of the glTF)."""
    H = W = None
    plan = []
    for p in paths:
        _, attrs, h, w, _ = texture_header(p)
        k = bands_of_header(p, attrs) ** 2
        if k != K and not (attrs.get("band_limited") and k < K):
            return k
        if H is not None and (h, w) != (H, W):
            raise TextureError(f"{p}: bounce level of {w}x{h} texels does not match the others' {W}x{H}")
        H, W = h, w
        names = channel_names(K, rgb=True)
        held = set(channel_names(k, rgb=True))
        plan.append((p, _row_groups([n if n in held else None for n in names], 3, K)))
    return H, W, plan


def bounce_files_values(paths: list, K: int) -> int:
    """Values of :func:`bounce_files_payload`'s payload (0 when it is left
    out); while it is made it also holds 8 bytes a value (the float32 sum and
    one level's float32 layers)."""
    plan = _bounce_plan([os.fspath(p) for p in paths], K)
    if isinstance(plan, int):
        return 0
    H, W, levels = plan
    return len(levels[0][1]) * 4 * H * W


def bounce_files_payload(paths: list, K: int, encoding: str = "half",
                         supercompression: str = "zstd") -> tuple[bytes, dict] | int:
    """:func:`bounce_payload` of the baked bounce levels ``paths`` summed in
    order (PreviewSet.load_bounce's float32 sum), from their files, or the
    coefficients a level holds when it is not K."""
    if encoding not in ENCODINGS:
        raise ValueError(f"encoding must be one of {', '.join(ENCODINGS)}, got {encoding!r}")
    plan = _bounce_plan([os.fspath(p) for p in paths], K)
    if isinstance(plan, int):
        return plan
    H, W, levels = plan
    total = None
    for p, groups in levels:
        layers = read_layers(p, groups, H, W, dtype=np.float32, error=TextureError)
        if total is None:
            total = layers
        else:
            total += layers
            del layers
    if encoding == "half":
        total = total.astype(np.float16)
    return _bounce_payload(total, 3, K, len(levels), supercompression, encoding)


#: The sun mask's payload format: R8 UNORM, q / 255 the visible fraction of
#: the disc (the mask's own steps are 1 / SUN_RAYS = 1/256: 8 bits hold them
#: with at most 1/510 of rounding; a filtered edge texel rounds as any other).
SUN_MASK_FORMAT = "R8"
#: With sub-texel edges (core.bake.estimators.sun_edge): RGBA16F, the very
#: halves Blender's preview uploads (prtt_shade.glsl sun_visible): r the mask,
#: g the distance d to the edge's line and a the penumbra's half-width h, both
#: in texels, b = 1 where the line holds. Not 8 bits: h is as small as 0.05
#: texel for a 0.5 degree sun near its occluder, where a step of d of
#: 4/255 texel would move the drawn fraction by a tenth.
SUN_EDGE_FORMAT = "RGBA16F"


def sun_payload(mask: np.ndarray, edges: np.ndarray | None = None, *,
                supercompression: str = "zstd") -> tuple[bytes, dict]:
    """A set's sun mask (H, W) in [0, 1], rows top first, as a one-layer R8
    KTX2 (q = round(255 mask)) and its JSON: width, height, format, bytes and
    ``maxError``, the largest |q / 255 - mask| (at most 1/510). With
    ``edges`` (H, W, 3) (d, h, valid; core.bake.estimators.sun_edge), rows
    top first: one RGBA16F KTX2 of (mask, d, valid, h) (SUN_EDGE_FORMAT),
    ``maxError`` then the mask's half rounding."""
    m = np.asarray(mask, np.float32)
    if m.ndim != 2:
        raise ValueError(f"a sun mask is (H, W), got {m.shape}")
    if not (np.isfinite(m).all() and m.min(initial=0.0) >= 0.0 and m.max(initial=0.0) <= 1.0):
        raise ValueError("a sun mask holds fractions 0 to 1")
    H, W = m.shape
    if edges is None:
        q = np.rint(m * 255.0).astype(np.uint8)
        err = float(np.abs(q.astype(np.float64) / 255.0 - m).max(initial=0.0))
        texels, kind, fmt = q[None, :, :, None], "sun_mask", SUN_MASK_FORMAT
    else:
        e = np.asarray(edges, np.float32)
        if e.shape != (H, W, 3) or not np.isfinite(e).all():
            raise ValueError(f"sun edges are finite (H, W, 3) beside an (H, W) mask, got {e.shape}")
        with np.errstate(over="ignore"):          # an overflow is refused just below
            texels = np.stack([m, e[..., 0], e[..., 2], e[..., 1]], axis=-1).astype(np.float16)
        if not np.isfinite(texels).all():
            raise ValueError("sun edges beyond a half float's range")
        err = float(np.abs(texels[..., 0].astype(np.float64) - m).max(initial=0.0))
        texels, kind, fmt = texels[None], "sun_mask_edges", SUN_EDGE_FORMAT
    blob, level_bytes = ktx2_bytes([texels], supercompression=supercompression,
                                   zstd_level=ZSTD_LEVEL, keys={"PRTTkind": kind})
    return blob, {"layers": 1, "width": int(W), "height": int(H), "format": fmt,
                  "supercompression": supercompression, "bytes": len(blob),
                  "uncompressedBytes": int(level_bytes[0][1]), "maxError": err}


def sun_extension(*, name: str, direction, angle: float, color, strength: float) -> dict:
    """The root's ``sun`` (core.light.sun.Sun's conventions, the bake frame):
    ``direction`` unit towards the sun (its mask was baked for it), ``angle``
    the disc's full angle (radians), linear ``color`` and ``strength`` (W/m²),
    ``irradiance`` = strength * color (facing the sun). A set's ``sun``
    payload is its shadow: the visible fraction of the disc per texel."""
    d = np.asarray(direction, np.float64)
    c = np.asarray(color, np.float64)
    return {"name": str(name), "direction": d.round(12).tolist(), "angle": float(angle),
            "color": c.round(9).tolist(), "strength": float(strength),
            "irradiance": (float(strength) * c).round(9).tolist()}


#: The lamps' masks' payload format: RGBA8 UNORM, channel i lamp i of the
#: root's ``lamps``, q / 255 the visible fraction of its sphere (steps of
#: 1/64: 8 bits hold them within 1/510); unused channels 0.
LAMP_MASK_FORMAT = "RGBA8"


def lamp_payload(masks: np.ndarray, *, supercompression: str = "zstd") -> tuple[bytes, dict]:
    """A set's lamp masks (H, W, L), 1 <= L <= 4, in [0, 1], rows top first,
    as a one-layer RGBA8 KTX2 (LAMP_MASK_FORMAT) and its JSON: width, height,
    format, ``lamps`` L, bytes and ``maxError`` (the largest rounding)."""
    m = np.asarray(masks, np.float32)
    if m.ndim != 3 or not 1 <= m.shape[2] <= 4:
        raise ValueError(f"lamp masks are (H, W, L) with 1 <= L <= 4, got {m.shape}")
    if not (np.isfinite(m).all() and m.min(initial=0.0) >= 0.0 and m.max(initial=0.0) <= 1.0):
        raise ValueError("lamp masks hold fractions 0 to 1")
    H, W, L = m.shape
    q = np.zeros((H, W, 4), np.uint8)
    q[..., :L] = np.rint(m * 255.0).astype(np.uint8)
    err = float(np.abs(q[..., :L].astype(np.float64) / 255.0 - m).max(initial=0.0))
    blob, level_bytes = ktx2_bytes([q[None]], supercompression=supercompression, zstd_level=ZSTD_LEVEL,
                                   keys={"PRTTkind": "lamp_mask"})
    return blob, {"layers": 1, "width": int(W), "height": int(H), "format": LAMP_MASK_FORMAT, "lamps": int(L),
                  "supercompression": supercompression, "bytes": len(blob),
                  "uncompressedBytes": int(level_bytes[0][1]), "maxError": err}


def lamps_extension(lamps) -> list:
    """The root's ``lamps`` (core.light.lamp.Lamp's conventions, the bake
    frame, in the masks' channel order): kind, name, position (m), radius
    (m), power (W), linear color, intensity (W/sr: power color / 4 pi),
    axis (a spot's unit direction of shining), spotSize (its full cone
    angle, radians) and spotBlend."""
    return [{"name": lp.name, "kind": lp.kind, "position": np.round(lp.position, 9).tolist(),
             "radius": float(lp.radius), "power": float(lp.power), "color": np.round(lp.color, 9).tolist(),
             "intensity": np.round(lp.intensity, 9).tolist(), "axis": np.round(lp.axis, 12).tolist(),
             "spotSize": float(lp.spot_size), "spotBlend": float(lp.spot_blend)} for lp in lamps]


#: Bytes a lamp texel costs at most while its payload is made (lamp_payload):
#: four float32 masks read, their 8 bits, the RGBA8 texels and their KTX2.
LAMP_MAKING_BYTES = 16 + 4 + 4 + 4.04

#: Bytes a sun texel costs at most while its payload is made (sun_payload):
#: the mask read (float32) and its 8 bits and their KTX2; with edges the
#: three planes read (float32), the RGBA16F stack and its KTX2.
SUN_MAKING_BYTES = {False: 4 + 1 + 1.01, True: 4 + 12 + 8 + 8.08}


def set_payload_bytes(transfer, relight, bounces: list, K: int, encoding: str = "half",
                      sun: tuple | None = None, lamps: str | None = None) -> int:
    """Bytes one texture set's payloads hold at most while they are made
    (:func:`file_payloads` of ``transfer`` and ``relight``, or
    :func:`bounce_files_payload` of ``bounces``), from the files' headers
    alone: the largest payload's layers and compressed bytes
    (:data:`MAKING_BYTES` a value; a baked bounce's float32 sum and level, 8
    more) and the set's other payloads' compressed bytes (at most
    :data:`STORED_BYTES` a value). ``sun`` (mask file, edge file or None):
    its payload's making (:data:`SUN_MAKING_BYTES` a texel) and stored
    bytes, from the mask's header; ``lamps`` (the lamp mask file or None) the
    same with LAMP_MAKING_BYTES. The band exr_bands holds is checked when
    it starts."""
    values = [file_payload_values(p) for p in (transfer, relight) if p]
    bounce = bounce_files_values(bounces, K) if bounces else 0
    making = [v * MAKING_BYTES[encoding] for v in values] + [bounce * (8 + MAKING_BYTES[encoding])]
    stored = (sum(values) + bounce) * STORED_BYTES[encoding]
    if sun:
        H, W = texture_header(os.fspath(sun[0]))[2:4]
        making.append(H * W * SUN_MAKING_BYTES[bool(sun[1])])
        stored += H * W * (8.08 if sun[1] else 1.01)
    if lamps:
        H, W = texture_header(os.fspath(lamps))[2:4]
        making.append(H * W * LAMP_MAKING_BYTES)
        stored += H * W * 4.04
    return int(max(making) + stored)


def material_extension(*, base_color, metallic: float, roughness: float, f0: float, normal_strength: float,
                       base_texture: bool, roughness_texture: bool, normal_texture: bool) -> dict:
    """A material's parameters as the preview shader reads them (its
    PRTTMaterial block, core.preview.pack.PreviewMaterial): linear base
    colour, metallic, roughness, the dielectric F0, the normal map's strength
    and which of them come from the glTF material's own textures (base
    colour: baseColorTexture; roughness: metallicRoughnessTexture's G;
    normals: normalTexture)."""
    return {"baseColor": [float(c) for c in tuple(base_color)[:3]], "metallic": float(metallic),
            "roughness": float(roughness), "f0": float(f0), "normalStrength": float(normal_strength),
            "baseColorTexture": bool(base_texture), "roughnessTexture": bool(roughness_texture),
            "normalTexture": bool(normal_texture)}


def display_extension(stops: float, view_transform: str, *, look: str = "None", device: str = "sRGB",
                      gamma: float = 1.0, table=None) -> dict:
    """How the preview turns radiance into pixels: ``exposure`` = 2 ** stops
    multiplies linear radiance first; then the sRGB encode (Blender's plain
    Standard) or, with ``table`` (a core.shading.display.DisplayTransform),
    the scene's view transform as that table (``table``: size N, encoding
    LUT_ENCODING, shaper [lo, hi] stops; its bufferView, the table's
    payload, is filled by the writer) and the display ``gamma`` after it
    (core.io.image_write.write_image)."""
    out = {"exposure": float(2.0 ** float(stops)), "stops": float(stops), "viewTransform": str(view_transform)}
    if table is not None:
        out.update(look=str(look), displayDevice=str(device), gamma=float(gamma),
                   table={"name": table.name, "size": table.size, "encoding": LUT_ENCODING,
                          "shaper": [float(table.lo), float(table.hi)]})
    return out


def environment_extension(*, description: str, strength: float, rotation=(0.0, 0.0, 0.0),
                          vector_type: str = "POINT", lookup_rotation=None, image: dict | None = None,
                          color=None) -> dict:
    """The World at export: its equirect image's file (``image``: name,
    mimeType, bytes; the writer adds its bufferView) or a constant ``color``,
    Background strength, the Mapping node's Euler XYZ rotation (radians) and
    type, and the lookup rotation R (core.light.envmap.mapping_rotation). The
    root light is compose_light(project_equirect(image), strength, R)."""
    R = np.eye(3) if lookup_rotation is None else np.asarray(lookup_rotation, np.float64)
    out = {"description": description, "strength": float(strength),
           "rotation": [float(a) for a in rotation], "vectorType": vector_type,
           "lookupRotation": R.round(12).tolist()}
    if image is not None:
        out["image"] = image
    if color is not None:
        out["color"] = [float(c) for c in color]
    return out


def root_extension(*, bands: int, light: np.ndarray, light_description: str, sets: list,
                   display: dict | None = None, environment: dict | None = None,
                   default_material: dict | None = None, sun: dict | None = None,
                   lamps: list | None = None) -> dict:
    """The root extension's JSON, ``sets`` each {"name", "resolution",
    "transfer": {..., "bufferView": <filled by the writer>}}. ``light``:
    (K, 3) RGB SH of the environment in the bake frame (Blender's World at
    export, strength and rotation applied); ``display``
    (:func:`display_extension`) and ``environment``
    (:func:`environment_extension`) when given; ``default_material``
    (:func:`material_extension`): what the preview shades a primitive without
    a material with (glTF's own default is metallic, which would draw it black);
    ``sun`` (:func:`sun_extension`) when the bake has a sun's masks,
    ``lamps`` (:func:`lamps_extension`) when it has lamps' masks."""
    L = np.asarray(light, np.float64)
    if L.ndim != 2 or L.shape[1] != 3 or L.shape[0] != bands * bands:
        raise ValueError(f"light: expected ({bands * bands}, 3) SH coefficients, got {L.shape}")
    return {
        "version": VERSION,
        "sh": {"bands": int(bands), "coefficients": int(bands * bands), "index": "k = l*l + l + m",
               "basis": "real orthonormal, Condon-Shortley phase (docs/sh-conventions.md)",
               "frame": "Blender world, Z up", "gltfToBakeFrame": [list(r) for r in GLTF_TO_BAKE_FRAME]},
        "light": {"description": light_description, "rgb": L.round(9).tolist()},
        "sets": sets,
        **({"display": display} if display is not None else {}),
        **({"environment": environment} if environment is not None else {}),
        **({"defaultMaterial": default_material} if default_material is not None else {}),
        **({"sun": sun} if sun is not None else {}),
        **({"lamps": lamps} if lamps else {}),
    }
