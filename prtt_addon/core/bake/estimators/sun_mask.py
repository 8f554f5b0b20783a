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
rays (its steps 1/SUN_RAYS). Every number is a hash of (seed, set, texel) and the
chunks write their own rows: the same mask for any thread count.

Refinement (``grid``, the fine masks of Sun Shadow Detail): a mask 2-4 times
finer a side holds 4-16 times the texels, nearly all of them in full sun or
full shadow. Every texel first traces the first :data:`FIRST_RAYS` rays of
its pattern (one in each quarter of the disc: a (0,2) net's first four
points); where they disagree the texel is in a penumbra, and it and every
texel within :data:`REFINE_RING` of it on the grid trace the rest. Those
texels' masks are exactly the full trace's (the same directions); the others
take what their first rays agree on, 0 or 1. What that can miss: a shadow
edge crossing less than about a quarter of the disc over a whole
(2 REFINE_RING + 1)² neighbourhood (the far tails of a penumbra, below
~1/4 coverage) or a shadow thinner than the disc's quarter at every texel
(a wire's); tests/test_sun_mask.py measures the difference from the full
trace on a penumbra.
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
#: Rays every texel traces first where the mask is refined (module docstring).
FIRST_RAYS = 4
#: Texels within this many of a texel whose first rays disagree trace all of theirs.
REFINE_RING = 2


def mask_bytes(width: int, height: int, texels: int, threads: int, chunk_rays: int, rays: int,
               refine: bool = False) -> int:
    """Upper bound of a set's mask pass (bytes): each thread's chunk
    (RAY_BYTES a ray), the texels' counts and mask and the plane it is dilated in;
    ``refine`` (sun_mask's ``grid``): the grown planes and the counts of both passes."""
    per = max(1, chunk_rays // max(rays, 1)) * rays
    chunks = max(1, threads) * min(per, max(1, texels) * rays) * RAY_BYTES
    extra = 3 * width * height + 32 * texels if refine else 0
    # Per texel: the flags and indices of the points facing the sun, the counts
    # (int64), their quotient (float64) and the mask (float32), with a margin.
    return chunks + 5 * width * height + 64 * texels + extra


def disc_pattern(rays: int, seed: int) -> np.ndarray:
    """(rays, 2) the (0,2) pattern in [0, 1)² every texel shifts."""
    return sobol2(rays, seed ^ _SALT)


def disc_directions(direction, angle: float, pattern: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """(m, R, 3) float64 unit directions over the disc about unit ``direction``
    (3,) of full angle ``angle`` (radians): ``pattern`` (R, 2) shifted by
    ``shift`` (m, 2) modulo 1, mapped uniformly in solid angle."""
    return cone_directions(direction, math.cos(0.5 * angle), pattern, shift)


def cone_directions(axis, cos_max, pattern: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """(m, R, 3) float64 unit directions uniform in solid angle over the cone
    about unit ``axis`` ((3,), or (m, 3) one a point) of half-angle acos
    ``cos_max`` (a number, or (m,)): ``pattern`` (R, 2) shifted by ``shift``
    (m, 2) modulo 1, (u, v) -> (cos theta = 1 - u (1 - cos_max), phi = 2 pi v)."""
    d = np.asarray(axis, np.float64).reshape(-1, 3)
    t, b = tangent_frames(d)
    u = (pattern[None, :, :] + shift[:, None, :]) % 1.0
    c = np.asarray(cos_max, np.float64).reshape(-1, 1)
    ct = 1.0 - u[..., 0] * (1.0 - c)
    st = np.sqrt(np.maximum(0.0, 1.0 - ct * ct))
    phi = 2.0 * math.pi * u[..., 1]
    return ((st * np.cos(phi))[..., None] * t[:, None, :] + (st * np.sin(phi))[..., None] * b[:, None, :]
            + ct[..., None] * d[:, None, :])


def sun_mask(rs: RayScene, position: np.ndarray, geo_normal: np.ndarray, ids: np.ndarray, direction,
             angle: float, *, rays: int, seed: int, set_index: int = 0, threads: int = 1,
             chunk_rays: int = 1 << 18, cancel=None, grid: tuple[int, int] | None = None) -> np.ndarray:
    """(N,) float32 in [0, 1]: the visible fraction of the sun's disc at each
    point; position/geo_normal (N, 3) float64 world points and unit geometric
    normals, ids (N,) int64 stable ids (the G-buffer's flat texel indices);
    direction (3,) unit towards the sun, angle its full angular diameter.
    ``grid`` (width, height): the ids are texels of that grid and the mask is
    refined where its first rays disagree (module docstring), else every
    point traces all ``rays``."""
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

    def seen(idx, rows):
        """(m,) rays of ``pattern[rows]`` that escape from the points ``idx``."""
        if cancel is not None and cancel.is_set():
            raise Cancelled()
        r = rows.stop - rows.start
        shift = np.stack([hash_unit(seed, set_index, ids[idx], _SALT, 1),
                          hash_unit(seed, set_index, ids[idx], _SALT, 2)], axis=-1)
        d = disc_directions(l, angle, pattern[rows], shift)                  # (m, r, 3)
        g = geo_normal[idx]
        above = np.einsum("mrc,mc->mr", d, g) > 0.0
        org = np.repeat(rs.origins(position[idx], g), r, axis=0)
        tfar = np.where(above.ravel(), np.float32(np.inf), np.float32(-1.0))
        hit = rs.occluded(org, d.reshape(-1, 3).astype(np.float32), tfar=tfar).reshape(-1, r)
        return np.count_nonzero(above & ~hit, axis=1)

    out[todo] = (escaping(seen, todo, ids, rays, grid, threads, chunk_rays, cancel) / rays).astype(np.float32)
    return out


def escaping(seen, todo: np.ndarray, ids: np.ndarray, rays: int, grid, threads: int, chunk_rays: int,
             cancel) -> np.ndarray:
    """(len(todo),) int64 rays of each point ``todo`` that escape, of ``rays``:
    ``seen(idx, rows)`` counts those of pattern rows ``rows`` from points
    ``idx``, in chunks on the threads (each chunk writes its own entries);
    with ``grid`` (width, height) refined where the first rays disagree
    (module docstring: ``ids`` the points' texels of that grid)."""
    def trace(points, rows) -> np.ndarray:
        count = np.zeros(points.size, np.int64)
        per = max(1, chunk_rays // (rows.stop - rows.start))
        starts = range(0, points.size, per)

        def put(res):
            count[res[0]:res[0] + res[1].size] = res[1]

        run_chunks(lambda a: (a, seen(points[a:a + per], rows)), starts, threads, put, cancel)
        return count

    first = min(FIRST_RAYS, rays) if grid is not None else rays
    count = trace(todo, slice(0, first))
    if first < rays:
        width, height = grid
        near = np.zeros((height, width), bool)
        near.ravel()[ids[todo[(count > 0) & (count < first)]]] = True     # the first rays disagree
        again = _grow(near, REFINE_RING).ravel()[ids[todo]]
        del near
        # The rest of their rays: with the first, exactly the full trace's count.
        refined = count[again] + trace(todo[again], slice(first, rays))
        count = np.where(count == first, rays, 0)              # decided: all of the disc or none
        count[again] = refined
    return count


def _grow(mask: np.ndarray, ring: int) -> np.ndarray:
    """(H, W) bool ``mask`` grown by ``ring`` texels each way (a square's max filter)."""
    out = mask.copy()
    for axis in (0, 1):
        src = out.copy()
        for k in range(1, ring + 1):
            if k >= src.shape[axis]:
                break
            a = [slice(None)] * 2
            b = [slice(None)] * 2
            a[axis], b[axis] = slice(k, None), slice(None, -k)
            out[tuple(a)] |= src[tuple(b)]
            out[tuple(b)] |= src[tuple(a)]
    return out
