"""A numpy reference for the viewport preview: the same picture, computed per
pixel by ray casting and the reference shading model (core/shading/shade.py).

Independent of the GPU path where it matters: visibility comes from Embree
rays through the pixel centres instead of rasterisation, attributes from the
hit's barycentrics in float64, shading from ``core.shading.shade`` and
``core.shading.materials``, texture reads from ``core.texels.texsample`` / ``gbuffer``.
Shared with the GPU path: the PreviewScene (the same meshes, materials and
texture values) and the documented conventions.

Pixels follow OpenGL: pixel (i, j), j from the bottom, has its centre at NDC
((2i + 1) / W - 1, (2j + 1) / H - 1). Attribute interpolation on a GPU is
perspective-correct, which is what barycentrics of the ray hit are.

Pixels whose centre lies within ``edge_margin`` pixels of an edge of the hit
triangle are flagged ambiguous: rasterisation rules and fixed-point snapping
may give them to the neighbouring triangle (or the background), so accuracy
comparisons leave them out (tests count them).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..bake.estimators import sun_edge
from ..bake.estimators.raytrace import RayScene
from ..bake.estimators.transfer import Points, TransferSettings, bake_points
from ..shading.materials import ShadingParams, derive_from_f0
from ..shading.shade import lamp_direct, shade, sun_direct
from ..texels.gbuffer import perturb_normals
from ..texels.texsample import bilinear, bilinear_repeat
from . import pack as pp


@dataclasses.dataclass
class PixelHits:
    """Per pixel (H, W): hit mask, mesh index, triangle in mesh, barycentrics
    (H, W, 3), distance to the nearest triangle edge in pixels."""

    hit: np.ndarray
    mesh: np.ndarray
    tri: np.ndarray
    bary: np.ndarray
    edge_px: np.ndarray


def pixel_rays(view_projection, width: int, height: int):
    """World-space ray origins (on the near plane) and unit directions, (H*W, 3)."""
    inv = np.linalg.inv(np.asarray(view_projection, np.float64))
    i, j = np.meshgrid(np.arange(width), np.arange(height))
    x = (2.0 * i.ravel() + 1.0) / width - 1.0
    y = (2.0 * j.ravel() + 1.0) / height - 1.0
    near = np.stack([x, y, -np.ones_like(x), np.ones_like(x)], axis=1) @ inv.T
    far = np.stack([x, y, np.ones_like(x), np.ones_like(x)], axis=1) @ inv.T
    near = near[:, :3] / near[:, 3:]
    far = far[:, :3] / far[:, 3:]
    d = far - near
    return near, d / np.linalg.norm(d, axis=1, keepdims=True)


def _screen(points, view_projection, width, height):
    h = np.concatenate([points, np.ones(points.shape[:-1] + (1,))], axis=-1) @ np.asarray(view_projection).T
    ndc = h[..., :2] / h[..., 3:]
    return np.stack([(ndc[..., 0] + 1) * 0.5 * width, (ndc[..., 1] + 1) * 0.5 * height], axis=-1)


def trace_pixels(ps: pp.PreviewScene, view_projection, width: int, height: int) -> PixelHits:
    """Cast one ray per pixel centre against every mesh of ``ps``."""
    tris = [m.world_corners("positions") for m in ps.meshes]
    owner = np.concatenate([np.full(t.shape[0], k) for k, t in enumerate(tris)]) if tris else np.zeros(0, int)
    local = np.concatenate([np.arange(t.shape[0]) for t in tris]) if tris else np.zeros(0, int)
    H, W = height, width
    hit = np.zeros(H * W, bool)
    mesh = np.full(H * W, -1)
    tri = np.full(H * W, -1)
    bary = np.zeros((H * W, 3))
    edge = np.zeros(H * W)
    if tris:
        allP = np.concatenate(tris)
        rs = RayScene(allP)
        org, d = pixel_rays(view_projection, W, H)
        prim, u, v, _ = rs.intersect(rs.to_local(org), d.astype(np.float32))
        hit = prim >= 0
        g = prim[hit]
        mesh[hit], tri[hit] = owner[g], local[g]
        bary[hit] = np.stack([1.0 - u[hit] - v[hit], u[hit], v[hit]], axis=1)
        # Distance (pixels) from the pixel centre to the nearest edge of its triangle.
        S = _screen(allP[g], view_projection, W, H)                   # (n, 3, 2)
        jj, ii = np.divmod(np.flatnonzero(hit), W)
        c = np.stack([ii + 0.5, jj + 0.5], axis=1)
        dist = np.full(g.shape[0], np.inf)
        for a, b in ((0, 1), (1, 2), (2, 0)):
            e = S[:, b] - S[:, a]
            ln = np.linalg.norm(e, axis=1)
            cross = e[:, 0] * (c[:, 1] - S[:, a, 1]) - e[:, 1] * (c[:, 0] - S[:, a, 0])
            dist = np.minimum(dist, np.abs(cross) / np.where(ln > 0, ln, 1e-300))
        edge[hit] = dist
    return PixelHits(hit.reshape(H, W), mesh.reshape(H, W), tri.reshape(H, W), bary.reshape(H, W, 3),
                     edge.reshape(H, W))


def _interp(corners, tri, bary):
    return np.einsum("nk,nkc->nc", bary, corners[tri])


def _tri_materials(m: pp.DrawMesh) -> np.ndarray:
    """(T,) material index of each triangle of m (from its draw ranges)."""
    out = np.full(m.triangles, -1)
    for mi, first, count in m.ranges:
        out[first:first + count] = mi
    return out


def _params(ps: pp.PreviewScene, mid: np.ndarray, muv: np.ndarray) -> ShadingParams:
    """Shading parameters of points with materials ``mid`` and material UVs
    ``muv`` (core.shading.materials' formulas, textures read like the shader)."""
    n = mid.shape[0]
    base = np.zeros((n, 3))
    metal, rough, f0 = np.zeros(n), np.zeros(n), np.zeros(n)
    for mi in np.unique(mid):
        sel = mid == mi
        mat = ps.materials[mi] if 0 <= mi < len(ps.materials) else pp.PreviewMaterial()
        base[sel] = mat.base_color
        metal[sel], rough[sel], f0[sel] = mat.metallic, mat.roughness, mat.f0
        if mat.base_texture >= 0:
            base[sel] = bilinear_repeat(_file_order(ps, mat.base_texture), muv[sel])[:, :3]
        if mat.roughness_texture >= 0:
            rough[sel] = bilinear_repeat(_file_order(ps, mat.roughness_texture), muv[sel])[:, 0]
    return derive_from_f0(np.maximum(base, 0.0), np.clip(metal, 0.0, 1.0), rough, f0)


def _file_order(ps: pp.PreviewScene, i: int) -> np.ndarray:
    """Image i as the GPU holds it (RGBA, grey replicated), back in file order."""
    return pp.image_rgba(ps.images[i])[::-1]


def _texture_pm(tex_hwk: np.ndarray) -> np.ndarray:
    H, W = tex_hwk.shape[:2]
    return np.ascontiguousarray(tex_hwk.reshape(H * W, -1), np.float32)


def reference_image(ps: pp.PreviewScene, mode: str, view_projection, camera, width: int, height: int, *,
                    exposure: float = 1.0, hits: PixelHits | None = None) -> tuple[np.ndarray, PixelHits]:
    """(H, W, 4) float64 linear RGBA (row 0 at the bottom) and the pixel hits."""
    hits = hits or trace_pixels(ps, view_projection, width, height)
    img = np.zeros((height, width, 4))
    cam = np.asarray(camera, np.float64)
    vertex_mode = mode.startswith("vertex-")
    method = mode.replace("vertex-", "")
    for k, m in enumerate(ps.meshes):
        sel = np.flatnonzero((hits.mesh == k).ravel())
        s = ps.sets.get(m.set_name)
        if sel.size == 0 or s is None:
            continue
        tri = hits.tri.ravel()[sel]
        bary = hits.bary.reshape(-1, 3)[sel]
        transfer = s.load_transfer()
        H, W, K = transfer.shape
        # the sun (and its bounce) is drawn in the fragment modes
        lit = ps.light if vertex_mode else ps.bounce_light
        bounce = s.load_bounce(K, lit) if ps.use_bounces and s.has_bounce else None
        if vertex_mode:
            color = _vertex_colors(ps, m, s, method, cam, bounce)[m.indices[tri]]     # (n, 3, 3)
            rgb = np.einsum("nk,nkc->nc", bary, color)
        else:
            rgb = _fragment_colors(ps, m, method, cam, transfer, bounce, tri, bary, s)
        flat = img.reshape(-1, 4)
        flat[sel, :3] = rgb * exposure
        flat[sel, 3] = 1.0
    return img, hits


def _view_vectors(cam, P):
    if cam[3] > 0.5:
        d = cam[:3] - P
        ln = np.linalg.norm(d, axis=1, keepdims=True)
        return np.where(ln > 0, d / np.where(ln > 0, ln, 1.0), [0.0, 0.0, 1.0])
    return np.broadcast_to(cam[:3], P.shape).copy()


def _fragment_colors(ps, m, method, cam, transfer, bounce, tri, bary, s=None):
    P = _interp(m.world_corners("positions"), tri, bary)
    v = _view_vectors(cam, P)
    n = _shading_normals(ps, m, tri, bary, v)
    muv = _interp(m.mat_uv[m.indices].astype(np.float64), tri, bary)
    params = _params(ps, _tri_materials(m)[tri], muv)
    uv = _interp(m.uv[m.indices].astype(np.float64), tri, bary)
    H, W, K = transfer.shape
    T = bilinear(_texture_pm(transfer), W, H, uv).astype(np.float64)
    bounces = []
    if bounce is not None:
        Hb, Wb = bounce.shape[:2]           # the bounce grid may be coarser than the transfer's
        B = bilinear(_texture_pm(bounce), Wb, Hb, uv).astype(np.float64).reshape(-1, 3, K)
        bounces = [B]
    rgb = shade(T, n, v, ps.light, params, bounces=bounces, method=method)
    if ps.sun is not None and s is not None and s.sun:
        # The sun's direct light with its baked mask, as the fragment shader adds it (PRTT_SUN).
        tex = s.load_sun_texture()
        Hm, Wm = tex.shape[:2]
        C = 1 if tex.ndim == 2 else tex.shape[2]
        filtered = bilinear(np.ascontiguousarray(tex.reshape(-1, C), np.float32), Wm, Hm, uv)
        vis = sun_edge.visible(filtered[:, 0] if C == 1 else filtered)
        rgb = rgb + sun_direct(n, v, params, vis, ps.sun.direction, ps.sun.irradiance, ps.sun.angle, method=method)
    if ps.lamps and s is not None and s.lamps:
        # The lamps' direct light with their baked masks, as the fragment shader adds it (PRTT_LAMPS).
        tex = s.load_lamp_texture()
        Hm, Wm = tex.shape[:2]
        masks = bilinear(np.ascontiguousarray(tex.reshape(-1, 4), np.float32), Wm, Hm, uv)
        rgb = rgb + lamp_direct(P, n, v, params, masks, ps.lamps, method=method)
    return rgb


def _shading_normals(ps, m, tri, bary, v):
    """Interpolated (normal-mapped) unit normals as the fragment shader forms them."""
    Nc = m.world_corners("normals")
    n = _interp(Nc, tri, bary)
    ln2 = np.einsum("nc,nc->n", n, n)
    # Where interpolated normals cancel, the shader uses the face normal facing the viewer.
    Pc = m.world_corners("positions")[tri]
    face = np.cross(Pc[:, 1] - Pc[:, 0], Pc[:, 2] - Pc[:, 0])
    fl = np.linalg.norm(face, axis=1, keepdims=True)
    face = np.where(fl > 0, face / np.where(fl > 0, fl, 1.0), v)
    face = np.where((np.einsum("nc,nc->n", face, v) < 0)[:, None], -face, face)
    n = np.where((ln2 > 1e-12)[:, None], n / np.sqrt(np.maximum(ln2, 1e-300))[:, None], face)
    mid = _tri_materials(m)[tri]
    if ps.normal_maps:
        for mi in np.unique(mid):
            mat = ps.materials[mi] if 0 <= mi < len(ps.materials) else None
            if mat is None or mat.normal_texture < 0:
                continue
            sel = mid == mi
            tan = _interp(m.world_corners("tangents"), tri[sel], bary[sel])
            nuv = _interp(m.nm_uv[m.indices].astype(np.float64), tri[sel], bary[sel])
            rgb = bilinear_repeat(_file_order(ps, mat.normal_texture), nuv)[:, :3]
            n[sel], _ = perturb_normals(n[sel], tan[:, :3], tan[:, 3], rgb, mat.normal_strength)
    return n


def _vertex_colors(ps, m, s, method, cam, bounce):
    """Shaded colour of every vertex of m (V, 3), as the vertex baselines compute it."""
    coeffs = s.load_vertex()
    M = np.asarray(m.matrix, np.float64)
    P = m.positions.astype(np.float64) @ M[:3, :3].T + M[:3, 3]
    n = m.normals.astype(np.float64) @ pp.normal_matrix(M)[:3, :3].T
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(ln ** 2 > 1e-12, n / np.where(ln > 0, ln, 1.0), [0.0, 0.0, 1.0])
    v = _view_vectors(cam, P)
    V = P.shape[0]
    # Materials per vertex: a vertex belongs to one material range (corners are
    # merged only within identical attributes, and ranges are per triangle).
    vert_mat = np.full(V, -1)
    for mi, first, count in m.ranges:
        vert_mat[m.indices[first:first + count].ravel()] = mi
    params = _params(ps, vert_mat, m.mat_uv.astype(np.float64))
    T = coeffs[np.round(m.vidx).astype(np.int64)].astype(np.float64)
    bounces = []
    if bounce is not None:
        H, W, _, K = bounce.shape
        bounces = [bilinear(_texture_pm(bounce), W, H, m.uv.astype(np.float64)).astype(np.float64).reshape(-1, 3, K)]
    return shade(T, n, v, ps.light, params, bounces=bounces, method=method)


def traced_reference(ps: pp.PreviewScene, view_projection, camera, width: int, height: int, *,
                     rays: int = 1024, exposure: float = 1.0, hits: PixelHits | None = None,
                     extra_occluders=None, seed: int = 7) -> tuple[np.ndarray, PixelHits]:
    """Ground truth without textures or vertices: at every pixel's surface point
    the transfer is ray traced (``rays`` Sobol rays, core.bake.estimators.transfer) and shaded
    with TPFL (the model is exact in T, so this is "PRT with infinitely fine
    transfer sampling"; no bounce light). Returns (H, W, 4) and the hits."""
    hits = hits or trace_pixels(ps, view_projection, width, height)
    img = np.zeros((height, width, 4))
    cam = np.asarray(camera, np.float64)
    tris = [m.world_corners("positions") for m in ps.meshes]
    if extra_occluders is not None:
        tris.append(np.asarray(extra_occluders, np.float64))
    rs = RayScene(np.concatenate(tris))
    flat = img.reshape(-1, 4)
    for k, m in enumerate(ps.meshes):
        sel = np.flatnonzero((hits.mesh == k).ravel())
        if sel.size == 0:
            continue
        tri = hits.tri.ravel()[sel]
        bary = hits.bary.reshape(-1, 3)[sel]
        P = _interp(m.world_corners("positions"), tri, bary)
        v = _view_vectors(cam, P)
        n = _shading_normals(ps, m, tri, bary, v)
        Pc = m.world_corners("positions")[tri]
        g = np.cross(Pc[:, 1] - Pc[:, 0], Pc[:, 2] - Pc[:, 0])
        g /= np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-300)
        g = np.where((np.einsum("nc,nc->n", g, n) < 0)[:, None], -g, g)
        pts = Points(P, n, g, np.arange(sel.size, dtype=np.int64) + (np.int64(k) << 40),
                     np.zeros(sel.size, bool))
        T, _ = bake_points(rs, pts, TransferSettings(bands=ps.bands, rays=rays, seed=seed))
        muv = _interp(m.mat_uv[m.indices].astype(np.float64), tri, bary)
        params = _params(ps, _tri_materials(m)[tri], muv)
        flat[sel, :3] = shade(T.astype(np.float64), n, v, ps.light, params, method="tpfl") * exposure
        flat[sel, 3] = 1.0
    return img, hits


def relative_error(gpu_rgb: np.ndarray, ref_rgb: np.ndarray, floor: float) -> np.ndarray:
    """Per-pixel max over channels of |gpu - ref| / max(|ref|, floor)."""
    return np.max(np.abs(gpu_rgb - ref_rgb) / np.maximum(np.abs(ref_rgb), floor), axis=-1)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World -> camera (OpenGL: looking down -Z) view matrix."""
    eye, target, up = (np.asarray(a, np.float64) for a in (eye, target, up))
    f = target - eye
    f /= np.linalg.norm(f)
    s = np.cross(f, up)
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    M = np.eye(4)
    M[0, :3], M[1, :3], M[2, :3] = s, u, -f
    M[:3, 3] = -M[:3, :3] @ eye
    return M


def perspective(fov_y_deg: float, aspect: float, near: float = 0.05, far: float = 200.0) -> np.ndarray:
    """OpenGL perspective projection."""
    f = 1.0 / math.tan(math.radians(fov_y_deg) / 2.0)
    return np.array([[f / aspect, 0, 0, 0], [0, f, 0, 0],
                     [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)], [0, 0, -1, 0]])
