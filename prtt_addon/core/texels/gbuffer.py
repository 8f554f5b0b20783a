"""The UV-space G-buffer: per covered texel a surface point and its normals.

For texture set s, every texel touched by one of its triangles (see raster.py)
gets: world position (float64), shading normal, geometric normal, triangle id
and coverage. Shading normals interpolate the per-corner split normals and, where
the triangle has a tangent-space normal map, come from the map (paper, "Normal
maps"): n = normalize(x T + y B + z N) with B = sign cross(N, T) (MikkTSpace, as
Blender's Normal Map node), blended with N by the node's strength.

The geometric normal is the triangle's face normal, turned to the side of the
shading normal (the side that is shaded). A shading normal that ends up below
the geometric horizon (an extreme normal map) is bent to 0.05 above it, since
nothing below the surface can be lit.

Texels whose triangle is degenerate in 3D *and* whose corner normals cancel have
no usable normal; they are dropped and counted (``dropped_texels``).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..model.scene import Scene
from .raster import rasterize
from .texsample import bilinear_repeat

#: Texels of one row band of a G-buffer built on a thread pool (build_gbuffer).
BAND_TEXELS = 1 << 21

#: Minimum cosine between a normal-mapped shading normal and the geometric normal.
MIN_HORIZON_COS = 0.05


@dataclasses.dataclass
class GBuffer:
    set_index: int
    width: int
    height: int
    texel: np.ndarray        # (N,) int64 flat index, row 0 = bottom
    tri: np.ndarray          # (N,) int64 scene triangle
    bary: np.ndarray         # (N, 3) float64
    position: np.ndarray     # (N, 3) float64 world
    normal: np.ndarray       # (N, 3) float64 shading normal, unit
    geo_normal: np.ndarray   # (N, 3) float64 geometric normal, unit, shading side
    coverage: np.ndarray     # (N,) float32
    normal_mapped: np.ndarray  # (N,) bool
    stats: dict

    @property
    def n(self) -> int:
        return int(self.texel.shape[0])

    def mask(self) -> np.ndarray:
        """(H, W) bool: the covered texels, row 0 = bottom."""
        m = np.zeros(self.width * self.height, bool)
        m[self.texel] = True
        return m.reshape(self.height, self.width)

    def release_surface(self, keep_geometry: bool = False) -> None:
        """Drop the per-texel surface arrays (~110 B a texel), keeping the layout
        (texel, coverage, size, stats): what a set needs once its rays are traced.
        ``keep_geometry``: keep position, normal and geo_normal (the kernel
        points share them), drop the rest. Afterwards the dropped fields are None."""
        self.tri = self.bary = self.normal_mapped = None
        if not keep_geometry:
            self.release_geometry()

    def release_geometry(self) -> None:
        """Drop position, normal and geo_normal (72 B a texel), keeping what the
        materials are evaluated from (tri, bary) and the layout."""
        self.position = self.normal = self.geo_normal = None


def face_normals(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) unit face normals by winding (zero where degenerate) and (T,) areas."""
    P = np.asarray(positions, dtype=np.float64)
    c = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    ln = np.linalg.norm(c, axis=1)
    scale = np.max(np.abs(P)) if P.size else 1.0
    ok = ln > 1e-14 * max(scale, 1e-300) ** 2
    n = np.zeros_like(c)
    n[ok] = c[ok] / ln[ok, None]
    return n, 0.5 * ln


def _normalize(v):
    ln = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(ln > 0, ln, 1.0), ln[..., 0]


def perturb_normals(N, tangent, sign, encoded_rgb, strength: float) -> tuple[np.ndarray, np.ndarray]:
    """Tangent-space normal mapping (the viewport shader's normal_mapped()).

    N (n, 3) unit interpolated normals; tangent (n, 3) interpolated tangents;
    sign (n,) bitangent signs (< 0 means -1); encoded_rgb (n, 3) map values
    in 0..1; strength as the Normal Map node's. Returns (normals, ok): where the
    tangent or the mapped vector vanishes the input normal is kept (ok False).
    """
    ts = 2.0 * np.asarray(encoded_rgb, np.float64) - 1.0
    # Gram-Schmidt keeps T orthogonal to the interpolated normal.
    tan = tangent - N * np.einsum("nc,nc->n", tangent, N)[:, None]
    tan, tl = _normalize(tan)
    B = np.where(np.asarray(sign) < 0, -1.0, 1.0)[:, None] * np.cross(N, tan)
    mapped_n, ml = _normalize(ts[:, :1] * tan + ts[:, 1:2] * B + ts[:, 2:3] * N)
    good = (tl > 1e-12) & (ml > 1e-12)
    blended, _ = _normalize(N + (mapped_n - N) * max(strength, 0.0))
    return np.where(good[:, None], blended, N), good


def apply_normal_maps(sc: Scene, tri, bary, n_interp) -> tuple[np.ndarray, np.ndarray]:
    """Shading normals from tangent-space normal maps where triangles have one."""
    out = n_interp.copy()
    mapped = np.zeros(tri.shape, bool)
    if sc.nm_index is None:
        return out, mapped
    idx = sc.nm_index[tri]
    for m, nm in enumerate(sc.normal_maps):
        sel = np.flatnonzero(idx == m)
        if sel.size == 0:
            continue
        t, b = tri[sel], bary[sel]
        uv = np.einsum("nk,nkc->nc", b, sc.nm_uvs[t])
        tan = np.einsum("nk,nkc->nc", b, sc.tangents[t, :, :3].astype(np.float64))
        new, good = perturb_normals(n_interp[sel], tan, sc.tangents[t, 0, 3],
                                    bilinear_repeat(nm.pixels, uv), nm.strength)
        out[sel[good]] = new[good]
        mapped[sel[good]] = True
    return out, mapped


