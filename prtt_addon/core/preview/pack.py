"""What the viewport preview draws, as plain arrays (no bpy, no gpu).

The preview's GPU code (blender/preview/renderer.py) and its numpy reference
(core/preview/reference.py) consume the same :class:`PreviewScene`, built
from a Blender scene (blender/preview/drawlist.py) or from a core Scene and its
bake (benchmarks, tests).

Layouts (core/preview/shader_source.py documents the GPU side):

* SH textures go to 2D array textures of ceil(K/4) RGBA layers: coefficient
  k is layer k // 4, component k % 4; rows bottom first (like UVs). Bounce
  textures (all levels summed: they add linearly) use 3 ceil(K/4) layers,
  channel c of coefficient k at layer c ceil(K/4) + k // 4.
* Per-vertex transfer: texel i (x = i % W, y = i // W) of a W-wide array
  texture, same layer packing.
* Meshes are indexed triangle lists in object space; corners with identical
  attributes share a vertex (so the vertex baselines shade each once), and
  triangles are sorted by material so each material is one draw range.
"""
from __future__ import annotations

import contextlib
import dataclasses
import math
import os

import numpy as np

from ..io.exr_bands import channel_bands, channel_groups
from ..io.exr_io import (
    TextureError,
    bands_of_header,
    channel_names,
    glossy_tint,
    read_edge_exr,
    read_lamp_exr,
    read_mask_exr,
    read_relight_exr,
    read_sh_exr,
    relight_channel_names,
    shown,
    texture_header,
)
from ..io.sidecars import read_corner_vertex, read_vertex_coeffs
from ..model.material import DEFAULT
from ..sh.gaunt import sparse_gaunt, tpfl_matrix
from ..shading.materials import dielectric_f0
from ..shading.relit import apply_light
from ..shading.shade import light_hash, sun_sh

#: Width of the per-vertex transfer texture.
VERTEX_TEXTURE_WIDTH = 4096

FLAG_BASE_TEXTURE = 1
FLAG_ROUGHNESS_TEXTURE = 2
FLAG_NORMAL_MAP = 4


@dataclasses.dataclass(frozen=True)
class PreviewMaterial:
    """Principled values of one material; textures index PreviewScene.images."""

    base_color: tuple = DEFAULT.base_color
    metallic: float = DEFAULT.metallic
    roughness: float = DEFAULT.roughness
    f0: float = float(dielectric_f0(DEFAULT.ior, DEFAULT.specular))
    base_texture: int = -1
    roughness_texture: int = -1
    normal_texture: int = -1
    normal_strength: float = 1.0

    @classmethod
    def from_spec(cls, spec: dict, *, normal_texture: int = -1, normal_strength: float = 1.0,
                  texture_index=None) -> "PreviewMaterial":
        """From a core material dict (core.shading.materials.Material fields).

        texture_index maps the dict's texture numbers to PreviewScene.images
        indices (identity when None)."""
        d = {**DEFAULT.as_dict(), **spec}
        remap = texture_index or (lambda i: i)
        bt, rt = int(d.get("base_color_texture", -1)), int(d.get("roughness_texture", -1))
        return cls(base_color=tuple(float(c) for c in d["base_color"]), metallic=float(d["metallic"]),
                   roughness=float(d["roughness"]), f0=float(dielectric_f0(d["ior"], d["specular"])),
                   base_texture=remap(bt) if bt >= 0 else -1, roughness_texture=remap(rt) if rt >= 0 else -1,
                   normal_texture=normal_texture, normal_strength=float(normal_strength))

    @property
    def flags(self) -> int:
        return ((FLAG_BASE_TEXTURE if self.base_texture >= 0 else 0)
                | (FLAG_ROUGHNESS_TEXTURE if self.roughness_texture >= 0 else 0)
                | (FLAG_NORMAL_MAP if self.normal_texture >= 0 else 0))

    def block(self) -> np.ndarray:
        """The PRTTMaterial uniform block: (8,) float32."""
        return np.array([*self.base_color, self.metallic, self.roughness, self.f0, self.normal_strength,
                         float(self.flags)], dtype=np.float32)


@dataclasses.dataclass
class DrawMesh:
    """One object's triangles in object space, ready for a vertex buffer.

    positions, normals (V, 3); uv (PRTT map), mat_uv (material textures), nm_uv
    (normal map) (V, 2); tangents (V, 4) xyz + bitangent sign; vidx (V,) row of
    the set's per-vertex transfer (-1: none); indices (T, 3); ranges: list of
    (material index, first triangle, triangle count); matrix (4, 4) model
    matrix (object -> world, float64). All float arrays float32.
    """

    name: str
    set_name: str | None
    positions: np.ndarray
    normals: np.ndarray
    uv: np.ndarray
    mat_uv: np.ndarray
    nm_uv: np.ndarray
    tangents: np.ndarray
    vidx: np.ndarray
    indices: np.ndarray
    ranges: list
    matrix: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
    key: str = ""

    @property
    def triangles(self) -> int:
        return int(self.indices.shape[0])

    def has_vertex_transfer(self) -> bool:
        return self.vidx.size > 0 and bool(np.all(self.vidx >= 0))

    def world_corners(self, attr: str) -> np.ndarray:
        """(T, 3, C) float64 corner values; positions/normals/tangents in world space."""
        a = getattr(self, attr)[self.indices].astype(np.float64)
        M = np.asarray(self.matrix, np.float64)
        if attr == "positions":
            return a @ M[:3, :3].T + M[:3, 3]
        if attr == "normals":
            return a @ normal_matrix(M)[:3, :3].T
        if attr == "tangents":
            out = a.copy()
            out[..., :3] = a[..., :3] @ M[:3, :3].T
            out[..., 3] *= np.sign(np.linalg.det(M[:3, :3])) or 1.0
            return out
        return a


