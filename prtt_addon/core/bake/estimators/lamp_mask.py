"""A lamp's mask: per texel, the visible fraction of a point or spot lamp's sphere (issue 49).

As the sun's (sun_mask.py), at a finite distance: a texel's point sends
:data:`core.light.lamp.LAMP_RAYS` rays spread uniformly over the solid angle
the lamp's sphere subtends there (a cone of half-angle asin(radius / r)
about the direction to its centre, r the distance), each as long as the way
to the sphere's near side; the mask is the fraction that arrives. A sphere
of uniform radiance looks the same from every direction in that cone, so
this is exactly its shadow term (Blender's Point lamp in Cycles with soft
falloff), with the penumbra the sphere's size makes. A point lamp (radius
0) sends one ray. Rays below the point's geometric horizon count as
blocked; a point inside the sphere sees it whole.

The same Owen-scrambled Sobol' (0,2) pattern as the sun's, shifted per
texel and lamp by a hash of (seed, set, texel, lamp), refined on the grid
where the first rays disagree (sun_mask.escaping): the same mask for any
thread count.
"""
from __future__ import annotations

import numpy as np

from ...base.errors import Cancelled
from .raytrace import RayScene
from .sampling import hash_unit
from .sun_mask import cone_directions, disc_pattern, escaping

#: The salt of the lamps' random numbers (apart from the sun's and the transfer's).
_SALT = 0x1A4B


def lamp_mask(rs: RayScene, position: np.ndarray, geo_normal: np.ndarray, ids: np.ndarray, lamp, *,
              rays: int, seed: int, set_index: int = 0, lamp_index: int = 0, threads: int = 1,
              chunk_rays: int = 1 << 18, cancel=None, grid: tuple[int, int] | None = None) -> np.ndarray:
    """(N,) float32 in [0, 1]: the visible fraction of ``lamp``'s sphere
    (core.light.lamp.Lamp) at each point; position/geo_normal (N, 3) float64
    world points and unit geometric normals, ids (N,) int64 stable ids (the
    G-buffer's flat texel indices). ``grid`` (width, height): refined where
    the first rays disagree (sun_mask's module docstring)."""
    n = int(position.shape[0])
    out = np.zeros(n, np.float32)
    if n == 0:
        return out
    c = np.asarray(lamp.position, np.float64)
    to = c[None, :] - np.asarray(position, np.float64)
    dist = np.sqrt(np.einsum("nc,nc->n", to, to))
    R = float(lamp.radius)
    inside = dist <= R
    out[inside] = 1.0
    l = to / np.maximum(dist, 1e-30)[:, None]
    sin_max = np.where(inside, 1.0, R / np.maximum(dist, 1e-30))
    # A point whose horizon hides the whole sphere traces nothing (mask 0).
    todo = np.flatnonzero(~inside & (np.einsum("nc,nc->n", geo_normal, l) > -sin_max))
    rays = 1 if R == 0.0 else int(rays)
    pattern = disc_pattern(rays, seed ^ _SALT)
    salt = _SALT + 16 * int(lamp_index)

    def seen(idx, rows):
        if cancel is not None and cancel.is_set():
            raise Cancelled()
        r = rows.stop - rows.start
        m = idx.size
        shift = np.stack([hash_unit(seed, set_index, ids[idx], salt, 1),
                          hash_unit(seed, set_index, ids[idx], salt, 2)], axis=-1)
        s_max = sin_max[idx]
        cos_max = np.sqrt(np.maximum(0.0, 1.0 - s_max * s_max))
        d = cone_directions(l[idx], cos_max, pattern[rows], shift)
        D = dist[idx][:, None]
        # each ray's cos from the centre's direction, as cone_directions made it
        ct = 1.0 - ((pattern[None, rows, 0] + shift[:, None, 0]) % 1.0) * (1.0 - cos_max[:, None])
        st = np.sqrt(np.maximum(0.0, 1.0 - ct * ct))
        g = geo_normal[idx]
        above = np.einsum("mrc,mc->mr", d, g) > 0.0
        # The way to the sphere's near side along each ray, shortened a little (the lamp is not geometry).
        far = D * ct - np.sqrt(np.maximum(0.0, R * R - (D * st) ** 2))
        tfar = np.where(above, (0.999 * far * rs.scale).astype(np.float32), np.float32(-1.0))
        org = np.repeat(rs.origins(position[idx], g), r, axis=0)
        hit = rs.occluded(org, d.reshape(-1, 3).astype(np.float32), tfar=tfar.reshape(-1)).reshape(m, r)
        return np.count_nonzero(above & ~hit, axis=1)

    count = escaping(seen, todo, ids, rays, grid if rays > 1 else None, threads, chunk_rays, cancel)
    out[todo] = (count / rays).astype(np.float32)
    return out
