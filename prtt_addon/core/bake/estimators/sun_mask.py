"""The sun's mask: per texel, the visible fraction of the sun's disc (issue 48).

A texel's point sends :data:`core.light.sun.SUN_RAYS` rays (``rays``) to
directions spread uniformly over the disc's solid angle, a cone of half-angle
angle / 2 about the sun's direction; the mask is the fraction that escapes.
That is exactly the shadow term of a disc of uniform radiance (Blender's Sun
in Cycles), so the preview's sun light is mask * the unshadowed sun, with a
penumbra as wide as the disc makes it. Rays below the point's geometric
horizon count as blocked (the surface itself hides the sun), as in the
transfer bake.

The directions are one Owen-scrambled Sobol' (0,2) pattern, (u, v) ->
(cos theta = 1 - u (1 - cos(angle / 2)), phi = 2 pi v), shifted per texel
(Cranley-Patterson, hashed from the seed, the set and the texel), so
neighbouring texels' errors are independent and a penumbra is smooth at 64
rays (its steps 1/64). Every number is a hash of (seed, set, texel) and the
chunks write their own rows: the same mask for any thread count.
"""
from __future__ import annotations

import math

import numpy as np

from ...base.errors import Cancelled
from ...base.threads import run_chunks
from .raytrace import RayScene
from .sampling import hash_unit, sobol2, tangent_frames

#: The salt of the mask's random numbers (apart from the transfer's).
_SALT = 0x5C41
#: Bytes of the temporaries a ray holds in a chunk: the disc's float64
#: coordinates and directions with their products (~112 B at the peak, in
#: disc_directions), then float32 directions, origins, tfar and flags.
RAY_BYTES = 128


def mask_bytes(width: int, height: int, texels: int, threads: int, chunk_rays: int, rays: int) -> int:
    """Upper bound of a set's mask pass (bytes): each thread's chunk
    (RAY_BYTES a ray), the texels' mask and the plane it is dilated in."""
    per = max(1, chunk_rays // max(rays, 1)) * rays
    chunks = max(1, threads) * min(per, max(1, texels) * rays) * RAY_BYTES
    return chunks + 4 * texels + 5 * width * height + 16 * texels


def disc_pattern(rays: int, seed: int) -> np.ndarray:
    """(rays, 2) the (0,2) pattern in [0, 1)² every texel shifts."""
    return sobol2(rays, seed ^ _SALT)


def disc_directions(direction, angle: float, pattern: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """(m, R, 3) float64 unit directions over the disc about unit ``direction``
    (3,) of full angle ``angle`` (radians): ``pattern`` (R, 2) shifted by
    ``shift`` (m, 2) modulo 1, mapped uniformly in solid angle."""
    d = np.asarray(direction, np.float64).reshape(1, 3)
    t, b = tangent_frames(d)
    u = (pattern[None, :, :] + shift[:, None, :]) % 1.0
    cos_max = math.cos(0.5 * angle)
    ct = 1.0 - u[..., 0] * (1.0 - cos_max)
    st = np.sqrt(np.maximum(0.0, 1.0 - ct * ct))
    phi = 2.0 * math.pi * u[..., 1]
    return ((st * np.cos(phi))[..., None] * t[0] + (st * np.sin(phi))[..., None] * b[0]
            + ct[..., None] * d[0])


def sun_mask(rs: RayScene, position: np.ndarray, geo_normal: np.ndarray, ids: np.ndarray, direction,
             angle: float, *, rays: int, seed: int, set_index: int = 0, threads: int = 1,
             chunk_rays: int = 1 << 18, cancel=None) -> np.ndarray:
    """(N,) float32 in [0, 1]: the visible fraction of the sun's disc at each
    point; position/geo_normal (N, 3) float64 world points and unit geometric
    normals, ids (N,) int64 stable ids (the G-buffer's flat texel indices);
    direction (3,) unit towards the sun, angle its full angular diameter."""
    n = int(position.shape[0])
    out = np.zeros(n, np.float32)
    if n == 0 or rays <= 0:
        return out
    l = np.asarray(direction, np.float64)
    half = 0.5 * angle
    # A point whose horizon hides the whole disc traces nothing (mask 0).
    facing = geo_normal @ l > -math.sin(half)
    todo = np.flatnonzero(facing)
    pattern = disc_pattern(rays, seed)
    per = max(1, chunk_rays // rays)
    parts = [todo[a:a + per] for a in range(0, todo.size, per)]

    def one(idx):
        if cancel is not None and cancel.is_set():
            raise Cancelled()
        shift = np.stack([hash_unit(seed, set_index, ids[idx], _SALT, 1),
                          hash_unit(seed, set_index, ids[idx], _SALT, 2)], axis=-1)
        d = disc_directions(l, angle, pattern, shift)                       # (m, R, 3)
        g = geo_normal[idx]
        above = np.einsum("mrc,mc->mr", d, g) > 0.0
        org = np.repeat(rs.origins(position[idx], g), rays, axis=0)
        tfar = np.where(above.ravel(), np.float32(np.inf), np.float32(-1.0))
        hit = rs.occluded(org, d.reshape(-1, 3).astype(np.float32), tfar=tfar).reshape(-1, rays)
        seen = np.count_nonzero(above & ~hit, axis=1)
        return idx, (seen / rays).astype(np.float32)

    def put(r):
        out[r[0]] = r[1]

    run_chunks(one, parts, threads, put, cancel)
    return out