def normal_matrix(M: np.ndarray) -> np.ndarray:
    """Inverse transpose of the 3x3 part, as a 4x4 whose [3, 3] is sign(det)."""
    M3 = np.asarray(M, np.float64)[:3, :3]
    det = np.linalg.det(M3)
    out = np.zeros((4, 4))
    out[:3, :3] = np.linalg.inv(M3).T if abs(det) > 1e-300 else np.eye(3)
    out[3, 3] = -1.0 if det < 0 else 1.0
    return out


def fix_corner_normals(normals: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Replace zero-length corner normals by their triangle's face normal
    (or +Z for a degenerate triangle), so interpolation rarely meets zero.
    normals, positions: (T, 3, 3)."""
    n = np.asarray(normals, np.float64).copy()
    ln = np.linalg.norm(n, axis=2)
    bad = ln < 1e-12
    if np.any(bad):
        P = np.asarray(positions, np.float64)
        fn = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
        fl = np.linalg.norm(fn, axis=1, keepdims=True)
        fn = np.where(fl > 1e-300, fn / np.where(fl > 0, fl, 1.0), [0.0, 0.0, 1.0])
        n[bad] = np.broadcast_to(fn[:, None, :], n.shape)[bad]
    return n


def build_mesh(name: str, set_name: str | None, corners: dict, material: np.ndarray, *,
               matrix=None, key: str = "") -> DrawMesh:
    """A DrawMesh from per-corner arrays (T, 3, C) and the material of each triangle.

    corners: positions, normals (required); uv, mat_uv, nm_uv, tangents, vidx
    (optional: zeros / -1 when absent). Identical corners are merged.
    """
    P = np.asarray(corners["positions"], np.float64)
    T = P.shape[0]
    if T == 0:
        raise ValueError(f"{name}: no triangles to draw")
    cols = {
        "positions": P.astype(np.float32),
        "normals": fix_corner_normals(corners["normals"], P).astype(np.float32),
        "uv": np.asarray(corners.get("uv", np.zeros((T, 3, 2))), np.float32),
        "mat_uv": np.asarray(corners.get("mat_uv", np.zeros((T, 3, 2))), np.float32),
        "nm_uv": np.asarray(corners.get("nm_uv", np.zeros((T, 3, 2))), np.float32),
        "tangents": np.asarray(corners.get("tangents", np.tile([1.0, 0, 0, 1], (T, 3, 1))), np.float32),
        "vidx": np.asarray(corners.get("vidx", np.full((T, 3), -1.0)), np.float32)[..., None],
    }
    widths = {k: v.shape[2] for k, v in cols.items()}
    mat = np.asarray(material, np.int64).reshape(T)
    # Merge identical corners (rows compared as raw bytes); the material is part
    # of the key, so a vertex is shaded with one material in the vertex baselines.
    mat_col = np.repeat(mat.astype(np.float32), 3)[:, None]
    flat = np.ascontiguousarray(np.concatenate([v.reshape(T * 3, -1) for v in cols.values()] + [mat_col], axis=1))
    rows = flat.view(np.dtype((np.void, flat.dtype.itemsize * flat.shape[1]))).ravel()
    _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
    uniq = flat[first]
    indices = inverse.reshape(T, 3).astype(np.uint32)
    order = np.argsort(mat, kind="stable")
    indices = indices[order]
    ms = mat[order]
    starts = np.flatnonzero(np.r_[True, ms[1:] != ms[:-1]])
    counts = np.diff(np.r_[starts, T])
    ranges = [(int(ms[s]), int(s), int(c)) for s, c in zip(starts, counts)]
    out, o = {}, 0
    for k, w in widths.items():
        out[k] = np.ascontiguousarray(uniq[:, o:o + w])
        o += w
    return DrawMesh(name=name, set_name=set_name, positions=out["positions"], normals=out["normals"],
                    uv=out["uv"], mat_uv=out["mat_uv"], nm_uv=out["nm_uv"], tangents=out["tangents"],
                    vidx=out["vidx"][:, 0], indices=indices, ranges=ranges,
                    matrix=np.eye(4) if matrix is None else np.asarray(matrix, np.float64), key=key)


@dataclasses.dataclass
class PreviewSet:
    """The baked textures of one texture set, loaded on demand.

    transfer: path of ``<set>.transfer.exr``; bounces: paths of its bounce
    levels; vertex: path of ``<set>.vertex.npz`` or None; relight: path of
    ``<set>.relight.exr`` (relightable bounces, instead of levels) or None.
    """

    name: str
    transfer: str
    bounces: tuple = ()
    vertex: str | None = None
    relight: str | None = None
    sun: str | None = None        # <set>.sun.exr: the visible fraction of the sun's disc per texel
    sun_edge: str | None = None   # <set>.sun_edge.exr: its sub-texel shadow edges (with sun only)
    lamps: str | None = None      # <set>.lamps.exr: the visible fraction of each lamp's sphere per texel
    lamp_count: int = 0           # its channels (the manifest's lamps, in order)

    @property
    def has_bounce(self) -> bool:
        return bool(self.bounces or self.relight)

    def bounce_key(self, light) -> str:
        """Cache key of the bounce texture shown under ``light``: relightable
        bounce light changes with the light, baked levels do not."""
        if self.relight:
            return self.key + "|light:" + light_hash(np.asarray(light))
        return self.key

    @property
    def key(self) -> str:
        parts = []
        for p in (self.transfer, *self.bounces, self.vertex, self.relight, self.sun, self.sun_edge, self.lamps):
            if p:
                try:
                    st = os.stat(p)
                    parts.append(f"{p}:{st.st_mtime_ns}:{st.st_size}")
                except OSError:
                    parts.append(f"{p}:missing")
        return "|".join(parts)

    def load_transfer(self) -> np.ndarray:
        """(H, W, K) float32, row 0 at the bottom."""
        return read_sh_exr(self.transfer)[0]

    def load_bounce(self, n_coeffs: int | None = None, light=None) -> np.ndarray | None:
        """(H, W, 3, K) float32: every bounce level summed, or None.

        A level the bake stored band-limited (tuning "auto": the bands its
        set's shading reads, header ``band_limited``) is padded with zero
        coefficients up to ``n_coeffs``; any other level keeps what it holds
        (a renderer refuses too few coefficients). Relightable bounces are
        shown under ``light`` (K, 3), the World as it is now (needed then)."""
        if self.relight:
            return self._relit(light, n_coeffs)
        total = None
        for p in self.bounces:
            b, attrs = read_sh_exr(p)
            if n_coeffs is not None and attrs.get("band_limited") and b.shape[-1] < n_coeffs:
                b = np.concatenate([b, np.zeros(b.shape[:-1] + (n_coeffs - b.shape[-1],), b.dtype)], axis=-1)
            if total is not None and total.shape != b.shape:
                raise ValueError(f"{p}: bounce level of shape {b.shape} does not match the others' {total.shape}")
            total = b if total is None else total + b
        return total

    def load_relight(self) -> tuple:
        """The relightable operator (dc, glossy, attrs) of exr_io.read_relight_exr."""
        return read_relight_exr(self.relight)

    def _relit(self, light, n_coeffs: int | None = None) -> np.ndarray:
        """(H, W, 3, K) float32: the relightable bounce light under ``light``
        (K, 3), the World as it is now, on the CPU (the numpy reference; the
        viewport relights on the GPU, renderer._relit_bounce)."""
        if light is None:
            raise ValueError(f"{self.relight}: relightable bounces need the light to show them under")
        dc, glossy, attrs = self.load_relight()
        bands = int(attrs["bands"]) if n_coeffs is None else int(round(math.sqrt(n_coeffs)))
        L = np.zeros((bands * bands, 3))
        given = np.asarray(light, np.float64)[:bands * bands]
        L[:given.shape[0]] = given
        return apply_light(dc, glossy, L, bands)

    def load_sun(self) -> np.ndarray | None:
        """(H, W) float32 sun mask, row 0 at the bottom, or None."""
        return read_mask_exr(self.sun)[0] if self.sun else None

    def load_sun_texture(self) -> np.ndarray | None:
        """The sun's texture as the shaders read it (prtt_shade.glsl
        sun_visible), row 0 at the bottom: (H, W) float32 the mask alone, or
        with edges (H, W, 4) (mask, d, valid, h); None without a mask.
        TextureError when the edges' size is not the mask's."""
        mask = self.load_sun()
        if mask is None or not self.sun_edge:
            return mask
        edge = read_edge_exr(self.sun_edge)[0]
        if edge.shape[:2] != mask.shape:
            raise TextureError(f"{self.sun_edge}: {edge.shape[1]}x{edge.shape[0]} edges for a "
                               f"{mask.shape[1]}x{mask.shape[0]} mask; bake again")
        return np.stack([mask, edge[..., 0], edge[..., 2], edge[..., 1]], axis=-1)

    def load_lamp_texture(self) -> np.ndarray | None:
        """(H, W, 4) float32 the lamps' masks as lampTex holds them (channel
        i lamp i, unused channels 0), row 0 at the bottom; None without lamps."""
        if not self.lamps or not self.lamp_count:
            return None
        m = read_lamp_exr(self.lamps, self.lamp_count)[0]
        out = np.zeros(m.shape[:2] + (4,), np.float32)
        out[..., :m.shape[2]] = m
        return out

    def load_vertex(self) -> np.ndarray | None:
        """(V, K) float32 per-vertex transfer, or None."""
        if not self.vertex:
            return None
        return read_vertex_coeffs(self.vertex)


@dataclasses.dataclass
class PreviewScene:
    """Everything one preview frame draws.

    light: (K, 3) float64 world-frame RGB SH (rotation and strength applied);
    images: list of (H, W, 4) float32 material textures / normal maps, file
    order (row 0 = top), linear values; image_keys: a cache key per image.
    material_names, image_names: where the scene came from Blender, the
    material (None: no material) of each entry of materials and the image of
    each entry of images (the glTF export matches them with Blender's).
    """

    bands: int
    meshes: list
    materials: list
    sets: dict
    light: np.ndarray
    images: list = dataclasses.field(default_factory=list)
    image_keys: list = dataclasses.field(default_factory=list)
    use_bounces: bool = True
    normal_maps: bool = True
    material_names: list = dataclasses.field(default_factory=list)
    image_names: list = dataclasses.field(default_factory=list)
    sun: "PreviewSun | None" = None      # drawn where a set has its mask (PreviewSet.sun)
    lamps: tuple = ()                    # core.light.lamp.Lamp, live, in the masks' channel order (PreviewSet.lamps)

    @property
    def bounce_light(self) -> np.ndarray:
        """(K, 3) the light relightable bounces are relit with: the
        environment's SH and, with a sun, its SH projection
        (shade.sun_sh): the sun's bounce, low-frequency as bounce light is."""
        if self.sun is None:
            return self.light
        return np.asarray(self.light, np.float64) + sun_sh(self.sun.direction, self.sun.irradiance, self.bands)


@dataclasses.dataclass(frozen=True)
class PreviewSun:
    """A sun as the preview draws it (core.light.sun.Sun's conventions):
    direction (3,) unit towards it, irradiance (3,) W/m² facing it (its colour
    times strength, live), angle its disc's full angle (radians)."""

    direction: tuple
    irradiance: tuple
    angle: float

    @classmethod
    def of(cls, sun) -> "PreviewSun":
        """From a core.light.sun.Sun."""
        return cls(tuple(sun.direction), tuple(float(v) for v in sun.irradiance), float(sun.angle))

    def block(self) -> np.ndarray:
        """The PRTTSun uniform block: direction and angle² / 16, irradiance; flat float32."""
        return np.array([*self.direction, self.angle * self.angle / 16.0, *self.irradiance, 0.0], np.float32)


def lamp_block(lamps) -> np.ndarray:
    """The PRTTLamps uniform block (shader_source.LAMP_TYPEDEFS) of up to four
    core.light.lamp.Lamp: info (count), then per lamp position and radius,
    intensity (W/sr) and the spot's smoothstep scale (1e20 for a hard cone,
    1 for a point), axis and cos half the cone (-2 for a point); flat float32."""
    lamps = tuple(lamps)[:4]
    pos, inten, spot = (np.zeros((4, 4)) for _ in range(3))
    for i, lp in enumerate(lamps):
        pos[i] = [*lp.position, lp.radius]
        smooth = lp.spot_smooth if lp.kind == "SPOT" else 1.0
        inten[i] = [*lp.intensity, min(smooth, 1e20)]
        spot[i] = [*lp.axis, lp.cos_half_cone if lp.kind == "SPOT" else -2.0]
    return np.concatenate([[len(lamps), 0, 0, 0], pos.ravel(), inten.ravel(), spot.ravel()]).astype(np.float32)


# --- packing for the GPU ------------------------------------------------------------

def layers(n_coeffs: int) -> int:
    return (n_coeffs + 3) // 4


def pack_layers(tex: np.ndarray) -> np.ndarray:
    """(H, W, K) -> (ceil(K/4), H, W, 4) float32, zero padded."""
    H, W, K = tex.shape
    L = layers(K)
    out = np.zeros((H, W, 4 * L), np.float32)
    out[..., :K] = tex
    return np.ascontiguousarray(out.reshape(H, W, L, 4).transpose(2, 0, 1, 3))


#: Bytes a texture's upload may hold beside the GPU's copy: one band of the
#: file's channels plus its float32 staging (twice: the buffer and the band's
#: texture). Bands are whole 32-row blocks where they can be (PIZ decodes 32
#: rows at a time), else whole 16-row ones (ZIP's), and at least one row.
STAGING_BYTES = 32 << 20
#: Bytes per texel of the staging (float32 RGBA, held twice).
STAGE_TEXEL_BYTES = 32


def band_rows(height: int, width: int, channels: int, channel_bytes: int = 4,
              budget: int = STAGING_BYTES) -> int:
    """Rows per upload band of a ``height`` x ``width`` texture read from
    ``channels`` channels of ``channel_bytes`` each: as many as ``budget``
    holds (staging included), in whole 32-row (else 16-row) blocks where it can."""
    rows = max(1, budget // max(1, _row_bytes(width, channels, channel_bytes)))
    if rows >= 16:          # whole ZIP blocks at least, whole PIZ blocks where they fit
        rows -= rows % (32 if rows >= 32 else 16)
    return int(min(rows, height))


def _row_bytes(width: int, channels: int, channel_bytes: int) -> int:
    """Bytes an upload holds per row of its band: the channels as received
    and the float32 staging (twice), in this process; the decoding child
    holds about the channels' share again in its own."""
    return width * (STAGE_TEXEL_BYTES + channels * channel_bytes)


def relit_bytes(op: "LayerSource") -> int:
    """Bytes of the float32 bounce texture a relightable operator's relight pass
    draws (3 ceil(K/4) RGBA32F layers at the operator's size)."""
    return op.height * op.width * 3 * layers(op.coeffs) * 16


class _BandRows:
    """Where a band (file rows ``top`` .. ``top + n - 1``, top first) of a
    source's texture lands on the GPU: rows ``gpu_row`` .. ``gpu_row + n - 1``."""

    @property
    def gpu_row(self) -> int:
        return self.source.height - self.top - self.n


class _BandedTexture:
    """What the band sources (:class:`LayerSource`, :class:`LevelSumSource`)
    share; each has ``height``, ``width``, ``layers``, ``channel_bytes``,
    ``bands`` and says how many channels a band reads (``_channels``) and
    whether its GPU texture is planned as half (``_half_planned``)."""

    def band_rows(self, budget: int = STAGING_BYTES) -> int:
        return band_rows(self.height, self.width, self._channels(), self.channel_bytes, budget)

    def fill(self, out: np.ndarray, rows: int | None = None) -> None:
        """Write every layer into ``out`` (L, H, W, 4) float32 (tests, tools:
        the renderer uploads band by band instead)."""
        if out.shape != (self.layers, self.height, self.width, 4):
            raise ValueError(f"{self.path}: layers of shape {out.shape}, expected "
                             f"{(self.layers, self.height, self.width, 4)}")
        with self.bands(rows) as bands:
            for band in bands:
                for layer in range(self.layers):
                    band.fill_layer(layer, out[layer, band.gpu_row:band.gpu_row + band.n])

    def plan(self) -> tuple[int, int]:
        """(bytes of the GPU texture, bytes staged beside it while it goes up),
        from the headers."""
        return (self.layers * self.height * self.width * 4 * (2 if self._half_planned() else 4),
                self.band_rows() * _row_bytes(self.width, self._channels(), self.channel_bytes))


@dataclasses.dataclass(eq=False)
class Band(_BandRows):
    """Rows ``top`` .. ``top + n - 1`` (file order, top first) of a
    :class:`LayerSource`'s channels; :meth:`fill_layer` writes one layer's
    rows of it bottom first, GPU rows ``gpu_row`` .. ``gpu_row + n - 1``."""

    source: "LayerSource"
    top: int
    n: int
    chans: dict
    tint: np.ndarray | None = None      # (n, W, 3) float32, rows bottom first

    def fill_layer(self, layer: int, out: np.ndarray) -> None:
        """Write this band of layer ``layer`` into ``out`` (n, W, 4) float32."""
        for j, name in enumerate(self.source.groups[layer]):
            if name is None:
                out[:, :, j] = 0.0
            elif isinstance(name, tuple):
                n, c = name
                np.multiply(self.tint[:, :, c], self.chans[n][::-1], out=out[:, :, j], dtype=np.float32)
            else:
                out[:, :, j] = self.chans[name][::-1]


@dataclasses.dataclass(eq=False)
class LayerSource(_BandedTexture):
    """A texture's GPU layers (L, H, W, 4) float32, row 0 at the bottom, made
    from its file's channels a band of rows at a time (exr_bands: decoded in
    a child process, never the whole file in this one): :meth:`bands` yields
    :class:`Band` s whose layers the renderer stages and uploads, so no copy
    of the whole texture (half or float32) sits beside the GPU's. The values
    are :func:`pack_layers` / :func:`pack_relight_operator`'s of the texture
    as read_sh_exr / read_relight_exr return it.

    ``groups``: per layer the four channel names (None: zero), or for a
    shared glossy row (name, colour): the channel tinted by that colour's
    exr_io.glossy_tint of the DC channels ``tint_from``. ``coeffs``: SH
    coefficients in the last axis of the texture as read (the renderer's band
    check); ``rgb``: a bounce texture where a transfer was expected;
    ``channel_bytes``: bytes per stored value the header declares (2 half, 4
    float), for sizing bands."""

    path: str
    groups: list
    height: int
    width: int
    coeffs: int
    rgb: bool = False
    tint_from: tuple | None = None       # the three DC channel names the glossy tints come from
    channel_bytes: int = 4
    dtypes: dict = dataclasses.field(default_factory=dict)    # name -> stored dtype, once a band stream started

    @property
    def layers(self) -> int:
        return len(self.groups)

    @property
    def files(self) -> list:
        return [self.path]

    @property
    def names(self) -> list:
        """The channels the layers read, each once, in layer order."""
        seen = dict.fromkeys(n if not isinstance(n, tuple) else n[0] for g in self.groups for n in g
                             if n is not None)
        if self.tint_from:
            seen.update(dict.fromkeys(self.tint_from))
        return list(seen)

    def _channels(self) -> int:
        return len(self.names)

    def _half_planned(self) -> bool:
        return self.channel_bytes == 2 and self.tint_from is None      # half stays half unless tinted

    @contextlib.contextmanager
    def bands(self, rows: int | None = None):
        """An iterator of :class:`Band` s top to bottom, ``rows`` file rows
        each (default :meth:`band_rows`); a band's arrays are valid until the
        next. TextureError (naming the file) if the file cannot be decoded."""
        with channel_bands(self.path, self.names, self.height, self.width, rows or self.band_rows(),
                           error=TextureError) as stream:
            self.dtypes = dict(stream.dtypes)

            def walk():
                for top, n, chans in stream:
                    tint = None
                    if self.tint_from:
                        tint = glossy_tint(np.stack([chans[c][::-1] for c in self.tint_from],
                                                    axis=-1).astype(np.float32))
                    yield Band(self, top, n, chans, tint)
            yield walk()

    @property
    def half_exact(self) -> bool:
        """Every value is a half float by construction (half channels, none
        tinted; known once :meth:`bands` has started); False means: check
        the values (half_exact of each band's layers)."""
        return (self.tint_from is None and bool(self.dtypes)
                and all(d == np.float16 for d in self.dtypes.values()))


def _missing(path: str, chans, names: list) -> None:
    missing = [n for n in names if n not in chans]
    if missing:
        raise TextureError(f"{path}: missing channels {missing[:4]}{'...' if len(missing) > 4 else ''}")


def transfer_layers(path: str) -> LayerSource:
    """LayerSource of a transfer texture (pack_layers(read_sh_exr(path)[0]))."""
    path = os.fspath(path)
    chans, attrs, H, W, nbytes = texture_header(path)
    K = bands_of_header(path, attrs) ** 2
    rgb = any(n.startswith("R.") for n in chans)
    names = channel_names(K, rgb)
    _missing(path, chans, names)
    return LayerSource(path, channel_groups(names), H, W, K, rgb, channel_bytes=nbytes)


def relight_operator_layers(path: str, *, expand: bool = True) -> LayerSource:
    """LayerSource of a relightable bounce texture's operator
    (pack_relight_operator of read_relight_exr(path)); ``coeffs`` = its light
    coefficients K; attributes ``glossy_bands`` and ``shared``. With
    ``expand=False`` shared glossy rows (tuning auto) stay as stored, once
    for all colours ((Kg - 1) ceil(Kg / 4) layers after the DC rows instead of
    three times as many), for the relight pass to tint (shader_source.
    relight_variant(shared=True)); they are then half floats as in the file."""
    path = os.fspath(path)
    chans, attrs, H, W, nbytes = texture_header(path)
    if attrs["kind"] != "relight":
        raise TextureError(f"{path}: a {shown(attrs['kind'])} texture, not a relightable bounce texture")
    bands = bands_of_header(path, attrs)
    K, kg = bands * bands, bands_of_header(path, attrs, "glossy_bands", 0, bands) ** 2
    colour = attrs.get("glossy_colour", "per-colour")
    if colour not in ("per-colour", "shared"):
        raise TextureError(f"{path}: unknown prtt_glossy_colour {shown(colour)} (per-colour or shared)")
    shared = colour == "shared"
    _missing(path, chans, relight_channel_names(K, kg, shared))
    groups = [g for c in "RGB" for g in channel_groups([f"{c}.dc.i{i:03d}" for i in range(K)])]
    tint_from = None
    if kg and shared and not expand:
        groups += [g for o in range(1, kg) for g in channel_groups([f"S.o{o:03d}.i{i:03d}" for i in range(kg)])]
    elif kg and shared:
        tint_from = tuple(f"{c}.dc.i000" for c in "RGB")
        groups += [g for c in range(3) for o in range(1, kg)
                   for g in channel_groups([(f"S.o{o:03d}.i{i:03d}", c) for i in range(kg)])]
    elif kg:
        groups += [g for c in "RGB" for o in range(1, kg) for g in channel_groups([f"{c}.o{o:03d}.i{i:03d}"
                                                                           for i in range(kg)])]
    src = LayerSource(path, groups, H, W, K, tint_from=tint_from, channel_bytes=nbytes)
    src.glossy_bands = int(attrs.get("glossy_bands", 0)) if kg else 0
    src.shared = bool(kg and shared and not expand)
    return src


@dataclasses.dataclass(eq=False)
class LevelSumSource(_BandedTexture):
    """Baked bounce levels summed, as the GPU takes them (pack_bounce of
    PreviewSet.load_bounce(coeffs)), made a band of rows at a time from
    every level's file at once: the same interface as :class:`LayerSource`
    (``layers``, ``bands``, ``fill``, ``plan``, ``half_exact``) for the renderer's
    upload. The float32 sums are made in the order load_bounce makes them
    (level by level; a band-limited level's missing coefficients add zero)."""

    levels: list                    # per level: (path, K of the level)
    height: int
    width: int
    coeffs: int                     # coefficients per colour after padding (every level's)
    channel_bytes: int = 4
    dtypes: dict = dataclasses.field(default_factory=dict)

    @property
    def path(self) -> str:
        return ", ".join(p for p, _ in self.levels)

    @property
    def layers(self) -> int:
        return 3 * layers(self.coeffs)

    @property
    def files(self) -> list:
        return [p for p, _ in self.levels]

    def _channels(self) -> int:
        return sum(3 * k for _, k in self.levels)

    def _half_planned(self) -> bool:
        return len(self.levels) == 1 and self.channel_bytes == 2     # one half level stays half; a sum is float32

    @contextlib.contextmanager
    def bands(self, rows: int | None = None):
        """An iterator of bands (``n``, ``gpu_row``, ``fill_layer``) as :meth:`LayerSource.bands`."""
        rows = rows or self.band_rows()
        with contextlib.ExitStack() as stack:
            streams = [stack.enter_context(channel_bands(p, channel_names(k, True), self.height, self.width, rows,
                                                         error=TextureError)) for p, k in self.levels]
            self.dtypes = {(i, n): d for i, st in enumerate(streams) for n, d in st.dtypes.items()}

            def walk():
                for parts in zip(*streams):
                    top, n = parts[0][0], parts[0][1]
                    yield _LevelBand(self, top, n, [chans for _, _, chans in parts])
            yield walk()

    @property
    def half_exact(self) -> bool:
        """One level of half channels: its values are half floats (a sum of
        several, in general, is not: checked band by band)."""
        return len(self.levels) == 1 and bool(self.dtypes) and all(d == np.float16 for d in self.dtypes.values())


@dataclasses.dataclass(eq=False)
class _LevelBand(_BandRows):
    source: LevelSumSource
    top: int
    n: int
    chans: list                     # per level: name -> (n, W) stored rows, top first

    def fill_layer(self, layer: int, out: np.ndarray) -> None:
        """Layer ``layer`` (colour c = layer // ceil(K/4), coefficients 4q ..
        4q + 3) of this band into ``out`` (n, W, 4) float32, rows bottom first."""
        K4 = layers(self.source.coeffs)
        c, q = divmod(layer, K4)
        for j in range(4):
            k = 4 * q + j
            o = out[:, :, j]
            if k >= self.source.coeffs:
                o[...] = 0.0
                continue
            for i, ((_, kl), chans) in enumerate(zip(self.source.levels, self.chans)):
                name = f"{'RGB'[c]}.sh{k:03d}"
                v = chans[name][::-1] if k < kl else np.float32(0.0)
                if i == 0:
                    o[...] = v
                else:
                    np.add(o, v, out=o, dtype=np.float32)


def bounce_level_layers(paths, n_coeffs: int) -> LevelSumSource:
    """LevelSumSource of a set's baked bounce levels (PreviewSet.load_bounce's
    sum, padded to ``n_coeffs`` where a level is stored band-limited), from
    the checked headers; TextureError naming the file when a level is not a
    colour SH texture or the levels' sizes differ."""
    levels, shape, nbytes = [], None, 2
    for p in paths:
        p = os.fspath(p)
        chans, attrs, H, W, b = texture_header(p)
        kl = bands_of_header(p, attrs) ** 2
        if not any(n.startswith("R.") for n in chans):
            raise TextureError(f"{p}: not a bounce texture (no colour channels R.sh000 ...)")
        _missing(p, chans, channel_names(kl, True))
        padded = n_coeffs if attrs.get("band_limited") and kl < n_coeffs else kl
        if shape is not None and (H, W, padded) != shape:
            raise TextureError(f"{p}: bounce level of shape {(H, W, 3, padded)} does not match the others' "
                               f"{(shape[0], shape[1], 3, shape[2])}")
        shape, nbytes = (H, W, padded), max(nbytes, b)
        levels.append((p, kl))
    if not levels:
        raise TextureError("no bounce levels")
    return LevelSumSource(levels, shape[0], shape[1], shape[2], nbytes)


def pack_bounce(bounce: np.ndarray) -> np.ndarray:
    """(H, W, 3, K) -> (3 ceil(K/4), H, W, 4): channel-major layer blocks."""
    H, W, C, K = bounce.shape
    return np.concatenate([pack_layers(bounce[:, :, c, :]) for c in range(C)], axis=0)


def pack_vertex_transfer(coeffs: np.ndarray, width: int = VERTEX_TEXTURE_WIDTH) -> np.ndarray:
    """(V, K) -> (ceil(K/4), rows, width, 4): texel i at (i % width, i // width)."""
    V, K = coeffs.shape
    w = max(1, min(width, V))
    rows = max(1, math.ceil(V / w))
    grid = np.zeros((rows * w, K), np.float32)
    grid[:V] = coeffs
    return pack_layers(grid.reshape(rows, w, K))


def half_exact(a: np.ndarray) -> bool:
    """Can ``a`` go to a half-float texture without changing a single value?"""
    if a.size == 0:
        return True
    if float(np.max(np.abs(a))) > 65504.0:
        return False
    return bool(np.array_equal(a.astype(np.float16).astype(np.float32), a))


def light_block(light: np.ndarray, bands: int) -> np.ndarray:
    """The PRTTLight uniform block for (K, 3) light: M(L_c) rows padded to
    4-coefficient groups, then the light coefficients; flat float32."""
    K = bands * bands
    L = np.asarray(light, np.float64)[:K]
    K4 = layers(K)
    M = tpfl_matrix(L, bands)                                  # (3, K, K)
    rows = np.zeros((3, K, 4 * K4))
    rows[:, :, :K] = M
    coeffs = np.zeros((K, 4))
    coeffs[:, :3] = L
    return np.concatenate([rows.ravel(), coeffs.ravel()]).astype(np.float32)


def pack_relight_operator(dc: np.ndarray, glossy: np.ndarray | None) -> np.ndarray:
    """Relightable operator -> (L, H, W, 4) layers for the GPU relight pass:
    the DC rows, colour-major (layer c * K4 + l: light coefficients 4l..4l+3),
    then with ``glossy`` (H, W, 3, Kg - 1, Kg) per colour and out coefficient
    o = 1 .. Kg - 1 its light coefficients (Kg4 layers each); zero padded."""
    parts = [pack_layers(dc[:, :, c, :]) for c in range(3)]
    if glossy is not None:
        parts += [pack_layers(glossy[:, :, c, o, :]) for c in range(3) for o in range(glossy.shape[3])]
    return np.concatenate(parts, axis=0)


def relight_block(light: np.ndarray, bands: int) -> np.ndarray:
    """The PRTTRelight uniform block: (K, 3) light per colour in 4-coefficient
    groups (vec4 c * K4 + q: coefficients 4q..4q+3 of colour c); flat float32."""
    K = bands * bands
    K4 = layers(K)
    out = np.zeros((3, 4 * K4), np.float32)
    L = np.asarray(light, np.float64)[:K]
    out[:, :L.shape[0]] = L.T
    return out.ravel()


def gaunt_table(bands: int, width: int) -> np.ndarray:
    """(rows, width, 4) float32: texel e = (i, j, k, tau_ijk) of the Gaunt non-zeros."""
    g = sparse_gaunt(bands)
    rows = max(1, math.ceil(g.nnz / width))
    out = np.zeros((rows * width, 4), np.float32)
    out[:g.nnz] = np.stack([g.i, g.j, g.k, g.value], axis=1)
    return out.reshape(rows, width, 4)


def image_rgba(img: np.ndarray) -> np.ndarray:
    """(H, W, C) file-order image -> (H, W, 4) float32 bottom row first, for upload.

    One channel is replicated to rgb (a grey texture); alpha is 1 if absent."""
    a = np.asarray(img, np.float32)
    if a.ndim == 2:
        a = a[..., None]
    H, W, C = a.shape
    out = np.ones((H, W, 4), np.float32)
    if C == 1:
        out[..., :3] = a
    else:
        out[..., :min(C, 4)] = a[..., :4]
    return np.ascontiguousarray(out[::-1])


def view_block(view_projection: np.ndarray, camera: np.ndarray, exposure: float, bands: int,
               depth_bias: float = 0.0, gamma_inv: float = 0.0) -> np.ndarray:
    """The PRTTView uniform block: mat4 (column-major, as GLSL reads it), camera,
    params (exposure, depth bias, K = bands^2 as the TPFL loop's run-time bound,
    1 / the display gamma: read by the display variants only)."""
    vp = np.asarray(view_projection, np.float64)
    return np.concatenate([vp.T.ravel(), np.asarray(camera, np.float64),
                           [exposure, depth_bias, float(bands * bands), gamma_inv]]).astype(np.float32)


# --- a PreviewScene straight from a core Scene and its bake (benchmarks, tests) ------------

def from_core_scene(sc, out_dir: str, light: np.ndarray, bands: int, *, use_bounces: bool = True,
                    sun=None, lamps=()) -> PreviewScene:
    """Every baked object of ``sc`` as a DrawMesh (world space, identity
    matrix), with the textures the bake wrote to ``out_dir``; ``sun`` (a
    core.light.sun.Sun) drawn with the sets' masks, ``lamps`` (core.light.lamp.Lamp,
    the bake's, in order) with their masks.

    Materials come from ``sc.materials`` (default grey where none), material
    textures from ``sc.textures``; normal maps are not carried over (the
    Blender path handles them)."""
    files = set(os.listdir(out_dir))
    mats = [PreviewMaterial.from_spec({k: v for k, v in m.items() if k != "name"}) for m in sc.materials]
    default_mat = len(mats)
    mats.append(PreviewMaterial())
    sets, meshes = {}, []
    names = sc.object_names or [f"object{i}" for i in range(int(sc.object_id.max()) + 1)]
    for s, set_name in enumerate(sc.set_names):
        transfer = f"{set_name}.transfer.exr"
        if transfer not in files:
            continue
        bounces = tuple(os.path.join(out_dir, f) for f in sorted(files)
                        if f.startswith(f"{set_name}.bounce") and f.endswith(".exr"))
        vfile = f"{set_name}.vertex.npz"
        rfile = f"{set_name}.relight.exr"
        sfile, efile = f"{set_name}.sun.exr", f"{set_name}.sun_edge.exr"
        with_sun = sfile in files and sun is not None
        sets[set_name] = PreviewSet(set_name, os.path.join(out_dir, transfer), bounces,
                                    os.path.join(out_dir, vfile) if vfile in files else None,
                                    os.path.join(out_dir, rfile) if rfile in files else None,
                                    os.path.join(out_dir, sfile) if with_sun else None,
                                    os.path.join(out_dir, efile) if with_sun and efile in files else None,
                                    *((os.path.join(out_dir, f"{set_name}.lamps.exr"), len(lamps))
                                      if lamps and f"{set_name}.lamps.exr" in files else (None, 0)))
        set_tris = sc.triangles_of_set(s)
        corner_vertex = None
        if vfile in files:
            corner_vertex = read_corner_vertex(os.path.join(out_dir, vfile))
        for o in np.unique(sc.object_id[set_tris]):
            rows = np.flatnonzero(sc.object_id[set_tris] == o)
            tris = set_tris[rows]
            corners = {"positions": sc.positions[tris], "normals": sc.normals[tris], "uv": sc.uvs[tris]}
            if sc.mat_uvs is not None:
                corners["mat_uv"] = sc.mat_uvs[tris]
            if corner_vertex is not None:
                corners["vidx"] = corner_vertex[rows].astype(np.float32)
            mid = (np.where(sc.material_id[tris] >= 0, sc.material_id[tris], default_mat)
                   if sc.material_id is not None else np.full(tris.size, default_mat))
            meshes.append(build_mesh(names[o], set_name, corners, mid, key=f"{out_dir}|{set_name}|{o}"))
    return PreviewScene(bands=bands, meshes=meshes, materials=mats, sets=sets, light=np.asarray(light)[:bands * bands],
                        images=list(sc.textures), image_keys=[f"{out_dir}|tex{i}" for i in range(len(sc.textures))],
                        use_bounces=use_bounces, normal_maps=False,
                        sun=PreviewSun.of(sun) if sun is not None else None, lamps=tuple(lamps))
