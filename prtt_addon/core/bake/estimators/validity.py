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

from ...base.threads import map_items
from ...texels.islands import island_labels
from .raytrace import RAY_EPSILON
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
#: Texels whose random numbers are drawn from one generator (seeded by the
#: block's first texel: the same numbers whatever the threads).
CHUNK_TEXELS = 65_536
#: Texels a task traces: a part of a block, its share of the block's numbers
#: drawn alone (_block_uniforms), so that both cores work on a set of fewer
#: than two blocks (the 512² window room's 89K texels were one block of
#: 65,536 and one of 23,832).
TASK_TEXELS = 8_192
#: Walls through a texel's neighbourhood (across_walls): directions in the
#: surface's plane, how far they look (in texel steps: a bilinear lookup reads
#: texel centres up to one step away), how steep a surface they stop at (|cos|
#: between its normal and the texel's under this: 60 degrees and more), and
#: the rays that compare the light on the two sides.
WALL_DIRECTIONS = 8
WALL_REACH = 0.75
WALL_STEEP = 0.5
SIDE_RAYS = 32
#: A texel moves across a wall only to a side that sees at most this share of
#: the sky its own side sees (dark inside, bright outside; a fence in the open
#: with the sky on both sides stays where it is).
DARKER = 0.5
#: ... and where this share of its rays or more meet back faces (the inside
#: test's measure; beside a wall the near hits are expected), only if it
#: sees the sky (SKY_RAYS): a solid, or a room whose walls face out (the
#: shed's roof faces out: up to 72 % of the rays beside its back wall).
OPEN_FRACTION = 0.9
#: ... and only into space: beyond the wall the way on must stay clear for
#: this many texel steps (not into a rug 1 cm thick lying on the floor, whose
#: bottom face and the floor's share a plane, so the back-face test misses it).
ENCLOSED_STEPS = 2.0


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


