"""Inter-reflection ("bounce") textures, the paper's section on inter-reflections.

Bounce level k at a texel p is the cosine-weighted incident radiance that
arrives after exactly k reflections, projected to SH:

    B_k(p)_c = integral (1 - V(w)) L_{k-1}(q(w) -> p)_c max(0, n.w) y(w) dw,

stored as ``<set>.bounce<k>.exr`` (channels R.sh000.., G.sh000.., B.sh000..).
At render time it is simply added to the direct incident radiance M(L) T
before the material lobes (shading.shade(..., bounces=...)).

Exit radiance, precomputed per texel (docs/shading.md, "Bounce bake")
----------------------------------------------------------------------
The radiance leaving a hit q towards p is the reference shading model
(shading.outgoing) with q's incident radiance Lp_q (3, K): M(L) T_q for
k = 1, the previous bounce texture for k > 1. Everything in it that does not
depend on the ray is computed once per level for every texel of the source
set, one row per texel (:func:`exit_textures`, a few large array products):

    diffuse  D_c    = rho_c sqrt(4 pi) / pi * Lp_c,0                (3 floats)
    glossy   G_c,lm = k_s,c A_l(s) Lp_c,lm, and the shading normal   (3K + 3)

with the material (rho, k_s, s) and the shading normal (normal-mapped) taken
at each texel's centre and dilated like the textures (so hits near island
borders never read an empty texel). Per hit only a lookup and an evaluation
remain:

    L(q -> p)_c = max(0, D_c + [q glossy] sum_lm G_c,lm y_lm(r)),
    r = reflect(q -> p, normalise(n)),

where [q glossy] says the hit triangle's material has a specular lobe, and
D, G and n are those of the texel nearest to q (:class:`ExitShader` says
why). Against evaluating the model at the exact hit point this moves the
material and normal to the texel grid (what the renderer does for the
transfer anyway); the difference is far below the Monte Carlo noise
(tests/test_bounce.py keeps its brute-force tolerances).

Rays: the transfer bake's chunk planner and seed scheme (transfer.chunk_plan,
frames and Sobol' patterns, balanced weights), each level with its own ids.

Skipped work, all counted in the manifest:
* rays that miss are never shaded (their term is exactly 0);
* occluder-only triangles (set -1) have no texture: they absorb (radiance 0);
* texels on the zero-ray analytic path, and texels all of whose *transfer*
  rays escaped (their transfer equals the unoccluded value), get exactly 0
  with no rays. The latter is an approximation: bounce rays are a different
  sample of the hemisphere, so a tiny object that every transfer ray missed
  is missed here too - an error of the size of the transfer's own noise;
* a set whose texels are all skipped is not traced at all and gets no file
  (the renderer treats a missing bounce texture as zero);
* levels after one whose energy is below ``bounce_tolerance`` of the direct
  light's are not baked (:func:`level_energy`; the manifest says so).

Bounce textures bake the light and the materials in (the paper's stated
limitation): the manifest records their hashes so the add-on can flag stale
bounces.
"""
from __future__ import annotations

import dataclasses
import math
import threading
import time

import numpy as np

from ...base.blas import single_threaded_blas
from ...base.errors import Cancelled
from ...base.memory import discard_pages
from ...base.threads import run_chunks
from ...model.material import Material
from ...sh.basis import basis_unchecked
from ...sh.gaunt import tpfl_matrix
from ...sh.rotation import rotate_zyz
from ...shading.materials import eval_materials
from ...shading.shade import lobe_factors
from ...texels.dilate import dilate, dilate_rows, dilation_rings
from ...texels.gbuffer import GBuffer
from . import hit_kernel
from .raytrace import RayScene
from .sampling import pattern_bank
from .transfer import (
    Points,
    TransferSettings,
    chunk_frames,
    chunk_plan,
    estimator_tables,
    shared_rotation,
    unoccluded_transfer,
)

SQRT_4PI = math.sqrt(4.0 * math.pi)

#: A texel whose float32 transfer is within this of the unoccluded value saw no
#: geometry with any transfer ray (the balanced estimator is exact there; one
#: blocked ray of 4096 moves the DC term by ~2e-4).
OPEN_TOLERANCE = 2e-5
#: The same test on a half-float texture read back from disk (half rounds the
#: coefficients, <= 1.8, by up to 5e-4; one blocked ray of 256 moves the DC
#: term by ~3e-3, of 4096 by ~2e-4, which this then misses).
HALF_OPEN_TOLERANCE = 1.5e-3
#: Rays per bounce chunk. A hit's shading makes temporaries of ~350 B; at the
#: transfer's 2^19 rays a chunk's arrays are tens of MB, which the allocator
#: maps fresh (and the kernel zeroes) every time: the shading ran 1.5x slower
#: than with 2^16, whose arrays are reused from the heap and stay in cache.
BOUNCE_CHUNK_RAYS = 1 << 16


