"""UV unwrapping with xatlas (in a child process, no Blender needed).

``unwrap(meshes, resolution, padding)`` lays out one or several indexed meshes
in a single non-overlapping atlas (one texture set) and returns per-triangle
corner UVs in [0, 1]. xatlas treats its resolution as a hint, so the atlas is
re-packed with a lower texel density until it fits ``resolution`` exactly
(a bounded number of tries), keeping ``padding`` texels between charts
(at least, and about one more: :func:`xatlas_padding`); a
small texture that cannot hold the charts with that padding is retried with
half the padding, down to 0, before giving up.

``unwrap_loops`` does the same for polygon meshes stored as Blender stores
them (:class:`LoopMesh`): one UV per loop (polygon corner), shared by every
triangle of the polygon.
"""
from __future__ import annotations

import dataclasses
import os
import subprocess
import tempfile

import numpy as np

from ..base.child import child_env, python_executable


def xatlas_padding(gap: int) -> int:
    """xatlas's PackOptions.padding for charts ``gap`` texels apart or more.
    xatlas pads each chart on every side, and with ``bilinear`` adds one texel
    more between charts: charts end 2 p + 1 texels apart (measured on the UV
    map: padding 6 gave 13-texel gaps, twice the space asked, issue 53)."""
    return max(0, -(-(int(gap) - 1) // 2))


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


@dataclasses.dataclass
class LoopMesh:
    """A polygon mesh as Blender stores it: polygons of loops (corners), each
    loop a vertex, and the triangles the polygons are cut into."""

    positions: np.ndarray           # (L, 3) float: each loop's vertex position
    triangles: np.ndarray           # (T, 3) int: loop ids of each triangle
    loop_vertex: np.ndarray         # (L,) int: each loop's vertex
    triangle_polygon: np.ndarray    # (T,) int: the polygon of each triangle
    polygon_start: np.ndarray       # (P,) int: each polygon's first loop
    polygon_total: np.ndarray       # (P,) int: each polygon's loop count


def unwrap_loops(meshes: list[LoopMesh], resolution: int, *, padding: int = 4) -> list[np.ndarray]:
    """Lay ``meshes`` out in one atlas (xatlas, as :func:`unwrap`): per mesh,
    per-loop UVs (L, 2) float64 in [0, 1].

    xatlas gets a vertex per loop: it charts them like welded vertices (it
    finds coincident positions) but never across a UV seam of the mesh. It
    works on triangles, so a polygon whose triangles land in different charts
    is laid out on its own (:func:`loop_uvs`) and every chart of the meshes is
    packed again, together.
    """
    uvs = unwrap([(m.positions, m.triangles) for m in meshes], resolution, padding=padding)
    layouts = [loop_uvs(m, uv) for m, uv in zip(meshes, uvs)]
    if not any(alone.any() for _, alone in layouts):
        return [per_loop for per_loop, _ in layouts]
    # A chart is the loops that share a mesh, a vertex and a UV; a polygon laid
    # out on its own is a chart of its own (its loops get keys nothing shares).
    keys, faces, base = [], [], 0
    for i, ((per_loop, alone), m) in enumerate(zip(layouts, meshes)):
        n = len(m.loop_vertex)
        key = np.concatenate([np.full((n, 1), i, np.float64), m.loop_vertex[:, None].astype(np.float64),
                              np.round(per_loop, 7)], axis=1)
        key[alone, 1] = -1 - np.flatnonzero(alone)
        keys.append(key)
        faces.append(m.triangles + base)
        base += n
    _, first, ids = np.unique(np.concatenate(keys), axis=0, return_index=True, return_inverse=True)
    flat = np.concatenate([per_loop for per_loop, _ in layouts])
    packed = pack_uv_charts(flat[first], ids.reshape(-1)[np.concatenate(faces)], resolution,
                            padding=padding).reshape(-1, 2)
    flat[np.concatenate(faces).reshape(-1)] = packed
    out, base = [], 0
    for m in meshes:
        out.append(flat[base:base + len(m.loop_vertex)])
        base += len(m.loop_vertex)
    return out


def loop_uvs(mesh: LoopMesh, tri_uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-loop UVs from per-triangle-corner UVs (T, 3, 2): (per-loop UVs
    (L, 2) float64, loops of polygons that must become charts of their own
    (L,) bool).

    One UV per loop is shared by all triangles of a polygon; a layout of
    triangles may put two triangles of a non-planar quad in different charts.
    Such a polygon is projected along its Newell normal (the plane that folds
    it least: a largest-triangle plane can turn a warped quad into a bow tie
    whose triangles overlap), at the texel density its triangles got (UV area
    over 3D area), and marked to be a chart of its own: where it is, it would
    overlap its neighbours, so the caller packs again.
    """
    tris = mesh.triangles
    per_loop = np.zeros((len(mesh.loop_vertex), 2), np.float64)
    per_loop[tris.reshape(-1)] = tri_uv.reshape(-1, 2)
    alone = np.zeros(len(mesh.loop_vertex), bool)
    conflict = np.abs(per_loop[tris] - tri_uv).max(axis=(1, 2)) > 1e-7      # per triangle
    poly = mesh.triangle_polygon
    for p in np.unique(poly[conflict]):
        ts = np.flatnonzero(poly == p)
        loops = np.arange(mesh.polygon_start[p], mesh.polygon_start[p] + mesh.polygon_total[p])
        Q = mesh.positions[loops]
        nrm = np.cross(Q, np.roll(Q, -1, axis=0)).sum(axis=0)
        nrm /= max(np.linalg.norm(nrm), 1e-300)
        e1 = np.cross(nrm, [1.0, 0.0, 0.0] if abs(nrm[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(nrm, e1)
        P = mesh.positions[tris[ts]]
        area3 = 0.5 * np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1).sum()
        U = tri_uv[ts]
        a, b = U[:, 1] - U[:, 0], U[:, 2] - U[:, 0]
        # written out: numpy 2 (Blender 5.1+) refuses np.cross of 2-vectors
        area2 = 0.5 * np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]).sum()
        scale = np.sqrt(area2 / area3) if area3 > 0 and area2 > 0 else 1.0
        d = Q - Q.mean(axis=0)
        per_loop[loops] = scale * np.stack([d @ e1, d @ e2], axis=1)
        alone[loops] = True
    return per_loop, alone


#: Tries of the xatlas child before an unwrap fails (a child that crashes or
#: hangs is started again; xatlas is deterministic, its thread pool is not).
CHILD_TRIES = 3


def _child_timeout(meshes) -> float:
    """Seconds an xatlas child may take: ~10x a measured 0.2 ms per face, and a minute."""
    return 60.0 + 2e-3 * sum(int(np.asarray(f).shape[0]) for _, f in meshes)


def _unwrap(meshes, resolution, padding, max_tries, uv_mesh=False):
    """:func:`unwrap_here` in a child process (``python -m
    prtt_addon.core.texels.xatlas_child``). xatlas's thread pool has crashed
    (a segfault) and deadlocked (joining its threads as an Atlas is
    destroyed) in this process, which in Blender is Blender itself: a child
    that dies or outlives its time is started again, up to CHILD_TRIES."""
    with tempfile.TemporaryDirectory(prefix="prtt-xatlas-") as d:
        inp, out = os.path.join(d, "in.npz"), os.path.join(d, "out.npz")
        arrays = {f"v{i}": np.asarray(v) for i, (v, _) in enumerate(meshes)}
        arrays.update({f"f{i}": np.asarray(f) for i, (_, f) in enumerate(meshes)})
        np.savez(inp, n=len(meshes), resolution=int(resolution), padding=int(padding), max_tries=int(max_tries),
                 uv_mesh=bool(uv_mesh), **arrays)
        why, timeout = "", _child_timeout(meshes)
        for _ in range(CHILD_TRIES):
            try:
                r = subprocess.run([python_executable(), "-m", "prtt_addon.core.texels.xatlas_child", inp, out],
                                   env=child_env(), capture_output=True, text=True, timeout=timeout)
            except subprocess.TimeoutExpired:
                why = f"xatlas did not finish in {timeout:.0f} s"
                continue
            if r.returncode == 0:
                with np.load(out) as z:
                    return [np.array(z[f"uv{i}"]) for i in range(len(meshes))]
            if r.returncode == UNWRAP_ERROR_EXIT:
                raise UnwrapError(r.stderr.strip().splitlines()[-1] if r.stderr.strip() else "xatlas failed")
            why = f"xatlas exited with {r.returncode}: {r.stderr.strip()[-300:]}"
    raise UnwrapError(f"the unwrap failed {CHILD_TRIES} times ({why})")


#: The child's exit status for an UnwrapError (its message is its last stderr line).
UNWRAP_ERROR_EXIT = 3


def unwrap_here(meshes, resolution, padding, max_tries, uv_mesh=False, keep: list | None = None):
    """Atlas several meshes together, in this process.

    meshes : list of (vertices (V, 3) float, faces (F, 3) int), or with
    ``uv_mesh`` of (uvs (V, 2), faces): existing charts, only packed.
    Returns for each mesh its corner UVs (F, 3, 2) float64 in [0, 1], in the
    order of its faces. ``keep``: a list that holds every xatlas Atlas made,
    so none is destroyed here (the child exits without destroying them).
    """
    import xatlas

    tpu = 0.0
    for _ in range(max_tries):
        atlas = xatlas.Atlas()
        if keep is not None:
            keep.append(atlas)
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
        po.padding = xatlas_padding(padding)
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
    for mi, (_v, f) in enumerate(meshes):
        vmap, idx, uv = atlas[mi]
        # xatlas returns UVs normalised by its own width/height; rescale to ours.
        uv = uv.astype(np.float64) * np.array([w / resolution, h / resolution])
        corner_uv = uv[idx.astype(np.int64)]             # (F', 3, 2)
        # xatlas keeps face order; map back to the input faces.
        if corner_uv.shape[0] != np.asarray(f).shape[0]:
            raise UnwrapError("xatlas changed the face count")
        out.append(np.clip(corner_uv, 0.0, 1.0))
    return out
