"""Texels whose sample point lies inside geometry (issue 53, item 2).

A floor texel whose centre falls under a box resting on the floor sees only
the inside of the box: its transfer is baked black, and bilinear lookups
blend it into the visible floor beside the box, a dark crease (bench
contact-profile: 0.70 / 0.87 / 0.97 of the traced light in the first three
quarter-texel bins at 1.8 cm texels). Such a texel is found by what its rays
hit: ``RAYS`` cosine-distributed rays about its geometric normal, and the
texel is inside when at least ``INSIDE_FRACTION`` of them are *blocked at
once*: they hit the back of a triangle (its winding normal facing along the
ray), or any triangle closer than ``contact`` (the bake passes CONTACT_TEXELS of
the set's :func:`texel_step`: half a texel).
The bake then drops it and the dilation fills it from its valid neighbours
(stages.mip_and_dilate).

Why the near hits: a wall's bottom row of texels whose centres fall exactly
on the floor it stands on (the window room's xatlas grid puts 95 texels
there at 512²) starts its rays in the floor's plane: every ray hits the
floor at t = 0, half of them its front face, and the texel bakes black (a
dark line along the wall's base, and the transfer filter smears it into the
wall). No texel in the open has nine in ten of its rays blocked within half
a texel: a point at the foot of a perpendicular wall has at most half.

Cost: the first :data:`FIRST_RAYS` rays of each texel are traced first; a
texel with fewer than ``FIRST_RAYS - (RAYS - needed)`` of them blocked cannot
reach ``needed`` of ``RAYS`` and is done, so only texels that may be inside
trace the rest. The answer is the one all ``RAYS`` rays give, bit for bit
(the same directions), at about a quarter of the rays in the open.

Why 90 %: under a single-sided plane facing up (a table top 0.4 m above a
floor, 0.8 m wide) up to half the rays of a floor texel hit the plane's
back, and Blender draws such planes from both sides; a tolerance of 10 %
back faces (Unity's default) marked 4,139 floor texels there, 50 % marked
342, 90 % none, and it marks every texel under a closed box. A large
single-sided plane very close over a surface (seen over more than ~72°
half-angle) would still read as inside.
"""
from __future__ import annotations

import math

import numpy as np

from .sampling import tangent_frames

#: Rays per texel, and the share of them that must hit back faces. 16 rays
#: mark the same texels as 32 on the contact scene (tests/test_contact_profile.py:
#: exactly those under the box) and 44 fewer of the room-class scene's 30,627,
#: at half the cost (bench: the 1024² transfer bake 1.17x instead of 1.44x).
RAYS = 16
INSIDE_FRACTION = 0.9
#: Rays traced for every texel before the rest (only where the rest can still decide "inside").
FIRST_RAYS = 4
#: Near hits: closer than this many of the set's texel steps (a texel's footprint) count as blocked.
CONTACT_TEXELS = 0.5
#: Texels traced at a time (RAYS rays each: ~1M rays, ~80 MB of temporaries).
CHUNK_TEXELS = 65_536


def winding_normals(positions: np.ndarray) -> np.ndarray:
    """(T, 3) float64 unnormalised winding normals of triangles (T, 3, 3)."""
    p = np.asarray(positions, np.float64)
    return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


def texel_step(texel: np.ndarray, position: np.ndarray, width: int) -> float:
    """Median world distance between horizontally adjacent covered texels of
    a set (its texel's footprint, world units); ``texel`` (N,) flat indices
    sorted ascending (the G-buffer's), ``position`` (N, 3). 0.0 when no two
    covered texels are adjacent."""
    t = np.asarray(texel)
    adj = np.flatnonzero((np.diff(t) == 1) & ((t[1:] % width) != 0))
    if adj.size == 0:
        return 0.0
    return float(np.median(np.linalg.norm(position[adj + 1] - position[adj], axis=1)))


def inside_texels(rays, winding: np.ndarray, position: np.ndarray, geo_normal: np.ndarray, *,
                  contact: float = 0.0, seed: int = 0, executor=None) -> np.ndarray:
    """(N,) bool: sample points (N, 3) world, with geometric normals (N, 3)
    unit, that lie inside geometry or on another surface. ``rays``: the
    scene's RayScene; ``winding``: winding_normals of its triangles;
    ``contact``: world distance under which any hit counts as blocked
    (0: back faces only); ``executor``: a thread pool the chunks run on
    (Embree releases the GIL). Deterministic for a seed: a chunk's
    directions depend on its first texel only."""
    n = len(position)
    out = np.zeros(n, bool)
    needed = int(math.ceil(INSIDE_FRACTION * RAYS - 1e-9))
    first_needed = max(0, FIRST_RAYS - (RAYS - needed))
    near = np.float32(contact * rays.scale)            # intersect's t is in the normalised frame

    def blocked(o, d, nr):
        """(M, nr) bool: rays from o (M * nr, 3) float32, normalised, along d (M * nr, 3) float64
        hit a back face or anything nearer than contact."""
        prim, _, _, t = rays.intersect(o, d.astype(np.float32))
        hit = prim >= 0
        bad = np.zeros(len(d), bool)
        bad[hit] = np.einsum("ij,ij->i", d[hit], winding[prim[hit]]) > 0
        if contact > 0:
            bad |= hit & (t < near)
        return bad.reshape(-1, nr)

    def chunk(a: int) -> None:
        b = min(n, a + CHUNK_TEXELS)
        rng = np.random.default_rng([seed, a])
        u1, u2 = rng.random((2, b - a, RAYS))
        r, phi = np.sqrt(u1), 2.0 * np.pi * u2
        local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - u1)], axis=-1)
        nrm = geo_normal[a:b]
        t1, t2 = tangent_frames(nrm)
        d = (local[..., :1] * t1[:, None] + local[..., 1:2] * t2[:, None] + local[..., 2:] * nrm[:, None])
        # Off the surface along its normal, as the transfer's rays start.
        o = rays.origins(position[a:b], nrm)
        f = FIRST_RAYS
        head = blocked(np.repeat(o, f, axis=0), d[:, :f].reshape(-1, 3), f).sum(axis=1)
        rest = np.flatnonzero(head >= first_needed)
        if rest.size == 0:
            return
        tail = blocked(np.repeat(o[rest], RAYS - f, axis=0), d[rest, f:].reshape(-1, 3), RAYS - f).sum(axis=1)
        out[a + rest] = head[rest] + tail >= needed

    starts = range(0, n, CHUNK_TEXELS)
    if executor is not None and len(starts) > 1:
        list(executor.map(chunk, starts))
    else:
        for a in starts:
            chunk(a)
    return out