@dataclasses.dataclass
class IncidentSet:
    """One set's texture that radiance leaving its surface is computed from,
    held only at the texels that may hold a value (covered texels and their
    dilation rings: ~60 % of an atlas), every other texel being zero.

    ``rows`` (M + 1, C) float32: row i is texel ``valid[i]``'s, the last is
    zeros (the layout of an exit table: relightable.level1_exit takes it as
    it is); ``valid`` (M,) ascending flat texel indices (row 0 = bottom).
    """

    rows: np.ndarray
    valid: np.ndarray
    width: int
    height: int

    #: Bytes of the pixel-major band :meth:`blocks_mean` builds at a time.
    BAND_BYTES = 32 << 20

    @classmethod
    def from_pixel_major(cls, pm: np.ndarray, width: int, height: int) -> "IncidentSet":
        """From a whole texture, pixel-major (H * W, C); ``valid`` = the texels with a non-zero value."""
        valid = np.flatnonzero(np.any(pm != 0, axis=1))
        rows = np.zeros((valid.size + 1, pm.shape[1]), np.float32)
        np.take(pm, valid, axis=0, out=rows[:-1])
        return cls(rows, valid, width, height)

    @classmethod
    def empty(cls, grown: np.ndarray, channels: int, valid: np.ndarray | None = None) -> "IncidentSet":
        """Zeros at the texels of mask ``grown`` (H, W) (texels.dilate.dilate's
        return), for :meth:`take` or :meth:`take_band` to fill; ``valid``: its
        flat indices when the caller has them already (shared, not copied)."""
        H, W = grown.shape
        if valid is None:
            valid = np.flatnonzero(grown.reshape(-1))
        return cls(np.zeros((valid.size + 1, channels), np.float32), valid, W, H)

    def take(self, c: int, plane: np.ndarray) -> None:
        """Channel ``c`` from its plane (H, W), zero outside ``valid`` (threads may take different channels)."""
        self.rows[:-1, c] = plane.reshape(-1)[self.valid]

    def take_band(self, y0: int, band: np.ndarray) -> None:
        """Every channel of texture rows y0 .. y0 + rows - 1 from ``band`` (C, rows, W)
        (exr_io.write_sh_planes' visit): the same values :meth:`take` takes."""
        C, n, W = band.shape
        lo, hi = np.searchsorted(self.valid, [y0 * W, (y0 + n) * W])
        at = self.valid[lo:hi] - y0 * W
        flat = band.reshape(C, n * W)
        for c in range(C):
            self.rows[lo:hi, c] = flat[c, at]

    @classmethod
    def from_planes(cls, planes: np.ndarray, grown: np.ndarray) -> "IncidentSet":
        """From channel planes (C, H, W) that are zero outside mask ``grown`` (H, W)
        (texels.dilate.dilate's return), one plane at a time: no pixel-major copy."""
        out = cls.empty(grown, planes.shape[0])
        for c in range(planes.shape[0]):
            out.take(c, planes[c])
        return out

    @property
    def channels(self) -> int:
        return int(self.rows.shape[1])

    #: Rows :meth:`at` copies at a time when it consumes the set.
    AT_BLOCK = 1 << 18

    def at(self, texels: np.ndarray, k: int | None = None, *, padded: bool = False,
           consume: bool = False) -> np.ndarray:
        """The first ``k`` (default all) channels at flat texel indices ``texels``
        (n,), zeros where the texture is empty: (n, k) float32, or with
        ``padded`` (n + 1, k) with a last row of zeros. When ``texels`` is
        ``valid`` itself and k = C, the rows themselves (no copy).
        ``consume`` (``texels`` ascending; the caller is done with this set):
        a copy is made a block of rows at a time, each giving back the pages
        of the rows behind it (base/memory.discard_pages), so the set and its
        copy are not both whole (#35); when a copy was made, the set's whole
        pages read as zeros afterwards."""
        k = self.channels if k is None else int(k)
        texels = np.asarray(texels)
        n = texels.shape[0]
        if k == self.channels and n == self.valid.size and np.array_equal(texels, self.valid):
            return self.rows if padded else self.rows[:-1]
        out = np.zeros((n + 1 if padded else n, k), np.float32)
        if self.valid.size == 0:
            return out
        first = np.searchsorted(self.valid, texels)       # ascending with texels: the rows still to read
        where = np.minimum(first, self.valid.size)
        where[self.valid[np.minimum(where, self.valid.size - 1)] != texels] = self.valid.size  # the zero row
        src = self.rows if k == self.channels else self.rows[:, :k]
        if not (consume and self.rows.flags.c_contiguous and n and np.all(np.diff(texels) > 0)):
            np.take(src, where, axis=0, out=out[:n])
            return out
        done = 0                                   # rows of the set below this are copied
        for a in range(0, n, self.AT_BLOCK):
            b = min(n, a + self.AT_BLOCK)
            np.take(src, where[a:b], axis=0, out=out[a:b])
            # Ascending texels read ascending rows: those below the next block's first are done
            # (``first``, not ``where``: a texel the set lacks reads the zero row at the end).
            nxt = min(int(first[b]) if b < n else self.valid.size, self.valid.size)
            if nxt > done:
                discard_pages(self.rows[done:nxt])
                done = nxt
        return out

    def band(self, row0: int, row1: int) -> np.ndarray:
        """Texture rows row0 .. row1 - 1, pixel-major ((row1 - row0) W, C) float32."""
        W = self.width
        out = np.zeros(((row1 - row0) * W, self.channels), np.float32)
        lo, hi = np.searchsorted(self.valid, [row0 * W, row1 * W])
        out[self.valid[lo:hi] - row0 * W] = self.rows[lo:hi]
        return out


