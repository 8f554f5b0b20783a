"""Meshes without Blender: procedural primitives, OBJ loading, and assembling
them into a bake :class:`~prtt_addon.core.model.scene.Scene`.

Used by the tests, the benchmark scenes and the demo. Units are metres, Z up.
A :class:`Mesh` is indexed: vertices (V, 3), faces (F, 3); ``normals`` are
per-vertex (smooth shading) or None (flat: face normals); ``uvs`` optional
per-corner (F, 3, 2).
"""
from __future__ import annotations

import dataclasses
import math
import os

import numpy as np

from ...core.model.assembly import MeshPart, assemble_parts
from ...core.model.scene import Scene
from ...core.texels.unwrap import unwrap


@dataclasses.dataclass
class Mesh:
    vertices: np.ndarray                 # (V, 3) float64
    faces: np.ndarray                    # (F, 3) int64
    normals: np.ndarray | None = None    # (V, 3) smooth normals, None = flat
    uvs: np.ndarray | None = None        # (F, 3, 2) corner UVs

    def transformed(self, *, scale=1.0, rotate_z: float = 0.0, translate=(0.0, 0.0, 0.0)) -> "Mesh":
        s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))
        c, si = math.cos(rotate_z), math.sin(rotate_z)
        R = np.array([[c, -si, 0.0], [si, c, 0.0], [0.0, 0.0, 1.0]])
        v = (self.vertices * s) @ R.T + np.asarray(translate, dtype=np.float64)
        n = None
        if self.normals is not None:
            n = (self.normals / s) @ R.T
            ln = np.linalg.norm(n, axis=1, keepdims=True)
            n = n / np.where(ln > 0, ln, 1.0)
        return Mesh(v, self.faces.copy(), n, None if self.uvs is None else self.uvs.copy())

    def corner_positions(self) -> np.ndarray:
        return self.vertices[self.faces]

    def corner_normals(self) -> np.ndarray:
        if self.normals is not None:
            return self.normals[self.faces]
        P = self.corner_positions()
        fn = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
        ln = np.linalg.norm(fn, axis=1, keepdims=True)
        fn = fn / np.where(ln > 0, ln, 1.0)
        return np.repeat(fn[:, None, :], 3, axis=1)

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])


def merge(meshes: list[Mesh]) -> Mesh:
    """One mesh from several (normals kept only if all are smooth)."""
    vs, fs, ns, off = [], [], [], 0
    smooth = all(m.normals is not None for m in meshes)
    for m in meshes:
        vs.append(m.vertices)
        fs.append(m.faces + off)
        if smooth:
            ns.append(m.normals)
        off += m.vertices.shape[0]
    return Mesh(np.concatenate(vs), np.concatenate(fs), np.concatenate(ns) if smooth else None)


# --- primitives ------------------------------------------------------------------------

def plane(size_x: float = 1.0, size_y: float | None = None, subdiv: int = 1) -> Mesh:
    """A z = 0 plane centred at the origin, facing +Z, subdiv x subdiv quads."""
    size_y = size_x if size_y is None else size_y
    n = int(subdiv)
    xs = np.linspace(-size_x / 2, size_x / 2, n + 1)
    ys = np.linspace(-size_y / 2, size_y / 2, n + 1)
    X, Y = np.meshgrid(xs, ys)
    v = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=-1)
    i = np.arange(n)
    a = (i[:, None] * (n + 1) + i[None, :]).ravel()
    b, c, d = a + 1, a + n + 2, a + n + 1
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return Mesh(v, f)


def box(size=(1.0, 1.0, 1.0), center=(0.0, 0.0, 0.0)) -> Mesh:
    """An axis-aligned box, 12 triangles, flat shaded, outward winding."""
    s = np.asarray(size, dtype=np.float64) / 2
    c = np.asarray(center, dtype=np.float64)
    corners = np.array([[x, y, z] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)], float)
    v = corners * s + c
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    f = []
    for a, b, cc, d in quads:
        f += [(a, b, cc), (a, cc, d)]
    return Mesh(v, np.array(f, dtype=np.int64))


