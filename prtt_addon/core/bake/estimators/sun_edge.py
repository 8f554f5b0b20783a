"""Sub-texel shadow edges of a sharp sun (issue 48): where a mask texel is too
coarse for the sun's penumbra, each texel near the edge stores its distance
to it, and the preview draws the edge where it is, as sharp as the disc makes it.

A 0.5 degree sun's penumbra is millimetres wide; a texel is often wider. The
mask (sun_mask.py) is the visible fraction at each texel's centre, so its
bilinear lookup draws every edge one texel wide, whatever the sun's size.
A lightmap's answer is a finer texture (Sun Shadow Detail, 4-16 times the
bytes); the edge is a line, so this stores the line instead, the way a
distance-field glyph stores a letter's outline:

* **Crossings.** Between two 4-neighbour texels on either side of 1/2 (the
  mask's lit and shadowed sides), the edge is where the ray to the sun's
  centre is first blocked: found by bisection along the segment between
  their points (:data:`STEPS` rays, to 2^-STEPS of the pair), with the
  occluder's distance t there (one closest-hit ray).
* **The line.** The edge's direction u at a crossing is the principal axis of
  the crossings around it (within :data:`NEAR` texels), in the receiver's plane;
  e = n x u is its normal towards the lit side. Across a straight edge the
  visible fraction of a uniform disc of angular radius a is
  :func:`profile` (d / h), d the signed distance from the line and
  h = tan(a) t sqrt(1 - (l.u)^2) / (n.l) the penumbra's half-width (the
  angle the edge subtends moves by d (n.l) / (t sqrt(1 - (l.u)^2)) per unit
  step across it).
* **Per texel** (within :data:`REACH` texels of a crossing on its UV island):
  d of its point from the nearest crossing's line and that crossing's h,
  both in that crossing's texel steps (so d / h is the world ratio), and a
  flag, valid. Linear in the texel's position on a plane, d interpolates
  exactly: the preview's bilinear lookup of (d, h) draws the edge at its
  sub-texel place, and profile(d / h) its penumbra.

A texel is left to the mask (valid 0) where the line does not explain it:
its mask differs from profile(d / h) at its centre by more than
:data:`TOLERANCE` (corners of shadows, occluders thinner than the disc), the
penumbra is :data:`WIDE` texels or wider (the mask resolves it), the edge is
the surface's own horizon (no occluder), the centre ray disagrees with the
mask at a pair's end, or a pair spans a fold (normals apart) or a seam. Far
from every crossing a texel in full sun or shadow is valid with d = +-REACH;
one with a fraction is not. Every number is a function of the mask and the
scene: the same for any thread count.
"""
from __future__ import annotations

import math

import numpy as np

from ...base.memory import check_fits
from ...texels.dilate import grown_mask
from ...texels.islands import island_labels
from .raytrace import RayScene

#: Texels from a crossing within which a texel stores its distance to the edge.
REACH = 3
#: Crossings within this many texels of each other make one edge's line.
NEAR = 1.6
#: Penumbra half-widths of this many texels or more are left to the mask (it resolves them).
WIDE = 1.0
#: Bisection steps along a pair: the crossing to 1/64 of a texel.
STEPS = 6
#: Largest |mask - profile(d / h)| at a texel's centre for the line to hold there.
TOLERANCE = 0.25
#: Smallest cosine between a pair's normals for them to be one surface.
FLAT_COS = 0.9
#: A pair longer than this many times the set's median pair spans a seam.
SEAM = 3.0
#: The half-width stored where no edge is near (d = +-REACH: profile saturates).
FAR_H = 0.5
#: Channels of the edge file (exr_io.write_edge_exr).
CHANNELS = ("d", "h", "valid")