def _cosine(u1: np.ndarray, u2: np.ndarray, t1: np.ndarray, t2: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(M, R, 3) float64 cosine-distributed directions from uniform numbers
    ``u1``, ``u2`` (M, R) about unit normals ``n`` (M, 3) with tangents
    ``t1``, ``t2`` (M, 3): r = sqrt(u1), phi = 2 pi u2, z = sqrt(1 - u1)."""
    r, phi = np.sqrt(u1), 2.0 * np.pi * u2
    return ((r * np.cos(phi))[..., None] * t1[:, None] + (r * np.sin(phi))[..., None] * t2[:, None]
            + np.sqrt(1.0 - u1)[..., None] * n[:, None])


#: Rays that look for the sky from a point judged inside (inside_texels) or
#: beyond a wall (across_walls): a solid's inside sees none, a room whose
#: walls face out sees its door or window (a 0.2 m door 1 m away: ~3 % of a
#: texel's cosine rays). Inside texels are judged by region (ROOM_SKY_SHARE):
#: 16 rays a texel find the door of a room thousands of texels large; a
#: point beyond a wall is judged alone, by 128 (under 1 % miss that door).
ESCAPE_RAYS = 16
SKY_RAYS = 128
#: A region of inside texels is a room's when this share of them see the sky
#: (the shed whose walls face out: 38 % at 16 rays; the floor around a torus
#: resting on it, or beside a sphere, where some texels near the contact see
#: past it: 0.6-7 %).
ROOM_SKY_SHARE = 0.2


def _uniform_rows(seed: list, rows: int, lo: int, hi: int, cols: int):
    """(u1, u2), each (hi - lo, cols) float64: rows lo..hi of
    ``np.random.default_rng(seed).random((2, rows, cols))``, without drawing
    the others: a double is one 64-bit step of PCG64, which ``advance`` skips."""
    def part(skip):
        bits = np.random.PCG64(np.random.SeedSequence(list(seed)))
        bits.advance(skip)
        return np.random.Generator(bits).random((hi - lo, cols))
    return part(lo * cols), part((rows + lo) * cols)


def _block_uniforms(seed, a: int, b: int, lo: int, hi: int, rays: int):
    """(u1, u2), each (hi - lo, rays): the numbers of texels lo..hi of block
    [a, b), whose generator is ``default_rng(seed + [a])`` drawing (2, b - a, rays)."""
    return _uniform_rows(list(seed) + [a], b - a, lo - a, hi - a, rays)


def _blocks(n: int):
    """(block start, its tasks [(block start, first, end)]) covering n texels:
    blocks of CHUNK_TEXELS in tasks of TASK_TEXELS."""
    for a in range(0, n, CHUNK_TEXELS):
        yield a, [(a, lo, min(n, a + CHUNK_TEXELS, lo + TASK_TEXELS))
                  for lo in range(a, min(n, a + CHUNK_TEXELS), TASK_TEXELS)]


#: Points a task of _sees_sky traces.
SKY_TASK = 2048


def _sees_sky(rays, points: np.ndarray, normals: np.ndarray, n_rays: int, seed, executor=None) -> np.ndarray:
    """(M,) bool: at least one of ``n_rays`` cosine rays about ``normals``
    (M, 3) from ``points`` (M, 3) world escapes the scene; ``seed`` seeds
    numpy's generator (a list of ints), which draws (2, M, n_rays) numbers;
    ``executor``: tasks of SKY_TASK points on its threads (each draws its
    rows of those numbers alone: the same answer)."""
    m = len(points)
    if m == 0:
        return np.zeros(0, bool)

    def task(lo):
        hi = min(m, lo + SKY_TASK)
        u1, u2 = _uniform_rows(seed, m, lo, hi, n_rays)
        nrm = normals[lo:hi]
        d = _cosine(u1, u2, *tangent_frames(nrm), nrm)
        o = np.repeat(rays.origins(points[lo:hi], nrm), n_rays, axis=0)
        return (~rays.occluded(o, d.reshape(-1, 3).astype(np.float32))).reshape(-1, n_rays).any(axis=1)

    return np.concatenate(map_items(executor, task, list(range(0, m, SKY_TASK))))


#: How far past a front face a back face in (nearly) its plane is looked for (normalised units).
COPLANAR_GAP = 4.0 * RAY_EPSILON


def _hidden_back(rays, winding, o, d, prim, t, front) -> np.ndarray:
    """(R,) bool: rays (o, d float32, normalised) whose first hit, a front
    face (``front``), has a back face within COPLANAR_GAP behind it. Two
    solids that share a plane (a wall's top under the ceiling's bottom, a
    box's bottom on the floor) or overlap (boxes of a wall's corner) show
    the ray a front face where it leaves one solid into the other; Embree
    picks either of two coplanar faces. Without this, a point inside such
    walls counted 8 % front hits and missed the nine in ten."""
    out = np.zeros(len(d), bool)
    f = np.flatnonzero(front)
    if f.size == 0:
        return out
    gap = np.float32(COPLANAR_GAP)
    o2 = o[f] + d[f] * (t[f] - gap)[:, None]
    p2, _, _, t2 = rays.intersect(np.ascontiguousarray(o2, np.float32), np.ascontiguousarray(d[f]),
                                  np.full(f.size, 3.0 * gap, np.float32))
    h = (p2 >= 0) & (p2 != prim[f])
    out[f[h]] = np.einsum("ij,ij->i", d[f[h]].astype(np.float64), winding[p2[h]]) > 0
    return out


def _back_faces(rays, winding, o: np.ndarray, d: np.ndarray, peel: bool):
    """Closest hits of rays from ``o`` (R, 3) float32, normalised, along ``d``
    (R, 3) float64: (hit (R,) bool, back (R,) bool: the hit is a back face,
    or with ``peel`` a front face with a back face just behind it, t (R,)
    float32 normalised distance)."""
    df = d.astype(np.float32)
    prim, _, _, t = rays.intersect(o, df)
    hit = prim >= 0
    back = np.zeros(len(d), bool)
    back[hit] = np.einsum("ij,ij->i", d[hit], winding[prim[hit]]) > 0
    if peel:
        back |= _hidden_back(rays, winding, o, df, prim, t, hit & ~back)
    return hit, back, t


def inside_texels(rays, winding: np.ndarray, position: np.ndarray, geo_normal: np.ndarray, *,
                  contact: float = 0.0, seed: int = 0, executor=None, grid=None) -> np.ndarray:
    """(N,) bool: sample points (N, 3) world, with geometric normals (N, 3)
    unit, that lie inside geometry or on another surface. ``rays``: the
    scene's RayScene; ``winding``: winding_normals of its triangles;
    ``contact``: world distance under which any hit counts as blocked
    (0: back faces only); ``executor``: a thread pool the chunks run on
    (Embree releases the GIL); ``grid``: (texel (N,) flat indices
    ascending, width, height) of the points' texture: a region of texels
    judged inside (8-connected in the texture) of which ROOM_SKY_SHARE see
    the sky is a room whose walls face out, not a solid, and is kept;
    without it each point must see no sky itself. Deterministic for a seed: a chunk's
    directions depend on its first texel only."""
    n = len(position)
    out = np.zeros(n, bool)
    sky_seen = np.zeros(n, bool)
    needed = int(math.ceil(INSIDE_FRACTION * RAYS - 1e-9))
    first_needed = max(0, FIRST_RAYS - (RAYS - needed))
    near = np.float32(contact * rays.scale)            # intersect's t is in the normalised frame

    def blocked(o, d, nr, peel):
        """(M, nr) bool: rays from o (M * nr, 3) float32, normalised, along d (M * nr, 3) float64
        hit a back face or anything nearer than contact; with ``peel`` also a
        front face with a back face just behind it (_hidden_back)."""
        hit, bad, t = _back_faces(rays, winding, o, d, peel)
        if contact > 0:
            bad |= hit & (t < near)
        return bad.reshape(-1, nr)

    def task(span) -> np.ndarray:
        """The texels of one task that are inside (indices, ascending)."""
        a, lo, hi = span
        u1, u2 = _block_uniforms([seed], a, min(n, a + CHUNK_TEXELS), lo, hi, RAYS)
        nrm = geo_normal[lo:hi]
        t1, t2 = tangent_frames(nrm)

        def directions(sel, first, last):
            """(m, last - first, 3) float64: rays first..last of texels ``sel`` (only those are
            made: the head's 4 of every texel, the rest's 12 of a few)."""
            return _cosine(u1[sel, first:last], u2[sel, first:last], t1[sel], t2[sel], nrm[sel])

        # Off the surface along its normal, as the transfer's rays start.
        o = rays.origins(position[lo:hi], nrm)
        f = FIRST_RAYS
        # The first rays without the peel (most of their hits are front faces of a
        # room's walls and ceiling: 0.24 s of the demo's 1024²); a texel inside
        # solids that share faces still has most of them blocked.
        head = blocked(np.repeat(o, f, axis=0), directions(slice(None), 0, f).reshape(-1, 3), f, False).sum(axis=1)
        rest = np.flatnonzero(head >= first_needed)
        if rest.size == 0:
            return rest
        tail = blocked(np.repeat(o[rest], RAYS - f, axis=0), directions(rest, f, RAYS).reshape(-1, 3), RAYS - f,
                       True).sum(axis=1)
        return lo + rest[head[rest] + tail >= needed]

    def block(item) -> None:
        # Back faces all round are a solid's inside, or a room whose walls face
        # out (Blender's cube with faces deleted): the room sees its door. Drawn
        # for the block's inside texels together (its seed: its first texel).
        a, marked = item
        out[marked] = True
        sky_seen[marked] = _sees_sky(rays, position[marked], geo_normal[marked], ESCAPE_RAYS, [seed, a, 0xE5],
                                     executor)

    for a, spans in _blocks(n):
        block((a, np.concatenate(map_items(executor, task, spans))))
    if not sky_seen.any():
        return out
    if grid is None:
        return out & ~sky_seen
    texel, width, height = grid
    mask = np.zeros(height * width, bool)
    mask[texel[out]] = True
    labels = island_labels(mask.reshape(height, width)).reshape(-1)[texel[out]]   # the inside texels' regions
    mask = None
    region, of = np.unique(labels, return_inverse=True)
    members = np.bincount(of, minlength=region.size)
    seeing = np.bincount(of[sky_seen[out]], minlength=region.size)
    room = (seeing > 0) & (seeing >= ROOM_SKY_SHARE * members)
    at = np.flatnonzero(out)
    out[at[room[of]]] = False
    return out


def validity_bytes(width: int, height: int, texels: int, threads: int = 1) -> int:
    """Upper bound of inside_texels' and across_walls' temporaries (bytes) for
    a set ``width`` x ``height`` with ``texels`` covered texels traced on
    ``threads``: each thread's chunk (up to CHUNK_TEXELS texels: their 16
    rays' random numbers, 256 B a texel, and the first 4 rays' directions,
    origins and hits, ~52 B a ray; the rest's only for the few texels that
    trace them: 40 B a ray of 16 with a margin, 42 MB), the per-texel flags,
    and the regions' labels (the mask, the union-find's parents and the
    labels: 17 B a texture texel)."""
    per_chunk = min(texels, CHUNK_TEXELS) * RAYS * 40
    running = min(max(1, threads), -(-texels // CHUNK_TEXELS) if texels else 1)
    return running * per_chunk + 4 * texels + 17 * width * height


#: How far in the texture (texels) the texel under a moved point is looked for.
RADIUS = 2


def _open_texel_at(points: np.ndarray, flat: np.ndarray, texel: np.ndarray, width: int, height: int,
                   position: np.ndarray, inside: np.ndarray | None, near: float, wall: np.ndarray,
                   across: np.ndarray) -> np.ndarray:
    """(M,) bool: the covered texel nearest each point (M, 3) world, among
    those within RADIUS texels of texel ``flat`` (M,) in the texture and
    beyond the wall (past the plane through ``wall`` (M, 3) normal to
    ``across`` (M, 3), the way the point moved), lies within ``near``
    (world) of it and is not ``inside``."""
    y, x = flat // width, flat % width
    best = np.full(len(points), np.inf)
    best_j = np.zeros(len(points), np.int64)
    n = texel.size
    for dy in range(-RADIUS, RADIUS + 1):
        for dx in range(-RADIUS, RADIUS + 1):
            yq, xq = y + dy, x + dx
            ok = (yq >= 0) & (yq < height) & (xq >= 0) & (xq < width)
            q = yq * width + xq
            j = np.minimum(np.searchsorted(texel, q), n - 1)
            ok &= texel[j] == q
            ok &= np.einsum("ij,ij->i", position[j] - wall, across) > 0
            d = np.where(ok, np.linalg.norm(position[j] - points, axis=1), np.inf)
            better = d < best
            best[better], best_j[better] = d[better], j[better]
    good = best <= near
    if inside is not None:
        good &= ~inside[best_j]
    return good


def across_walls(rays, winding: np.ndarray, position: np.ndarray, geo_normal: np.ndarray, step: float,
                 texel: np.ndarray, width: int, height: int, *, inside: np.ndarray | None = None, seed: int = 0,
                 executor=None) -> tuple[np.ndarray, np.ndarray]:
    """Texels next to a wall that stands on their surface, moved to its darker
    side: (index (M,) int64 ascending, position (M, 3) float64 world), the
    texels to move and where.

    Why: a zero-thickness wall (a single plane) standing on a continuous
    floor splits no texel. A floor texel whose centre lies just outside a
    dark room holds the outside's light, and every bilinear lookup up to a
    texel inside reads it: a bright leak along the inside of the wall (bench
    contact-profile --leak: 7x the traced light a quarter texel in). The
    texels that straddle, or lie within a step of, such a wall cannot be right
    on both sides; a dark line along the outside base of a wall reads as a
    contact shadow, a bright one inside a room as a leak, so they take the
    darker side's light, as a lightmapper's leak fix does.

    Found by WALL_DIRECTIONS rays in the texel's plane from its ray origin, as
    far as WALL_REACH texel steps (``step``, world units): one that hits a
    surface at WALL_STEEP or steeper is a wall at distance t. The candidate is
    the centre mirrored across it (t beyond it, less where something nearer
    stops the way on); it is taken when the texel's surface goes on there (a
    ray back along the normal meets a surface facing the same way within a
    few ray offsets), the way on beyond the wall is clear for ENCLOSED_STEPS,
    it is not in a solid (where the way on ends at a back face, the far side
    of a solid wall, or OPEN_FRACTION of its SIDE_RAYS cosine rays meet back
    faces, one of SKY_RAYS must escape: a room whose walls face out sees its
    door), and its SIDE_RAYS cosine rays escape at most DARKER as often as the centre's do (the same
    directions).
    And the texel nearest the candidate beyond the wall, among the set's
    covered texels within RADIUS texels in the texture (``texel`` (N,) flat
    indices ascending, of a ``width`` x ``height`` set), must lie within
    one and a half steps of it and not be ``inside`` ((N,) bool, inside_texels;
    those never move): the floor goes on under a single-plane wall with open
    texels, while under a solid wall (a box standing on it, a shelf's board)
    its texels are inside. That holds where the rays above cannot tell: solids
    that overlap or share faces (a wall's top with the ceiling's bottom) hide
    the back faces the inside test counts.
    Deterministic for a seed: a chunk's directions depend on its first texel."""
    n = len(position)
    if n == 0 or step <= 0:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    reach = np.float32(WALL_REACH * step * rays.scale)                 # normalised frame
    unit = winding / np.maximum(np.linalg.norm(winding, axis=1, keepdims=True), 1e-300)
    angles = 2.0 * np.pi * np.arange(WALL_DIRECTIONS) / WALL_DIRECTIONS
    found_index, found_position = [], []

    def walls(span):
        """The texels of one task with a wall beside them: (index (M,) ascending,
        the wall's direction (M, 3), its normalised distance (M,), what the way
        on beyond it meets (prim (M,), t (M,)), the mirrored point (M, 3) world,
        the texels' tangents (M, 3) x 2)."""
        a, lo, hi = span
        nrm = geo_normal[lo:hi]
        t1, t2 = tangent_frames(nrm)
        # (m, D, 3): the plane's directions, a texel's turned by its frame.
        d = np.cos(angles)[None, :, None] * t1[:, None] + np.sin(angles)[None, :, None] * t2[:, None]
        o = rays.origins(position[lo:hi], nrm)
        od = np.repeat(o, WALL_DIRECTIONS, axis=0)
        hit = rays.occluded(od, d.reshape(-1, 3).astype(np.float32),
                            np.full(len(od), reach, np.float32)).reshape(-1, WALL_DIRECTIONS)
        if inside is not None:
            hit &= ~inside[lo:hi, None]
        cand = np.flatnonzero(hit.any(axis=1))
        if cand.size == 0:
            return None
        # The nearest steep hit of each candidate's directions.
        rows, cols = np.nonzero(hit[cand])
        oc, dc = o[cand[rows]], d[cand[rows], cols]
        prim, _, _, t = rays.intersect(oc, dc.astype(np.float32))
        steep = (prim >= 0) & (t <= reach)
        steep[steep] &= np.abs(np.einsum("ij,ij->i", unit[prim[steep]], nrm[cand[rows[steep]]])) <= WALL_STEEP
        if not steep.any():
            return None
        rows, cols, t = rows[steep], cols[steep], t[steep]
        order = np.lexsort((t, rows))
        first = order[np.flatnonzero(np.r_[True, np.diff(rows[order]) != 0])]
        who = cand[rows[first]]                                   # task-local texels with a wall
        dirs = d[who, cols[first]]
        tw = t[first].astype(np.float64)                          # normalised distance to the wall
        # Mirrored across the wall, unless something stops the way on first.
        beyond = o[who] + (dirs * (tw[:, None] * (1.0 + 1e-3))).astype(np.float32)
        p2, _, _, t2b = rays.intersect(beyond.astype(np.float32), dirs.astype(np.float32))
        further = np.where(p2 >= 0, np.minimum(t2b.astype(np.float64) * 0.5, tw), tw)
        moved = position[lo + who] + dirs * ((tw * (1.0 + 1e-3) + further) / rays.scale)[:, None]
        return lo + who, dirs, tw, p2, t2b, moved, t1[who], t2[who]

    def block(item):
        """The texels of one block that move, and where: the random numbers of
        both sides' rays drawn for the block's texels with a wall together (its
        seed: its first texel)."""
        a, parts = item
        parts = [q for q in parts if q is not None]
        if not parts:
            return None
        who, dirs, tw, p2, t2b, moved, t1w, t2w = (np.concatenate(c) for c in zip(*parts))
        # Both sides' sky, by the same cosine rays about the normal.
        rng = np.random.default_rng([seed, a, 0x5A])
        u1, u2 = rng.random((2, who.size, SIDE_RAYS))
        nw = geo_normal[who]
        rd = _cosine(u1, u2, t1w, t2w, nw).reshape(-1, 3)

        def sides(points):
            og = np.repeat(rays.origins(points, nw), SIDE_RAYS, axis=0)
            h, back, _ = _back_faces(rays, winding, og, rd, True)
            return (~h).reshape(-1, SIDE_RAYS).sum(axis=1), back.reshape(-1, SIDE_RAYS).sum(axis=1)

        # The texel's surface must go on under the wall to the mirrored point (a
        # floor under a single-plane wall), not end at it (a table leg's foot on
        # the floor would move under the floor): a ray back along the normal
        # meets a surface facing as the texel's within a few origin offsets.
        og = rays.origins(moved, nw)
        pb, _, _, tb = rays.intersect(og, (-nw).astype(np.float32))
        on = (pb >= 0) & (tb <= np.float32(4.0 * RAY_EPSILON))
        on[on] &= np.einsum("ij,ij->i", unit[pb[on]], nw[on]) >= 1.0 - WALL_STEEP / 10.0
        sky_here, _ = sides(position[who])
        sky_there, back_there = sides(moved)
        # Beyond the wall the way on is clear for a while, and the point is not in
        # a solid: a solid wall shows its far side's back face (the window room's
        # 20 cm walls, a shelf's 3 cm board overlapping another, where the inside
        # test's rays meet hidden or shared faces), or most rays meet back faces,
        # and it sees no sky. A room whose walls face out shows back faces too,
        # but sees its door.
        hit_on = p2 >= 0
        back_on = np.zeros(len(p2), bool)
        back_on[hit_on] = np.einsum("ij,ij->i", dirs[hit_on], winding[p2[hit_on]]) > 0
        roomy = ~hit_on | (t2b > np.float32(ENCLOSED_STEPS * step * rays.scale))
        take = on & roomy & (sky_there <= DARKER * sky_here) & (sky_here > 0)
        doubt = np.flatnonzero(take & (back_on | (back_there >= OPEN_FRACTION * SIDE_RAYS)))
        if doubt.size:
            take[doubt] = _sees_sky(rays, moved[doubt], nw[doubt], SKY_RAYS, [seed, a, 0x5B])
        if take.any():
            wall_at = position[who] + dirs * (tw / rays.scale)[:, None]
            take[take] &= _open_texel_at(moved[take], texel[who[take]], texel, width, height, position,
                                         inside, 1.5 * step, wall_at[take], dirs[take])
        return who[take], moved[take]

    # A block at a time (what its tasks found is held until it is done), its tasks on the threads.
    for a, spans in _blocks(n):
        part = block((a, map_items(executor, walls, spans)))
        if part is not None:
            found_index.append(part[0])
            found_position.append(part[1])
    if not found_index:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    return np.concatenate(found_index).astype(np.int64), np.concatenate(found_position)