def build_gbuffer(sc: Scene, set_index: int, *, normal_maps: bool = True, executor=None,
                  bands: int = 2, cancel=None, resolution: tuple[int, int] | None = None) -> GBuffer:
    """Rasterise set ``set_index`` of ``sc`` and fill its G-buffer.

    ``resolution`` (width, height) replaces the set's own (the bounce textures'
    coarser grid over the same UV layout). With an ``executor`` (a thread
    pool), ``bands`` row bands are built in parallel (numpy releases the GIL)
    and merged; the result is the same. ``cancel`` (has is_set()) is checked
    as the rasteriser goes: parallel.Cancelled.
    """
    w, h = (int(v) for v in (resolution if resolution is not None else sc.set_resolution[set_index]))
    # Bands of at most BAND_TEXELS: the rasteriser's per-band arrays stay bounded
    # (a 4096² set in two bands held 1.5 GB of them beside the G-buffer).
    bands = max(bands, -(-w * h // BAND_TEXELS))
    if executor is None or bands < 2 or h < 2 * bands:
        return _build_gbuffer(sc, set_index, normal_maps, None, cancel, (w, h))
    cuts = np.linspace(0, h, bands + 1).astype(int)
    parts = list(executor.map(lambda k: _build_gbuffer(sc, set_index, normal_maps, (cuts[k], cuts[k + 1]),
                                                       cancel, (w, h)), range(bands)))
    return merge_gbuffers(parts)


def merge_gbuffers(parts: list[GBuffer]) -> GBuffer:
    """Concatenate G-buffers of disjoint row bands (in row order). The parts
    give up each array as it is merged (their fields become None), so the
    merge holds one field twice at most, not the whole G-buffer."""
    def cat(name):
        out = np.concatenate([getattr(p, name) for p in parts])
        for p in parts:
            setattr(p, name, None)
        return out
    stats = {}
    for k, v in parts[0].stats.items():
        if isinstance(v, list):
            stats[k] = sorted(set().union(*[p.stats[k] for p in parts]))
        else:
            stats[k] = sum(p.stats[k] for p in parts)
    # A zero-area triangle spans both bands' candidate lists; count it once.
    stats["zero_area_uv_triangles"] = parts[0].stats["zero_area_uv_triangles"]
    p0 = parts[0]
    return GBuffer(p0.set_index, p0.width, p0.height, cat("texel"), cat("tri"), cat("bary"),
                   cat("position"), cat("normal"), cat("geo_normal"), cat("coverage"),
                   cat("normal_mapped"), stats)


def _build_gbuffer(sc: Scene, set_index: int, normal_maps: bool, rows, cancel, size) -> GBuffer:
    tris = sc.triangles_of_set(set_index)
    w, h = size
    r = rasterize(sc.uvs[tris], w, h, rows, cancel)
    tri = tris[r.tri]
    bary = r.bary
    pos = np.einsum("nk,nkc->nc", bary, sc.positions[tri])
    n_s, ns_len = _normalize(np.einsum("nk,nkc->nc", bary, sc.normals[tri].astype(np.float64)))
    fn, _ = face_normals(sc.positions[tris])
    n_g = fn[r.tri]
    g_ok = np.any(n_g != 0, axis=1)
    s_ok = ns_len > 1e-6
    n_s = np.where(s_ok[:, None], n_s, n_g)
    n_g = np.where(g_ok[:, None], n_g, n_s)
    keep = s_ok | g_ok
    # Face normal to the shaded side.
    flip = np.einsum("nc,nc->n", n_g, n_s) < 0
    n_g[flip] *= -1.0
    mapped = np.zeros(tri.shape, bool)
    if normal_maps:
        n_s, mapped = apply_normal_maps(sc, tri, bary, n_s)
        cos = np.einsum("nc,nc->n", n_s, n_g)
        # Only normal-mapped texels are bent: a smooth-shading normal that grazes
        # the face is legitimate and is baked as it is (the horizon test clips it).
        low = (cos < MIN_HORIZON_COS) & mapped
        if low.any():
            tang, _ = _normalize(n_s[low] - cos[low, None] * n_g[low])
            n_s[low] = (MIN_HORIZON_COS * n_g[low]
                        + np.sqrt(1 - MIN_HORIZON_COS ** 2) * tang)
    overlap_objects = sorted({sc.object_names[o] for o in sc.object_id[tris[r.overlap_triangles]]})
    stats = {
        "texels": int(keep.sum()),
        "centre_texels": r.centre_texels,
        "conservative_texels": r.conservative_texels,
        "overlap_texels": r.overlap_texels,
        "overlap_objects": overlap_objects,
        "zero_area_uv_triangles": int(r.zero_area_triangles.size),
        "dropped_texels": int((~keep).sum()),
        "normal_mapped_texels": int(mapped[keep].sum()),
    }
    k = keep
    return GBuffer(set_index, w, h, r.texel[k], tri[k], bary[k], pos[k], n_s[k], n_g[k],
                   r.coverage[k], mapped[k], stats)