def profile(s):
    """The visible fraction of a uniform disc whose straight shadow edge
    lies ``s`` disc radii from its centre, towards the lit side (array or
    float): 1 - (acos s - s sqrt(1 - s²)) / pi, s clamped to [-1, 1]."""
    s = np.clip(np.asarray(s, np.float64), -1.0, 1.0)
    return 1.0 - (np.arccos(s) - s * np.sqrt(1.0 - s * s)) / math.pi


def visible(tex):
    """The sun's visible fraction as the preview's sun_visible reads it
    (shaders/prtt_shade.glsl), the numpy twin: ``tex`` (n,) the mask alone, or
    (n, 4) filtered (mask, d, valid, h); where valid is whole (> 0.999) and h
    > 0, :func:`profile` (d / h), else the mask. (n,) float64."""
    tex = np.asarray(tex, np.float64)
    if tex.ndim == 1:
        return tex
    m, d, ok, h = tex[:, 0], tex[:, 1], tex[:, 2], tex[:, 3]
    use = (ok > 0.999) & (h > 0.0)
    s = np.divide(d, h, out=np.zeros_like(d), where=use)
    return np.where(use, profile(s), m)


#: Bytes a pair of texels across an edge holds in :func:`sun_edges`: its points, normals and rays.
PAIR_BYTES = 200


def edge_bytes(texels: int, pairs: int = 0) -> int:
    """Bytes of :func:`sun_edges` on a set of ``texels``: per texel its rows,
    labels, planes and results (~120 B), and PAIR_BYTES per pair across an
    edge. The pairs are the mask's crossings, known once it is traced
    (sun_edges checks their bytes then: the plan counts the texels'); at
    most 2 a texel."""
    return 120 * texels + PAIR_BYTES * pairs