def box_face_uvs(b: Mesh) -> np.ndarray:
    """(12, 3, 2) corner UVs for a ``box()``: each face in its own cell of a
    3 x 2 grid, 5 % margin (no overlaps; any box size, even a 10 um slab)."""
    uvs = np.zeros((b.n_faces, 3, 2))
    for f in range(6):
        tri = b.vertices[b.faces[2 * f:2 * f + 2]]                       # (2, 3, 3)
        n = np.cross(tri[0, 1] - tri[0, 0], tri[0, 2] - tri[0, 0])
        ax = [a for a in range(3) if abs(n[a]) < 1e-12 * max(1.0, np.abs(n).max())][:2]
        p = tri[..., ax]
        lo, hi = p.reshape(-1, 2).min(0), p.reshape(-1, 2).max(0)
        local = (p - lo) / np.where(hi > lo, hi - lo, 1.0)
        cell = np.array([f % 3, f // 3], float)
        uvs[2 * f:2 * f + 2] = (cell + 0.05 + 0.9 * local) / np.array([3.0, 2.0])
    return uvs


def uv_sphere(radius: float = 1.0, segments: int = 32, rings: int = 16) -> Mesh:
    """A smooth UV sphere (poles are single vertices)."""
    th = np.linspace(0, math.pi, rings + 1)[1:-1]
    ph = np.linspace(0, 2 * math.pi, segments, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    v = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    v = np.concatenate([[[0, 0, 1.0]], v, [[0, 0, -1.0]]])
    f = []
    top, bot = 0, v.shape[0] - 1
    ring = lambda r, s: 1 + r * segments + (s % segments)  # noqa: E731
    for s in range(segments):
        f.append((top, ring(0, s), ring(0, s + 1)))
        f.append((bot, ring(rings - 2, s + 1), ring(rings - 2, s)))
    for r in range(rings - 2):
        for s in range(segments):
            a, b, c, d = ring(r, s), ring(r + 1, s), ring(r + 1, s + 1), ring(r, s + 1)
            f += [(a, b, c), (a, c, d)]
    return Mesh(v * radius, np.array(f, dtype=np.int64), v.copy())


def icosphere(radius: float = 1.0, subdiv: int = 2, smooth: bool = True) -> Mesh:
    t = (1 + 5 ** 0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                  [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    m = Mesh(v, f)
    for _ in range(subdiv):
        m = subdivide(m)
        m.vertices /= np.linalg.norm(m.vertices, axis=1, keepdims=True)
    n = m.vertices.copy() if smooth else None
    return Mesh(m.vertices * radius, m.faces, n)


def lathe(profile: np.ndarray, segments: int = 32) -> Mesh:
    """Surface of revolution about +Z of a (P, 2) profile of (radius, z), smooth."""
    prof = np.asarray(profile, dtype=np.float64)
    ph = np.linspace(0, 2 * math.pi, segments, endpoint=False)
    r, z = prof[:, 0][:, None], prof[:, 1][:, None]
    v = np.stack([r * np.cos(ph)[None, :], r * np.sin(ph)[None, :],
                  np.repeat(z, segments, axis=1)], -1).reshape(-1, 3)
    P = prof.shape[0]
    f = []
    for i in range(P - 1):
        for s in range(segments):
            a, b = i * segments + s, i * segments + (s + 1) % segments
            c, d = (i + 1) * segments + (s + 1) % segments, (i + 1) * segments + s
            f += [(a, b, c), (a, c, d)]
    m = Mesh(v, np.array(f, dtype=np.int64))
    m.normals = vertex_normals(m)
    return m


def torus(major: float = 1.0, minor: float = 0.3, n_major: int = 48, n_minor: int = 24) -> Mesh:
    u = np.linspace(0, 2 * math.pi, n_major, endpoint=False)
    w = np.linspace(0, 2 * math.pi, n_minor, endpoint=False)
    U, Wm = np.meshgrid(u, w, indexing="ij")
    c = np.stack([np.cos(U), np.sin(U), 0 * U], -1)
    n = np.cos(Wm)[..., None] * c + np.sin(Wm)[..., None] * np.array([0, 0, 1.0])
    v = (major * c + minor * n).reshape(-1, 3)
    f = []
    for i in range(n_major):
        for j in range(n_minor):
            a = i * n_minor + j
            b = ((i + 1) % n_major) * n_minor + j
            cc = ((i + 1) % n_major) * n_minor + (j + 1) % n_minor
            d = i * n_minor + (j + 1) % n_minor
            f += [(a, b, cc), (a, cc, d)]
    return Mesh(v, np.array(f, dtype=np.int64), n.reshape(-1, 3))


def subdivide(m: Mesh) -> Mesh:
    """Midpoint subdivision: every triangle -> 4 (shape unchanged, flat).

    Per-corner UVs are carried (children take the parent's UVs at the
    corners and edge midpoints, so a UV layout stays valid); smooth vertex
    normals are averaged onto the new vertices."""
    f = m.faces
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    uniq, inv = np.unique(e, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    mid = 0.5 * (m.vertices[uniq[:, 0]] + m.vertices[uniq[:, 1]])
    V = m.vertices.shape[0]
    F = f.shape[0]
    ab, bc, ca = inv[:F] + V, inv[F:2 * F] + V, inv[2 * F:] + V
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    nf = np.concatenate([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1),
                         np.stack([ca, bc, c], 1), np.stack([ab, bc, ca], 1)])
    normals = None
    if m.normals is not None:
        nm = m.normals[uniq[:, 0]] + m.normals[uniq[:, 1]]
        ln = np.linalg.norm(nm, axis=1, keepdims=True)
        normals = np.concatenate([m.normals, nm / np.where(ln > 0, ln, 1.0)])
    uvs = None
    if m.uvs is not None:
        ua, ub, uc = m.uvs[:, 0], m.uvs[:, 1], m.uvs[:, 2]
        uab, ubc, uca = 0.5 * (ua + ub), 0.5 * (ub + uc), 0.5 * (uc + ua)
        uvs = np.concatenate([np.stack([ua, uab, uca], 1), np.stack([uab, ub, ubc], 1),
                              np.stack([uca, ubc, uc], 1), np.stack([uab, ubc, uca], 1)])
    return Mesh(np.concatenate([m.vertices, mid]), nf, normals, uvs)


def vertex_normals(m: Mesh) -> np.ndarray:
    """Area-weighted smooth vertex normals."""
    P = m.vertices[m.faces]
    fn = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    n = np.zeros_like(m.vertices)
    for k in range(3):
        np.add.at(n, m.faces[:, k], fn)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(ln > 0, ln, 1.0)


def load_obj(path, *, smooth: bool = True) -> Mesh:
    """Read a Wavefront OBJ (v, vt, f; polygons fan-triangulated, negative indices)."""
    vs, vts, faces, fts = [], [], [], []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if line.startswith("v "):
                vs.append(line.split()[1:4])
            elif line.startswith("vt "):
                vts.append(line.split()[1:3])
            elif line.startswith("f "):
                parts = [p.split("/") for p in line.split()[1:]]
                vi = [int(p[0]) for p in parts]
                ti = [int(p[1]) if len(p) > 1 and p[1] else 0 for p in parts]
                for k in range(1, len(vi) - 1):
                    faces.append((vi[0], vi[k], vi[k + 1]))
                    fts.append((ti[0], ti[k], ti[k + 1]))
    v = np.array(vs, dtype=np.float64)
    f = np.array(faces, dtype=np.int64)
    f = np.where(f < 0, f + v.shape[0], f - 1)
    uvs = None
    ft = np.array(fts, dtype=np.int64)
    if vts and (ft != 0).all():
        vt = np.array(vts, dtype=np.float64)
        ft = np.where(ft < 0, ft + vt.shape[0], ft - 1)
        uvs = vt[ft]
    m = Mesh(v, f, None, uvs)
    if smooth:
        m.normals = vertex_normals(m)
    return m


def asset_path(name: str) -> str:
    """Path of a bundled test mesh in assets/models/."""
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))  # dev/bench/ -> repo
    p = os.path.join(root, "assets", "models", name)
    if not os.path.isfile(p):
        raise FileNotFoundError(f"test mesh {name} not found at {p}")
    return p


# --- scene assembly --------------------------------------------------------------------

def chart_gap(xatlas_padding: int) -> int:
    """The gap in texels to ask core's unwrap for, so that xatlas gets
    ``xatlas_padding`` on each side, at every halving of a retry too
    (unwrap.xatlas_padding(2 p + 1) = p, and of (2 p + 1) // 2 = p // 2 with
    p even, the same as halving p; odd p round as before: tested)."""
    return 2 * int(xatlas_padding) + 1


def assemble(objects: list[tuple[str, Mesh]], *, resolution: int = 1024, atlas: bool = False,
             padding: int = 4, keep_uvs: bool = False, resolutions: dict | None = None) -> Scene:
    """A bake Scene from named meshes, unwrapped with xatlas (core.model.assembly
    joins them, as it does the Blender export's objects).

    atlas=False: one texture set per object (each with its own unwrap);
    atlas=True: one shared set "atlas" holding every object.
    keep_uvs: use a mesh's own UVs (must lie in [0, 1] without overlaps).
    resolutions: per-object resolution overrides (per-object sets only).
    padding: xatlas's own padding on each side of a chart (charts end
    :func:`chart_gap` = 2 p + 1 texels apart): the benchmark scenes, the bake
    identity record and every benchmark figure were made with it, before
    core's unwrap took the gap instead (issue 53), so their layouts stay.
    """
    names = [n for n, _ in objects]
    if len(set(names)) != len(names):
        raise ValueError(f"object names must be unique: {names}")
    if atlas:
        todo = [(m.vertices, m.faces) for _, m in objects]
        uvs = unwrap(todo, resolution, padding=chart_gap(padding))
        set_names, set_res = ["atlas"], [[resolution, resolution]]
    else:
        uvs = []
        for n, m in objects:
            if keep_uvs and m.uvs is not None:
                uvs.append(m.uvs)
            else:
                r = (resolutions or {}).get(n, resolution)
                uvs.append(unwrap([(m.vertices, m.faces)], r, padding=chart_gap(padding))[0])
        set_names = names
        set_res = [[(resolutions or {}).get(n, resolution)] * 2 for n in names]
    parts = [MeshPart(n, m.corner_positions(), m.corner_normals(), uvs[i], 0 if atlas else i)
             for i, (n, m) in enumerate(objects)]
    return assemble_parts(parts, set_names, set_res)
