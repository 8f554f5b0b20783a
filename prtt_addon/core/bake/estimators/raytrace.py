"""Embree (embreex) ray queries on a scene normalised for float32.

Geometry is recentred on its bounding-box centre and scaled so the largest
half-extent is 1 before it goes to Embree in float32. A millimetre part and a
kilometre terrain therefore see the same relative precision, and one
dimensionless ray offset works for both:

``RAY_EPSILON = 2e-6`` (normalised units): origins move this far along the
geometric normal. That is 16 float32 ULPs at |p| = 1 (coordinates are at most
~1.7), well above the rounding of a vertex or an interpolated position to
float32, and 2e-6 of the scene's half size (10 um in a 10 m room, 2 mm on a
1 km terrain), below any contact gap a user models. A box resting exactly on a
floor stays dark underneath (the offset origin is inside the box and Embree
hits its faces from inside: no light leaks).

Scenes are built with Embree's robust flag: watertight intersection, so a ray
through a shared edge of a closed mesh cannot slip between its triangles.

embreex releases the GIL while tracing, so two Python threads trace on two
cores. Building its triangle buffers, though, is a per-element loop that
holds the GIL (~0.7 us a triangle): the scene is therefore built as several
geometries of at most :data:`BUILD_CHUNK` triangles, so that no single call
holds the GIL for long and a signal's watchdog (worker.py) can always run.
"""
from __future__ import annotations

import functools

import numpy as np

from ...base.errors import Cancelled

#: Ray origin offset along the geometric normal, in normalised scene units.
RAY_EPSILON = 2e-6
#: Shading and geometric normals closer than this (1 - cos) need no horizon test.
SAME_NORMAL = 1e-6
#: Triangles per Embree geometry: ~0.2 s of embreex's GIL-holding copy loop.
#: Embree builds one BVH over all of a scene's geometries, so this costs no speed.
BUILD_CHUNK = 1 << 18


def surface_area(positions: np.ndarray, rows: np.ndarray | None = None) -> float:
    """One-sided area (world units²) of triangles (T, 3, 3), or of those
    ``rows``, summed BUILD_CHUNK triangles at a time (no float64 copy of them all)."""
    n = positions.shape[0] if rows is None else rows.size
    area = 0.0
    for a in range(0, n, BUILD_CHUNK):
        t = np.asarray(positions[a:a + BUILD_CHUNK] if rows is None else positions[rows[a:a + BUILD_CHUNK]],
                       np.float64)
        area += 0.5 * float(np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum())
    return area


class RayScene:
    """All scene triangles in one Embree scene.

    positions : (T, 3, 3) float64 world-space triangles.
    cancel : optional object with is_set() (a threading.Event), checked between
             build chunks: parallel.Cancelled.
    """

    def __init__(self, positions: np.ndarray, *, robust: bool = True, cancel=None):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        P = np.asarray(positions, dtype=np.float64)
        lo = P.reshape(-1, 3).min(axis=0)
        hi = P.reshape(-1, 3).max(axis=0)
        self.center = 0.5 * (lo + hi)
        half = float(np.max(hi - lo)) * 0.5
        # A scene of one point (all triangles collapsed) still gets a scale.
        self.scale = 1.0 / half if half > 0 else 1.0
        self.n_triangles = int(P.shape[0])
        self._positions = positions             # for :attr:`area`, only if asked (no copy kept)
        self.robust = robust
        self._scene = rtcore_scene.EmbreeScene(robust=robust)
        # Geometry g holds triangles g*BUILD_CHUNK ... (geomIDs count up from 0).
        self._meshes = []
        for a in range(0, self.n_triangles, BUILD_CHUNK):
            if cancel is not None and cancel.is_set():
                raise Cancelled()
            tri = np.ascontiguousarray(self.to_local(P[a:a + BUILD_CHUNK].reshape(-1, 3)).reshape(-1, 3, 3))
            self._meshes.append(TriangleMesh(self._scene, tri))
        # Commit now, in one thread: embreex commits lazily on the first query,
        # which would race if two threads made the first query together.
        self._scene.run(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32),
                        query="OCCLUDED")

    @functools.cached_property
    def area(self) -> float:
        """Surface area (world units², one side): what guided rays size their
        cells by when the points do not say theirs (guided.py). Computed on
        first use, not with the BVH: a bake's sets give their own."""
        return surface_area(self._positions)

    def origins(self, points: np.ndarray, geo_normal: np.ndarray) -> np.ndarray:
        """Ray origins (N, 3) float32: world points (N, 3) normalised and moved
        RAY_EPSILON along their unit geometric normals ((N, 3), or one (3,))."""
        return self.to_local(points) + (RAY_EPSILON * np.asarray(geo_normal)).astype(np.float32)

    def to_local(self, points: np.ndarray) -> np.ndarray:
        """World (N, 3) float64 -> normalised (N, 3) float32."""
        return ((np.asarray(points, dtype=np.float64) - self.center) * self.scale).astype(np.float32)

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, tfar: np.ndarray | None = None) -> np.ndarray:
        """(N,) bool: does a ray (normalised origin, unit dir, float32 (N, 3)) hit anything.

        ``tfar`` (N,) float32 limits the rays; a negative tfar marks a ray that
        Embree skips without traversal (its result is then meaningless).
        """
        r = self._scene.run(origins, dirs, dists=tfar, query="OCCLUDED")
        return r == 0

    def occluded_raw(self, origins: np.ndarray, dirs: np.ndarray, tfar: np.ndarray | None = None) -> np.ndarray:
        """The bare embreex call: (N,) int32, 0 = occluded (the benchmark baseline;
        also the bake's inner loop, which passes a reusable ``tfar`` so that
        embreex allocates and fills no interval array per call)."""
        return self._scene.run(origins, dirs, dists=tfar, query="OCCLUDED")

    def intersect(self, origins: np.ndarray, dirs: np.ndarray, tfar: np.ndarray | None = None):
        """Closest hits: (prim (N,) int32, -1 = miss; u, v barycentrics; t distance);
        ``tfar`` (N,) float32 limits the rays (normalised units)."""
        r = self._scene.run(origins, dirs, dists=tfar, output=1)
        prim, geom = r["primID"], r["geomID"]
        if len(self._meshes) > 1:
            prim = np.where(geom >= 0, geom * BUILD_CHUNK + prim, -1).astype(np.int32)
        return prim, r["u"], r["v"], r["tfar"]
