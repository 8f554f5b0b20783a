"""UV unwrapping with xatlas (in-process, no Blender needed).

``unwrap(meshes, resolution, padding)`` lays out one or several indexed meshes
in a single non-overlapping atlas (one texture set) and returns per-triangle
corner UVs in [0, 1]. xatlas treats its resolution as a hint, so the atlas is
re-packed with a lower texel density until it fits ``resolution`` exactly
(a bounded number of tries), keeping ``padding`` texels between charts; a
small texture that cannot hold the charts with that padding is retried with
half the padding, down to 0, before giving up.
"""
from __future__ import annotations

import numpy as np


class UnwrapError(RuntimeError):
    """xatlas could not lay the meshes out in one atlas."""


def unwrap(meshes: list[tuple[np.ndarray, np.ndarray]], resolution: int, *,
           padding: int = 4, max_tries: int = 6) -> list[np.ndarray]:
    """See the module doc; raises UnwrapError if even padding 0 does not fit."""
    if resolution < 8:
        raise ValueError(f"atlas resolution must be >= 8, got {resolution}")
    pad = int(padding)
    while True:
        try:
            return _unwrap(meshes, resolution, pad, max_tries)
        except UnwrapError as exc:
            if pad == 0 or "could not fit" not in str(exc):
                raise
            pad //= 2


def pack_uv_charts(uvs: np.ndarray, faces: np.ndarray, resolution: int, *, padding: int = 4,
                   max_tries: int = 6) -> np.ndarray:
    """Pack existing UV charts into one [0, 1] atlas without overlaps (xatlas's
    packer on a UV mesh): charts are the groups of faces connected through
    shared ``uvs`` rows; each is moved, rotated and scaled as a whole.

    uvs : (V, 2) float; faces : (F, 3) int indices into uvs.
    Returns (F, 3, 2) float64 corner UVs in [0, 1], in face order.
    """
    if resolution < 8:
        raise ValueError(f"atlas resolution must be >= 8, got {resolution}")
    pad = int(padding)
    while True:
        try:
            return _unwrap([(uvs, faces)], resolution, pad, max_tries, uv_mesh=True)[0]
        except UnwrapError as exc:
            if pad == 0 or "could not fit" not in str(exc):
                raise
            pad //= 2


def _unwrap(meshes, resolution, padding, max_tries, uv_mesh=False):
    """Atlas several meshes together.

    meshes : list of (vertices (V, 3) float, faces (F, 3) int), or with
    ``uv_mesh`` of (uvs (V, 2), faces): existing charts, only packed.
    Returns for each mesh its corner UVs (F, 3, 2) float64 in [0, 1], in the
    order of its faces.
    """
    import xatlas

    tpu = 0.0
    for _ in range(max_tries):
        atlas = xatlas.Atlas()
        for v, f in meshes:
            v = np.ascontiguousarray(v, dtype=np.float32)
            f = np.ascontiguousarray(f, dtype=np.uint32)
            if f.size == 0:
                raise UnwrapError("a mesh without faces cannot be unwrapped")
            if uv_mesh:
                atlas.add_uv_mesh(v, f)
            else:
                atlas.add_mesh(v, f)
        po = xatlas.PackOptions()
        po.resolution = int(resolution)
        po.padding = int(padding)
        po.bilinear = True
        po.texels_per_unit = float(tpu)
        atlas.generate(pack_options=po)
        w, h = atlas.width, atlas.height
        if atlas.atlas_count == 1 and w <= resolution and h <= resolution:
            break
        # Too big: shrink the density by the overshoot and pack again.
        cur = atlas.texels_per_unit
        tpu = cur * min(resolution / max(w, h, 1), 0.97) if atlas.atlas_count == 1 else cur * 0.7
    else:
        raise UnwrapError(f"xatlas could not fit the charts into one {resolution}x{resolution} atlas "
                          f"(padding {padding}); raise the resolution")
    out = []
    for mi, (v, f) in enumerate(meshes):
        vmap, idx, uv = atlas[mi]
        # xatlas returns UVs normalised by its own width/height; rescale to ours.
        uv = uv.astype(np.float64) * np.array([w / resolution, h / resolution])
        corner_uv = uv[idx.astype(np.int64)]             # (F', 3, 2)
        # xatlas keeps face order; map back to the input faces.
        if corner_uv.shape[0] != np.asarray(f).shape[0]:
            raise UnwrapError("xatlas changed the face count")
        out.append(np.clip(corner_uv, 0.0, 1.0))
    return out