def sun_edges(rs: RayScene, position: np.ndarray, geo_normal: np.ndarray, texel: np.ndarray, width: int,
              height: int, mask: np.ndarray, direction, angle: float, use: np.ndarray | None = None
              ) -> tuple[np.ndarray, dict]:
    """(N, 3) float32 (d, h, valid) per texel of a set (module docstring) and
    counts; position/geo_normal (N, 3) float64 the texels' world points and
    unit geometric normals, texel (N,) int64 flat indices (row 0 at the
    bottom) on a ``width`` x ``height`` grid, mask (N,) the sun mask there,
    direction (3,) unit towards the sun, angle its full angle (radians);
    ``use`` (N,) bool: the texels that take part (not those texel validity
    dropped: they are filled from their neighbours)."""
    n = int(texel.size)
    out = np.zeros((n, 3), np.float32)
    counts = {"crossings": 0, "edge_texels": 0, "mask_texels": 0}
    if n == 0:
        return out, counts
    W, H = int(width), int(height)
    l = np.asarray(direction, np.float64)
    use = np.ones(n, bool) if use is None else np.asarray(use, bool)
    v = np.asarray(mask, np.float64)
    row = np.full(W * H, -1, np.int64)
    row[texel[use]] = np.flatnonzero(use)
    cov = np.zeros(W * H, bool)
    cov[texel[use]] = True
    label = island_labels(cov.reshape(H, W)).ravel()
    tx, ty = texel % W, texel // W
    lit = v > 0.5
    unresolved = np.zeros(n, bool)                      # texels of a pair whose edge cannot be found

    # --- the pairs across 1/2: (lit row, shadowed row, axis) ---------------------------------
    a_rows, b_rows, anchors, axes = [], [], [], []
    for axis, step in ((0, 1), (1, W)):
        ok = (tx < W - 1) if axis == 0 else (ty < H - 1)
        src = texel[ok & use]
        ra, rb = row[src], row[src + step]
        keep = rb >= 0
        ra, rb, src = ra[keep], rb[keep], src[keep]
        cross = lit[ra] != lit[rb]
        ra, rb, src = ra[cross], rb[cross], src[cross]
        a = np.where(lit[ra], ra, rb)
        b = np.where(lit[ra], rb, ra)
        a_rows.append(a), b_rows.append(b), anchors.append(src), axes.append(np.full(a.size, axis, np.int8))
    A, B = np.concatenate(a_rows), np.concatenate(b_rows)
    anchor, axis_of = np.concatenate(anchors), np.concatenate(axes)
    m = int(A.size)
    # The pairs are known only now (the mask's crossings): their bytes are checked before they are made.
    check_fits(PAIR_BYTES * m, f"the sun's shadow edges: {m} texel pairs across them",
               advice="bake with --no-sun-edges, or at a lower resolution or Sun Shadow Detail")
    good = np.zeros(m, bool)
    lam = np.zeros(m)
    t_world = np.zeros(m)
    if m:
        Pa, Pb = position[A], position[B]
        Na, Nb = geo_normal[A], geo_normal[B]
        span = np.linalg.norm(Pb - Pa, axis=1)
        flat = (np.einsum("ij,ij->i", Na, Nb) > FLAT_COS) & (span > 0) & (
            span <= SEAM * float(np.median(span)))
        l32 = np.broadcast_to(l.astype(np.float32), (m, 3))

        def point(x):
            P = Pa + x[:, None] * (Pb - Pa)
            N = Na + x[:, None] * (Nb - Na)
            N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-300)
            return P, N

        def blocked(x):
            """(m,) bool: the ray to the sun's centre is blocked (or below the horizon) at x."""
            P, N = point(x)
            hit = rs.occluded(rs.origins(P, N), np.ascontiguousarray(l32),
                              tfar=np.full(m, np.inf, np.float32))
            return hit | (N @ l <= 0.0)

        # The centre ray must agree with the mask at both ends; then bisect.
        good = flat & ~blocked(np.zeros(m)) & blocked(np.ones(m))
        lo, hi = np.zeros(m), np.ones(m)
        for _ in range(STEPS):
            mid = 0.5 * (lo + hi)
            bm = blocked(mid)
            hi = np.where(bm, mid, hi)
            lo = np.where(bm, lo, mid)
        lam = 0.5 * (lo + hi)
        P, N = point(hi)
        prim, _, _, tt = rs.intersect(rs.origins(P, N), np.ascontiguousarray(l32),
                                      tfar=np.full(m, np.inf, np.float32))
        good &= (prim >= 0) & np.isfinite(tt)           # no occluder: the surface's own horizon
        t_world = np.where(prim >= 0, tt, 0.0) / rs.scale
        unresolved[A[~good]] = True
        unresolved[B[~good]] = True
    counts["crossings"] = int(np.count_nonzero(good))

    # --- each crossing's place, line and penumbra ---------------------------------------------
    ax, ay = (anchor % W).astype(np.float64), (anchor // W).astype(np.float64)
    cx = ax + np.where(axis_of == 0, np.where(lit[row[anchor]], lam, 1.0 - lam), 0.0) if m else ax
    cy = ay + np.where(axis_of == 1, np.where(lit[row[anchor]], lam, 1.0 - lam), 0.0) if m else ay
    e = np.zeros((m, 3))
    h = np.zeros(m)
    Pc = np.zeros((m, 3))
    step_len = np.ones(m)
    if m:
        Pc, Nc = point(lam)
        step_len = np.maximum(span, 1e-300)
        planes = np.full((2, W * H), -1, np.int64)
        gi = np.flatnonzero(good)
        planes[axis_of[gi], anchor[gi]] = gi
        cnt = np.zeros(m)
        s1 = np.zeros((m, 3))
        s2 = np.zeros((m, 3, 3))
        r = int(math.ceil(NEAR)) + 1
        for oy in range(-r, r + 1):
            for ox in range(-r, r + 1):
                x, y = ax.astype(np.int64) + ox, ay.astype(np.int64) + oy
                inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
                flat_idx = np.where(inside, y * W + x, 0)
                for k in (0, 1):
                    j = np.where(inside, planes[k, flat_idx], -1)
                    ok = good & (j >= 0)
                    jj = np.where(ok, j, 0)
                    ok &= np.hypot(cx[jj] - cx, cy[jj] - cy) <= NEAR
                    ok &= label[anchor[jj]] == label[anchor]
                    dp = np.where(ok[:, None], Pc[jj] - Pc, 0.0)
                    cnt += ok
                    s1 += dp
                    s2 += dp[:, :, None] * dp[:, None, :]
        mean = s1 / np.maximum(cnt, 1)[:, None]
        cov3 = s2 / np.maximum(cnt, 1)[:, None, None] - mean[:, :, None] * mean[:, None, :]
        _, vec = np.linalg.eigh(cov3)
        u = vec[:, :, 2]
        lone = cnt < 2                                  # no neighbour: across the pair's own axis
        u[lone] = np.cross(Nc[lone], Pa[lone] - Pb[lone])
        u -= np.einsum("ij,ij->i", u, Nc)[:, None] * Nc
        u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)
        e = np.cross(Nc, u)
        e *= np.where(np.einsum("ij,ij->i", e, Pa - Pb) < 0.0, -1.0, 1.0)[:, None]
        nl = np.maximum(Nc @ l, 1e-6)
        lu = np.clip(u @ l, -1.0, 1.0)
        h = math.tan(0.5 * angle) * t_world * np.sqrt(1.0 - lu * lu) / nl / step_len
        sharp = good & (h < WIDE) & (h > 0.0)
    else:
        sharp = good

    # --- each texel's nearest crossing on its island ------------------------------------------
    best = np.full(n, -1, np.int64)
    best_d2 = np.full(n, np.inf)
    if m:
        planes = np.full((2, W * H), -1, np.int64)
        gi = np.flatnonzero(good)
        planes[axis_of[gi], anchor[gi]] = gi
        near_any = np.zeros(W * H, bool)
        near_any[anchor[gi]] = True
        band = grown_mask(near_any.reshape(H, W), REACH + 1).ravel()[texel] & use
        bt = np.flatnonzero(band)
        bx, by = tx[bt], ty[bt]
        for oy in range(-REACH - 1, REACH + 1):
            for ox in range(-REACH - 1, REACH + 1):
                x, y = bx + ox, by + oy
                inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
                flat_idx = np.where(inside, y * W + x, 0)
                for k in (0, 1):
                    j = np.where(inside, planes[k, flat_idx], -1)
                    ok = j >= 0
                    jj = np.where(ok, j, 0)
                    d2 = (cx[jj] - bx) ** 2 + (cy[jj] - by) ** 2
                    ok &= (d2 <= REACH * REACH) & (label[anchor[jj]] == label[texel[bt]])
                    closer = ok & (d2 < best_d2[bt])
                    best[bt[closer]] = jj[closer]
                    best_d2[bt[closer]] = d2[closer]
    found = best >= 0
    j = np.where(found, best, 0)
    d = np.zeros(n)
    hh = np.full(n, FAR_H)
    valid = np.zeros(n, bool)
    if m:
        d = np.einsum("ij,ij->i", position - Pc[j], e[j]) / step_len[j]
        hh = np.where(found, h[j], FAR_H)
        fit = profile(d / np.maximum(hh, 1e-12))
        valid = found & sharp[j] & (np.abs(fit - v) <= TOLERANCE)
    far = ~found & ((v == 0.0) | (v == 1.0))
    d = np.where(far, np.where(v == 1.0, REACH, -REACH), np.clip(d, -REACH, REACH))
    hh = np.where(far, FAR_H, hh)
    valid = (valid | far) & use & ~unresolved
    out[:, 0] = np.where(valid, d, 0.0)
    out[:, 1] = np.where(valid, hh, 0.0)
    out[:, 2] = valid
    counts["edge_texels"] = int(np.count_nonzero(valid & found))
    counts["mask_texels"] = int(np.count_nonzero(~valid & use))
    return out, counts