@dataclasses.dataclass
class SurfaceTexels:
    """One set's shading inputs per texel, dilated like its textures.

    ``valid`` (M,) ascending flat texel indices (row 0 = bottom) that hold a
    value: covered texels and the dilation rings around them. Per valid texel:
    ``albedo``/``spec`` (M, 3), Phong ``exponent`` (M,), unit shading
    ``normal`` (M, 3) (normal-mapped where the G-buffer is), all float64.
    ``row_of`` (H * W,) int32: each texel's index in ``valid``, M where empty.
    """

    width: int
    height: int
    valid: np.ndarray
    albedo: np.ndarray
    spec: np.ndarray
    exponent: np.ndarray
    normal: np.ndarray
    row_of: np.ndarray

    @property
    def glossy(self) -> bool:
        return bool(self.spec.strides[0] != 0 and np.any(self.spec > 0.0))


#: Texels whose materials surface_texels evaluates at a time.
SURFACE_BLOCK = 1 << 18


def surface_texels(sc, gb: GBuffer, dilate_iterations: int, *, diffuse_only: bool = False) -> SurfaceTexels:
    """Material and shading normal at every texel centre of ``gb``, dilated by
    ``dilate_iterations`` rings (the mean of filled neighbours, the textures'
    rule; normals renormalised). ``diffuse_only``: the albedo alone (spec,
    exponent and normal are zeros), for a grid only the diffuse term leaves from.

    Built at the valid texels' rows, dilated there (texels.dilate.dilate_rows,
    the same sums as the planes' dilation): no (channels, H, W) planes, which
    with their copies at the valid texels had held ~2x the result (#35)."""
    H, W = gb.height, gb.width
    rings, grown = dilation_rings(gb.mask(), dilate_iterations)
    valid = np.flatnonzero(grown.reshape(-1))
    grown = None
    M = valid.size
    row_of = np.full(H * W, M, np.int32)
    row_of[valid] = np.arange(M, dtype=np.int32)
    albedo = np.zeros((M, 3))
    spec = exponent = normal = None
    if not diffuse_only:
        spec, exponent, normal = np.zeros((M, 3)), np.zeros(M), np.zeros((M, 3))
    # The materials in blocks of texels (their formulas are per texel): the
    # per-texel temporaries of a whole 2048² G-buffer were ~250 MB.
    for a in range(0, gb.n, SURFACE_BLOCK):
        b = min(a + SURFACE_BLOCK, gb.n)
        p = eval_materials(sc, gb.tri[a:b], gb.bary[a:b])
        at = row_of[gb.texel[a:b]]
        albedo[at] = p.albedo
        if not diffuse_only:
            spec[at] = p.spec
            exponent[at] = p.exponent
            normal[at] = gb.normal[a:b]
    dilate_rows([albedo] if diffuse_only else [albedo, spec, exponent, normal], row_of, W, rings)
    if diffuse_only:
        # Read-only zeros that take no memory (a full-resolution grid has millions of texels).
        zeros3 = np.broadcast_to(np.zeros(3), (M, 3))
        return SurfaceTexels(W, H, valid, albedo, zeros3, np.broadcast_to(np.zeros(()), (M,)), zeros3, row_of)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    return SurfaceTexels(W, H, valid, albedo, spec, exponent, normal, row_of)


