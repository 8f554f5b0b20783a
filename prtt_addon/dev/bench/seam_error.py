"""Error at UV seams (issue 53): the picture of a bake against a traced
ground truth, on pixels whose surface point lies within a texel of a UV
island's border, beside the pixels a few texels inside.

A torus (no texture, one grey material) is unwrapped in Blender with a
given method into one ``resolution``² set, baked (transfer only, no bounce)
and drawn by the preview's numpy twin (core/preview/reference.reference_image,
the same bilinear lookups as the GPU) in TPFL; the ground truth traces the
transfer at every pixel's surface point (traced_reference, ``ref_rays``).
Errors are |picture - truth| / mean(truth) per pixel: mean and 99th
percentile over the seam pixels and over the inner ones.
"""
from __future__ import annotations

import os
import tempfile

import numpy as np

#: Seam pixels: surface point within this many texels of an island border.
SEAM_TEXELS = 1.0
#: Inner pixels: between these distances from a border, in texels.
INNER_TEXELS = (2.5, 8.0)


def border_distance(uv_corners: np.ndarray, points: np.ndarray, resolution: int) -> np.ndarray:
    """(P,) distance in texels from UV points (P, 2) to the nearest island border
    edge (an edge of one triangle only, by its two UV corners) of uv_corners (T, 3, 2)."""
    from scipy.spatial import cKDTree  # test and bench dependency (requirements.txt)

    uv = np.asarray(uv_corners, np.float64) * resolution
    edges = np.stack([uv[:, [0, 1]], uv[:, [1, 2]], uv[:, [2, 0]]], axis=1).reshape(-1, 2, 2)
    key = np.round(edges * 1e4).astype(np.int64).reshape(-1, 4)
    a, b = key[:, :2], key[:, 2:]
    swap = (a[:, 0] > b[:, 0]) | ((a[:, 0] == b[:, 0]) & (a[:, 1] > b[:, 1]))
    canon = np.where(swap[:, None], np.concatenate([b, a], 1), key)
    _, inv, count = np.unique(canon, axis=0, return_inverse=True, return_counts=True)
    border = edges[count[inv.ravel()] == 1]
    # Points every 0.1 texel along the border edges: distances to within 0.05 texel.
    n = np.maximum(1, np.ceil(np.linalg.norm(border[:, 1] - border[:, 0], axis=1) / 0.1)).astype(int)
    t = np.concatenate([np.arange(k + 1) / k for k in n])
    seg = np.repeat(np.arange(len(border)), n + 1)
    samples = border[seg, 0] + t[:, None] * (border[seg, 1] - border[seg, 0])
    d, _ = cKDTree(samples).query(np.asarray(points, np.float64) * resolution)
    return d


def torus_errors(method: str, *, resolution: int = 512, rays: int = 512, ref_rays: int = 1024,
                 size=(480, 320), env: str = "forest", padding: int | None = None) -> dict:
    """Unwrap a torus with ``method`` (SMART, LIGHTMAP, XATLAS), bake, draw,
    compare: {"seam": {"mean", "p99", "pixels"}, "inner": {...}}. Needs bpy
    with the add-on registered."""
    import bpy

    from ...blender.scene.job import export_scene  # needs bpy
    from ...core.bake.pipeline.context import BakeSettings
    from ...core.bake.pipeline.runner import bake_scene
    from ...core.light.envmap import environment_light
    from ...core.preview.pack import from_core_scene
    from ...core.preview.reference import look_at, perspective, reference_image, traced_reference

    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.mesh.primitive_torus_add(major_segments=48, minor_segments=24, major_radius=1.0, minor_radius=0.35)
    bpy.ops.object.shade_smooth()
    ob = bpy.context.active_object
    st = bpy.context.scene.prtt
    st.resolution, st.texture_sets, st.unwrap_method = resolution, "ATLAS", method
    if padding is not None:
        st.padding = padding
    ob.select_set(True)
    if bpy.ops.prtt.unwrap() != {"FINISHED"}:
        raise RuntimeError("unwrap failed")
    sc = export_scene(bpy.context, with_light=False).scene
    light = environment_light(env, 5)
    w, h = size
    eye = np.array([2.2, -2.6, 2.0])
    vp = perspective(40.0, w / h) @ look_at(eye, (0.0, 0.0, 0.0))
    cam = np.array([*eye, 1.0])
    with tempfile.TemporaryDirectory(prefix="prtt-seams-") as d:
        bake_scene(sc, os.path.join(d, "b"), BakeSettings(rays=rays, bounces=0))
        ps = from_core_scene(sc, os.path.join(d, "b"), light, 5)
        img, hits = reference_image(ps, "tpfl", vp, cam, w, h)
        ref, _ = traced_reference(ps, vp, cam, w, h, rays=ref_rays, hits=hits)
    m = ps.meshes[0]
    sel = hits.hit & (hits.edge_px > 0.5) & (hits.mesh == 0)
    uvc = m.world_corners("uv")
    tri, bary = hits.tri[sel], hits.bary[sel]
    points = np.einsum("nk,nkc->nc", bary, uvc[tri])
    dist = border_distance(uvc, points, resolution)
    err = np.abs(img[..., :3][sel] - ref[..., :3][sel]).mean(axis=1) / ref[..., :3][sel].mean()
    out = {}
    for name, mask in (("seam", dist <= SEAM_TEXELS), ("inner", (dist >= INNER_TEXELS[0]) & (dist <= INNER_TEXELS[1]))):
        e = err[mask]
        out[name] = ({"mean": float(e.mean()), "p99": float(np.percentile(e, 99)), "pixels": int(mask.sum())}
                     if e.size else {"mean": float("nan"), "p99": float("nan"), "pixels": 0})
    return out
