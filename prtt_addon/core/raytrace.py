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

embreex releases the GIL, so two Python threads trace on two cores.
"""
from __future__ import annotations

import numpy as np

#: Ray origin offset along the geometric normal, in normalised scene units.
RAY_EPSILON = 2e-6


class RayScene:
    """All scene triangles in one Embree scene.

    positions : (T, 3, 3) float64 world-space triangles.
    """

    def __init__(self, positions: np.ndarray, *, robust: bool = True):
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
        self.robust = robust
        tri = np.ascontiguousarray(self.to_local(P.reshape(-1, 3)).reshape(-1, 3, 3))
        self._scene = rtcore_scene.EmbreeScene(robust=robust)
        self._mesh = TriangleMesh(self._scene, tri)
        # Commit now, in one thread: embreex commits lazily on the first query,
        # which would race if two threads made the first query together.
        self._scene.run(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32),
                        query="OCCLUDED")

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

    def intersect(self, origins: np.ndarray, dirs: np.ndarray):
        """Closest hits: (prim (N,) int32, -1 = miss; u, v barycentrics; t distance)."""
        r = self._scene.run(origins, dirs, output=1)
        return r["primID"], r["u"], r["v"], r["tfar"]