@dataclasses.dataclass
class TexelRows:
    """A texel grid's lookup into per-texel rows: ``row_of`` (H * W,) int32,
    each texel's row (M, the last row of zeros, where the grid has no value)."""

    width: int
    height: int
    row_of: np.ndarray
    n_rows: int                          # M + 1: the valid texels' rows and the zero row

    @classmethod
    def of(cls, surf: "SurfaceTexels") -> "TexelRows":
        return cls(surf.width, surf.height, surf.row_of, surf.valid.size + 1)

    def rows_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Rows of the texels nearest to UV coordinates (x, y) in [0, 1]."""
        ix = np.clip((x * self.width).astype(np.int64), 0, self.width - 1)
        iy = np.clip((y * self.height).astype(np.int64), 0, self.height - 1)
        return self.row_of[iy * self.width + ix]


@dataclasses.dataclass
class ExitTextures:
    """Radiance leaving one set's surface, ready for lookups (float32 rows).

    One row per valid texel of a grid and a last row of zeros, so no
    texture-sized array is filled for a level. ``diffuse`` (M + 1, 3): D_c on
    the grid ``diffuse_grid``. ``glossy`` (M' + 1, 3 + 3K) or None when the
    set has no specular lobe: the shading normal, then G_R, G_G, G_B (K each),
    on ``glossy_grid`` (the same grid, or a coarser one: bounce level 1 under
    tuning auto, where the diffuse term keeps the transfer's resolution).
    """

    diffuse_grid: TexelRows
    diffuse: np.ndarray
    glossy_grid: TexelRows | None
    glossy: np.ndarray | None


def exit_textures(surf: SurfaceTexels, Lp: np.ndarray, bands: int,
                  diffuse_at: tuple[SurfaceTexels, np.ndarray] | None = None) -> ExitTextures:
    """Exit radiance textures from incident radiance ``Lp`` (M, 3, K) at the
    valid texels of ``surf`` (float32 or float64; computed in float32, which the
    lookups use). ``diffuse_at`` = (SurfaceTexels, Lp_dc (M', 3)): the diffuse
    term from that (finer) grid instead, from the DC terms of its incident radiance."""
    K = bands * bands
    M = surf.valid.size
    if Lp.shape != (M, 3, K):
        raise ValueError(f"incident radiance must be ({M}, 3, {K}), got {Lp.shape}")
    dsurf, dc = (surf, Lp[:, :, 0]) if diffuse_at is None else diffuse_at
    diffuse = np.zeros((dsurf.valid.size + 1, 3), np.float32)
    diffuse[:-1] = (dsurf.albedo * (SQRT_4PI / math.pi)) * dc
    glossy = None
    if surf.glossy:
        A = lobe_factors(surf.exponent, bands).astype(np.float32)                    # (M, K)
        spec = surf.spec.astype(np.float32)
        glossy = np.empty((M + 1, 3 + 3 * K), np.float32)
        glossy[M] = 0.0
        rows = glossy[:M]
        rows[:, :3] = surf.normal
        for c in range(3):
            blk = rows[:, 3 + c * K:3 + (c + 1) * K]
            np.multiply(A, spec[:, c:c + 1], out=blk)
            blk *= Lp[:, c, :]
    grid = TexelRows.of(surf)
    dgrid = grid if diffuse_at is None else TexelRows.of(dsurf)
    return ExitTextures(dgrid, diffuse, grid if glossy is not None else None, glossy)


def incident_at(surf: SurfaceTexels, incident: IncidentSet, light: np.ndarray, bands: int) -> np.ndarray:
    """Lp (M, 3, K) float32 at the valid texels: M(L) T of a transfer texture lit
    by ``light`` (level 1; later levels read the previous bounce planes)."""
    K = bands * bands
    rows = incident.at(surf.valid)
    Mx = tpfl_matrix(np.asarray(light)[:K], bands)                               # (3, K, K)
    M2 = np.ascontiguousarray(Mx.reshape(3 * K, K).T, dtype=np.float32)
    return (rows[:, :K] @ M2).reshape(-1, 3, K)


def incident_dc_at(surf: SurfaceTexels, incident: IncidentSet, light: np.ndarray, bands: int) -> np.ndarray:
    """(M, 3) float32: the DC terms of :func:`incident_at` alone (all the
    diffuse exit radiance reads), one (K, 3) product instead of (K, 3K)."""
    K = bands * bands
    Mx = tpfl_matrix(np.asarray(light)[:K], bands)                               # (3, K, K)
    M0 = np.ascontiguousarray(Mx[:, 0, :].T, dtype=np.float32)                   # (K, 3)
    return incident.at(surf.valid)[:, :K] @ M0


def block_mean_incident(incident: IncidentSet, valid: np.ndarray, f: int, dilate_iterations: int) -> IncidentSet:
    """``incident`` on the grid 1/f per side: each coarse texel the mean of the
    f x f block's texels in ``valid`` (flat indices that hold a value), blocks
    without one filled by ``dilate_iterations`` rings (the textures' rule)."""
    W, H, C = incident.width, incident.height, incident.channels
    w, h = W // f, H // f
    mask = np.zeros(H * W, np.float32)
    mask[valid] = 1.0
    count = mask.reshape(h, f, w, f).sum(axis=(1, 3))
    have = count > 0
    # The block means straight into channel planes, a band of block rows at a time
    # (each block's sum is the same whichever band holds it): no (h, w, C) copy
    # of them beside the planes (#35).
    planes = np.zeros((C, h, w), np.float32)
    step = max(1, IncidentSet.BAND_BYTES // max(1, f * W * C * 4))
    for a0 in range(0, h, step):
        a1 = min(h, a0 + step)
        pm = incident.band(a0 * f, a1 * f)
        blocks = np.einsum("aibjc,aibj->abc", pm.reshape(a1 - a0, f, w, f, C),
                           mask[a0 * f * W:a1 * f * W].reshape(a1 - a0, f, w, f))
        hv = have[a0:a1]
        blocks[hv] /= count[a0:a1][hv][:, None]
        planes[:, a0:a1] = np.moveaxis(blocks, 2, 0)
    mask = pm = blocks = None
    return IncidentSet.from_planes(planes, dilate(planes, have, dilate_iterations))


def level_energy(tex_rows: np.ndarray) -> float:
    """Energy of incident-radiance SH rows (n, 3K) or (n, 3, K): the sum of the
    DC terms (cosine-weighted irradiance / sqrt(4 pi)) over texels and colours."""
    r = np.asarray(tex_rows)
    r = r.reshape(r.shape[0], 3, -1)
    return float(np.sum(r[:, :, 0], dtype=np.float64))


def textured_triangles(sc) -> np.ndarray:
    """(T,) bool: the triangle's material reads a texture (its factors vary
    over the surface, so no single value stands for them)."""
    if sc.material_id is None or not sc.materials:
        return np.zeros(sc.n_triangles, bool)
    textured = [i for i, m in enumerate(sc.materials) if Material.from_dict(m).textured]
    return np.isin(sc.material_id, textured)


def glossy_triangles(sc) -> np.ndarray:
    """(T,) bool: the triangle's material has a specular lobe somewhere
    (textured materials count as glossy if any factor could make one)."""
    T = sc.n_triangles
    p = eval_materials(sc, np.arange(T), np.full((T, 3), 1.0 / 3.0))
    return np.any(p.spec > 0.0, axis=1) | textured_triangles(sc)


def uv_frames(sc) -> np.ndarray:
    """(T, 6) float32 per triangle: uv of corner 0 and the two edge vectors
    (one gather per hit, :func:`hit_uvs`)."""
    uv = sc.uvs.astype(np.float64)
    return np.ascontiguousarray(np.concatenate([uv[:, 0], uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]], axis=1),
                                dtype=np.float32)


def hit_uvs(frames: np.ndarray, tri: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) texture coordinates of hits on triangles ``tri`` at Embree's (u, v)."""
    f = np.take(frames, tri, axis=0)
    return f[:, 0] + u * f[:, 2] + v * f[:, 4], f[:, 1] + u * f[:, 3] + v * f[:, 5]


def texel_order(near: np.ndarray, n_rows: int) -> np.ndarray:
    """A permutation visiting ``near`` (rows of a table of ``n_rows``) in
    ascending blocks. Random lookups in a texture of hundreds of MB are ~5x
    slower than ordered ones, and a radix sort on 16-bit keys (blocks of
    texels) costs a fraction of that."""
    shift = max(0, int(n_rows - 1).bit_length() - 16)
    return np.argsort((near >> shift).astype(np.uint16), kind="stable")


def hits_by_set(sc, frames: np.ndarray, exits: dict, tri: np.ndarray, u: np.ndarray, v: np.ndarray):
    """For each set of ``exits`` (set index -> an exit whose ``diffuse_grid`` is
    a TexelRows) that hits land on: (exit, sel, near, x, y), ``sel`` the hits'
    indices in texel order (:func:`texel_order`), ``near`` their rows on the
    exit's diffuse grid and (x, y) their texture coordinates."""
    sets = sc.set_id[tri]
    for s, ex in exits.items():
        sel = np.flatnonzero(sets == s)
        if sel.size == 0:
            continue
        x, y = hit_uvs(frames, tri[sel], u[sel], v[sel])
        near = ex.diffuse_grid.rows_at(x, y)
        o = texel_order(near, ex.diffuse_grid.n_rows)
        yield ex, sel[o], near[o], x[o], y[o]


def reflect_rows(n: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(3, m) unit reflections of the view vectors ``w`` (3, m) about the normals
    ``n`` (3, m) (dilated, so not unit): r = 2 (n.w) n / |n|^2 - w. Coordinates
    as rows: every operation runs on contiguous arrays (strided columns of a
    gathered table made this twice as slow)."""
    d = 2.0 * (n * w).sum(axis=0) / np.maximum((n * n).sum(axis=0), np.float32(1e-30))
    r = d * n
    r -= w
    r /= np.sqrt(np.maximum((r * r).sum(axis=0), np.float32(1e-30)))
    return r


class ExitShader:
    """Radiance leaving hit points towards the ray origins, from per-set
    :class:`ExitTextures` (set index -> textures; sets without are black).

    Lookups take the nearest texel. Bilinear lookups (the renderer's filter)
    read four rows instead of one and were, with the glossy rows' 312 bytes,
    two thirds of the bounce bake's time; within a texel the exit radiance
    varies far less than a bounce texel's Monte Carlo noise, and the
    receiver averages many hits (tests/test_bounce.py keeps its brute-force
    tolerances; docs/benchmarks.md has the measurement).
    """

    def __init__(self, sc, exits: dict, bands: int, glossy_tri: np.ndarray):
        self.sc, self.exits, self.bands = sc, exits, bands
        self.K = bands * bands
        self.uv_frame = uv_frames(sc)
        self.glossy_tri = glossy_tri
        # The compiled per-hit loop when numba is there (hit_kernel; same
        # results to float32 rounding), else radiance()'s numpy.
        self.compiled = hit_kernel.available()
        self.consts = hit_kernel.recurrence_constants(bands)

    def path(self) -> str:
        """How hits are shaded: "compiled" (hit_kernel) or "numpy" (the manifest says which)."""
        return "compiled" if self.compiled and hit_kernel.usable("baked", self.bands) else "numpy"

    def shade_rays(self, L: np.ndarray, prim: np.ndarray, u: np.ndarray, v: np.ndarray, ray_of: np.ndarray,
                   D: np.ndarray) -> None:
        """Write into rows ray_of of ``L`` (rays, 3) float32 the radiance that
        hits (prim, u, v) send back along the rays ``D`` (rays, 3) (zero from
        sets without exit textures); other rows are left as they are."""
        if self.path() == "numpy":
            L[ray_of] = self.radiance(prim, u, v, -D[ray_of])
            return
        sets = self.sc.set_id[prim]
        lit = np.zeros(prim.size, bool)
        for s, ex in self.exits.items():
            mine = sets == s
            sel = np.flatnonzero(mine)
            if sel.size:
                lit |= mine
                hit_kernel.shade_set_hits(sel, prim, u, v, ray_of, D, self.uv_frame, self.glossy_tri, ex,
                                          self.bands, self.consts, L)
        L[ray_of[~lit]] = 0.0                        # hits on sets dark at this level

    def radiance(self, tri: np.ndarray, u: np.ndarray, v: np.ndarray, view: np.ndarray) -> np.ndarray:
        """(n, 3) float32 for hits on triangles ``tri`` at Embree's (u, v),
        ``view`` (n, 3) float32 unit vectors from the hit towards the ray origin."""
        out = np.zeros((tri.size, 3), np.float32)
        for ex, sel, near, x, y in hits_by_set(self.sc, self.uv_frame, self.exits, tri, u, v):
            val = np.take(ex.diffuse, near, axis=0)
            gl = self.glossy_tri[tri[sel]] if ex.glossy is not None else None
            if gl is not None and gl.any():
                g = np.flatnonzero(gl)
                gnear = near[g] if ex.glossy_grid is ex.diffuse_grid else ex.glossy_grid.rows_at(x[g], y[g])
                val[g] = self._glossy(ex, gnear, view[sel[g]], val[g])
            np.maximum(val, 0.0, out=val)
            out[sel] = val
        return out

    def _glossy(self, ex: ExitTextures, row: np.ndarray, view: np.ndarray, diffuse: np.ndarray) -> np.ndarray:
        """sum_lm G_c,lm y_lm(r) + ``diffuse`` (m, 3) at glossy rows ``row``, r the reflection of view."""
        G = np.take(ex.glossy, row, axis=0)                                   # (m, 3 + 3K)
        m, K = row.size, self.K
        r = reflect_rows(np.ascontiguousarray(G[:, 0:3].T), np.ascontiguousarray(view.T))
        y = basis_unchecked((r[0], r[1], r[2]), self.bands, np.float32)     # (m, K)
        out = np.einsum("nck,nk->nc", G[:, 3:].reshape(m, 3, K), y)
        out += diffuse
        return out


def open_texels(T_texels: np.ndarray, normals: np.ndarray, bands: int,
                tol: float = OPEN_TOLERANCE, block: int = 1 << 16) -> np.ndarray:
    """(N,) bool: transfer equals the unoccluded clamped cosine (no ray blocked).
    In blocks of texels: whole-set (N, K) float64 temporaries made it 2-3x slower."""
    out = np.empty(len(T_texels), bool)
    for a in range(0, out.size, block):
        b = min(a + block, out.size)
        A = unoccluded_transfer(normals[a:b], bands)
        out[a:b] = np.abs(np.asarray(T_texels[a:b], np.float64) - A).max(axis=1) <= tol
    return out


def level_points(pts: Points, skip: np.ndarray, level: int) -> Points:
    """A bounce level's Points: ``pts``' own arrays (not copies) with ids tagged
    by the level, so every level draws its own patterns and frames from the
    one seed scheme (transfer.chunk_plan, chunk_frames); ``analytic`` is
    ``skip`` (N,): the texels the level does not trace."""
    return Points(pts.position, pts.normal, pts.geo_normal, pts.ids + (np.int64(level) << 50), skip,
                  pts.frame_group)


@dataclasses.dataclass
class ChunkHits:
    """One traced chunk of a bounce level, for the estimator that projects it.

    ``cols`` (n,) the chunk's texel columns in the (C, H*W) textures; ``S``
    rays per texel; ``D`` (n*S, 3) float32 ray directions (texel-major);
    ``hit`` indices of the rays that hit, ``prim``/``u``/``v`` their triangle
    and barycentrics; ``table`` (S, K) the estimator table; ``fr`` the
    chunk's frames (``shared``: one frame for all its texels)."""

    cols: np.ndarray
    S: int
    D: np.ndarray
    hit: np.ndarray
    prim: np.ndarray
    u: np.ndarray
    v: np.ndarray
    table: np.ndarray
    fr: object

    @property
    def n(self) -> int:
        return self.cols.size

    def to_world(self, rows: np.ndarray, K: int, per_texel: int) -> np.ndarray:
        """World SH (n * per_texel, K) of ray values ``rows`` (n * per_texel, S)
        float32 (texel-major): the estimator's first K coefficients in each
        texel's frame, turned to the world."""
        table = self.table[:, :K]
        if self.fr.shared:
            # One frame: turn the estimator table to world once, not every texel's result.
            return rows @ (table.astype(np.float64) @ shared_rotation(self.fr, K)).astype(np.float32)
        rep = lambda a: np.repeat(a, per_texel)  # noqa: E731
        return rotate_zyz(rows @ table, rep(self.fr.alpha), rep(self.fr.beta), rep(self.fr.gamma))

    def local_to_world(self, local: np.ndarray, K: int, per_texel: int) -> np.ndarray:
        """World SH (n * per_texel, K) of coefficients ``local`` (n * per_texel,
        K) float32 in each texel's frame (texel-major). Each texel's rotation
        is built once, as rotate_zyz of the identity's K rows, and applied to
        its rows by one batched product: per_texel rotations of each texel
        (27 for the relightable glossy rows against 9 rows) were most of a
        relightable chunk's projection."""
        if self.fr.shared:
            return local @ shared_rotation(self.fr, K).astype(np.float32)
        n = self.n
        eye = np.tile(np.eye(K, dtype=np.float32), (n, 1))                     # (n K, K)
        rep = lambda a: np.repeat(a, K)  # noqa: E731
        dt = rotate_zyz(eye, rep(self.fr.alpha), rep(self.fr.beta), rep(self.fr.gamma)).reshape(n, K, K)
        return np.matmul(local.reshape(n, per_texel, K), dt).reshape(n * per_texel, K)


@dataclasses.dataclass(eq=False)
class LevelRays:
    """What every chunk of one set's bounce level traces from (level_rays):
    the set's Points ``sub`` (ids tagged by the level; chunks index them),
    their texture columns ``cols`` and the settings. Picklable: a Dask worker receives it
    once per level (core/bake/executors/dask_cluster.py) and traces chunks from it
    exactly as the local threads do."""

    sub: Points
    cols: np.ndarray
    st: TransferSettings
    G: int                             # ray patterns (transfer.chunk_plan)
    n: int = 0                         # texels traced (the others are skipped)

    def tables(self) -> tuple[np.ndarray, np.ndarray]:
        """(directions (G, S, 3), estimator table (G, S, K)) of the level's patterns (cached)."""
        st = self.st
        dirs_bank, _, _ = pattern_bank(self.G, st.rays, st.bands, st.sampler, st.distribution, st.seed)
        _, table = estimator_tables(st, self.G, st.rays)
        return dirs_bank, table


def level_rays(gb: GBuffer, pts: Points, skip: np.ndarray, st: TransferSettings, level: int):
    """(LevelRays, chunks) of one set's level: the texels not skipped, planned
    by transfer.chunk_plan (biggest chunks first). The planner passes over
    skipped texels as it does over analytic ones: the same chunks, in the
    same order, as planning the traced texels alone, without copying their
    points (88 B a texel, #35)."""
    sub = level_points(pts, skip, level)
    chunks, G = chunk_plan(sub, dataclasses.replace(st, analytic=True))
    return (LevelRays(sub, gb.texel, st, G, int(skip.size - np.count_nonzero(skip))),
            sorted(chunks, key=lambda c: -c.idx.size))


def trace_chunk(rs: RayScene, lr: LevelRays, tables, chunk) -> ChunkHits:
    """Trace one chunk of a level (tables = lr.tables()): its rays and hits."""
    st, (dirs_bank, table) = lr.st, tables
    g, idx = chunk.g, chunk.idx
    fr = chunk_frames(rs, lr.sub, idx, st.seed, shared=chunk.shared)
    n, S = idx.size, st.rays
    if fr.shared:
        # Texels of one flat face group share the frame (as in the transfer bake).
        D = np.tile(dirs_bank[g] @ np.asarray(fr.R[0]).T, (n, 1))
    else:
        D = np.matmul(dirs_bank[g][None], fr.R.transpose(0, 2, 1)).reshape(-1, 3)
    O = np.repeat(fr.origins, S, axis=0)
    prim, u, v, _ = rs.intersect(O, np.ascontiguousarray(D))
    hit = np.flatnonzero(prim >= 0)
    return ChunkHits(lr.cols[idx], S, D, hit, prim[hit].astype(np.int64), u[hit], v[hit], table[g], fr)


def trace_bounce_level(rs: RayScene, gb: GBuffer, pts: Points, skip: np.ndarray, st: TransferSettings,
                       level: int, project, store, *, progress=None, cancel=None, remote=None) -> dict:
    """Trace one set's bounce level: every chunk's hits go to ``project(ChunkHits)``
    (a pure function of the chunk: BakedProjection, relight.RelightProjection),
    whose result ``store(cols, result)`` writes for the chunk's texel columns
    (called for disjoint texels; from the bake's threads, or from the calling
    thread when ``remote`` (distributed.DaskBake) runs the chunks on a
    cluster). ``skip`` (N,) marks texels that get zero without rays. Returns
    the stats (texels, skipped_texels, rays_traced, hits_shaded, seconds)."""
    lr, chunks = level_rays(gb, pts, skip, st, level)
    stats = {"texels": int(gb.n), "skipped_texels": int(skip.sum()), "rays_traced": 0,
             "hits_shaded": 0}
    lock = threading.Lock()
    t0 = time.perf_counter()
    done = 0

    def sink(n, cols, result, hits):
        nonlocal done
        store(cols, result)
        with lock:
            stats["rays_traced"] += n * st.rays
            stats["hits_shaded"] += hits
            done += n

    def on_result(_):
        if progress:
            progress(done, lr.n, stats["rays_traced"])

    if remote is not None:
        remote.trace_level(lr, chunks, project, sink, on_result, cancel)
    else:
        tables = lr.tables()

        def run(chunk):
            if cancel is not None and cancel.is_set():
                raise Cancelled()
            ch = trace_chunk(rs, lr, tables, chunk)
            sink(ch.n, ch.cols, project(ch), int(ch.hit.size))

        # The chunks' products are small and run one per core: OpenBLAS's own
        # threads would only spin against them (a third of the time, measured).
        with single_threaded_blas():
            run_chunks(run, chunks, st.n_threads, on_result, cancel)
    stats["seconds"] = time.perf_counter() - t0
    return stats


@dataclasses.dataclass(eq=False)
class BakedProjection:
    """A baked level's projection of one chunk: (3K, n) float32, the world SH
    of the radiance its rays bring (``shader`` at the hits), colour-major
    rows (R.sh000.., G.., B..) for the chunk's texel columns."""

    shader: ExitShader
    K: int

    def __call__(self, ch: ChunkHits) -> np.ndarray:
        n, S, K = ch.n, ch.S, self.K
        L = np.zeros((n * S, 3), np.float32)
        if ch.hit.size:
            self.shader.shade_rays(L, ch.prim, ch.u, ch.v, ch.hit, ch.D)
        # One product for the three colours: (n*3, S) @ (S, K).
        Lt = np.ascontiguousarray(L.reshape(n, S, 3).transpose(0, 2, 1)).reshape(n * 3, S)
        return ch.to_world(Lt, K, 3).reshape(n, 3 * K).T


def bake_bounce_set(rs: RayScene, gb: GBuffer, pts: Points, skip: np.ndarray, shader: ExitShader,
                    st: TransferSettings, level: int, *, progress=None, cancel=None, remote=None):
    """One set's bounce level: returns ((3K, H*W) float32 texture, coverage mask
    (H, W), stats). ``skip`` (N,) marks texels that get zero without rays."""
    K = st.bands ** 2
    tex = np.zeros((3 * K, gb.height * gb.width), np.float32)

    def store(cols, planes):
        hit_kernel.store_columns(tex, cols, planes)

    stats = trace_bounce_level(rs, gb, pts, skip, st, level, BakedProjection(shader, K), store,
                               progress=progress, cancel=cancel, remote=remote)
    stats["hit_shading"] = shader.path()
    return tex, gb.mask(), stats


def bounce_settings(st: TransferSettings, bounce_rays: int) -> TransferSettings:
    """The transfer settings a bounce pass traces with (its own ray count)."""
    return dataclasses.replace(st, rays=bounce_rays, adaptive_tol=0.0, analytic=False,
                               estimator="balanced", chunk_rays=min(st.chunk_rays, BOUNCE_CHUNK_RAYS))
