"""Texels whose sample point lies inside geometry (issue 53, item 2).

A floor texel whose centre falls under a box resting on the floor sees only
the inside of the box: its transfer is baked black, and bilinear lookups
blend it into the visible floor beside the box, a dark crease (bench
contact-profile: 0.70 / 0.87 / 0.97 of the traced light in the first three
quarter-texel bins at 1.8 cm texels). Such a texel is found by what its rays
hit: ``RAYS`` cosine-distributed rays about its geometric normal, and the
texel is inside when at least ``INSIDE_FRACTION`` of them hit the back of a
triangle (its winding normal facing along the ray). The bake then drops it
and the dilation fills it from its valid neighbours (stages.mip_and_dilate).

Why 90 %: under a single-sided plane facing up (a table top 0.4 m above a
floor, 0.8 m wide) up to half the rays of a floor texel hit the plane's
back, and Blender draws such planes from both sides; a tolerance of 10 %
back faces (Unity's default) marked 4,139 floor texels there, 50 % marked
342, 90 % none, and it marks every texel under a closed box. A large
single-sided plane very close over a surface (seen over more than ~72°
half-angle) would still read as inside.
"""
from __future__ import annotations

import numpy as np

from .sampling import tangent_frames

#: Rays per texel, and the share of them that must hit back faces. 16 rays
#: mark the same texels as 32 on the contact scene (tests/test_contact_profile.py:
#: exactly those under the box) and 44 fewer of the room-class scene's 30,627,
#: at half the cost (bench: the 1024² transfer bake 1.17x instead of 1.44x).
RAYS = 16
INSIDE_FRACTION = 0.9
#: Texels traced at a time (RAYS rays each: ~1M rays, ~80 MB of temporaries).
CHUNK_TEXELS = 65_536


def winding_normals(positions: np.ndarray) -> np.ndarray:
    """(T, 3) float64 unnormalised winding normals of triangles (T, 3, 3)."""
    p = np.asarray(positions, np.float64)
    return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


def inside_texels(rays, winding: np.ndarray, position: np.ndarray, geo_normal: np.ndarray, *,
                  seed: int = 0, executor=None) -> np.ndarray:
    """(N,) bool: sample points (N, 3) world, with geometric normals (N, 3)
    unit, that lie inside geometry. ``rays``: the scene's RayScene;
    ``winding``: winding_normals of its triangles; ``executor``: a thread
    pool the chunks run on (Embree releases the GIL). Deterministic for a
    seed: a chunk's directions depend on its first texel only."""
    n = len(position)
    out = np.zeros(n, bool)

    def chunk(a: int) -> None:
        b = min(n, a + CHUNK_TEXELS)
        rng = np.random.default_rng([seed, a])
        u1, u2 = rng.random((2, b - a, RAYS))
        r, phi = np.sqrt(u1), 2.0 * np.pi * u2
        local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - u1)], axis=-1)
        nrm = geo_normal[a:b]
        t1, t2 = tangent_frames(nrm)
        d = (local[..., :1] * t1[:, None] + local[..., 1:2] * t2[:, None] + local[..., 2:] * nrm[:, None])
        d = d.reshape(-1, 3)
        # Off the surface along its normal, as the transfer's rays start.
        o = np.repeat(rays.origins(position[a:b], nrm), RAYS, axis=0)
        prim = rays.intersect(o.astype(np.float32), d.astype(np.float32))[0]
        hit = prim >= 0
        back = np.zeros(len(d), bool)
        back[hit] = np.einsum("ij,ij->i", d[hit], winding[prim[hit]]) > 0
        out[a:b] = back.reshape(-1, RAYS).mean(axis=1) >= INSIDE_FRACTION

    starts = range(0, n, CHUNK_TEXELS)
    if executor is not None and len(starts) > 1:
        list(executor.map(chunk, starts))
    else:
        for a in starts:
            chunk(a)
    return out
