"""Relightable inter-reflections (``--bounce-mode relightable``): bounce light
as a linear map of the light, so turning or swapping the World relights it
without a rebake (docs/shading.md, "Relightable bounces").

Light propagates in each colour channel alone and every bounce level is
linear in the light L (3 colours x K coefficients, K = bands²). Per receiver
texel p and colour c the bake stores the operator R(p)_c that maps the
light's coefficients to the bounce light's:

    B(p)_c,o = sum_i R(p)_c,o,i L_c,i

summed over all levels (N bounces, one texture). Two parts:

* ``dc`` (3, K): the DC row o = 0 over every light coefficient: all that
  diffuse shading (and the next level's diffuse exit) reads, exact;
* ``glossy`` (3, Kg - 1, Kg), Kg = glossy_bands²: rows o = 1 .. Kg - 1 over
  the first Kg light coefficients, only for sets with a glossy material:
  the directional bounce light glossy lobes read, band-limited in and out
  (the stated approximation; glossy_bands = bands is exact).

Exit radiance as linear forms. At a hit q the radiance leaving towards p is,
in the light's coefficients (the baked path's exit radiance, bounce.py, with
L left free):

    level 1:  diffuse  rho_c / pi * T(q)_i          (M(L)T's DC is L.T / sqrt(4 pi))
              glossy   k_s,c sum_o y_o(r) E(q)_o,i,  E_o,i = A_o(s) M(T(q))_o,i
    level n:  diffuse  rho_c sqrt(4 pi) / pi * R_{n-1}(q)_c,0,i
              glossy   k_s,c sum_o y_o(r) A_o(s) R_{n-1}(q)_c,o,i

with o, i < Kg in the glossy terms (M(T) the triple-product matrix of the
transfer, A_o the Phong lobe's factors, r the reflection of q -> p). The
receiver projects these vectors exactly as the baked estimator projects
radiance (same rays, seeds, tables and frames), the DC row from the
estimator's DC weights, the glossy rows turned to the world like any SH.
Unlike the baked path nothing is clamped at zero per hit (a clamp is not
linear): the two agree wherever the band-limited exit radiance is not
negative.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from ...base.memory import discard_pages
from ...sh.basis import basis_unchecked
from ...sh.gaunt import sparse_gaunt
from ...shading.shade import lobe_factors
from ...texels.gbuffer import GBuffer
from . import hit_kernel
from .bounce import ChunkHits, SurfaceTexels, TexelRows, hits_by_set, reflect_rows, trace_bounce_level, uv_frames
from .column_spill import ColumnSpill
from .raytrace import RayScene
from .transfer import Points, TransferSettings

SQRT_4PI = math.sqrt(4.0 * math.pi)
_NO_FORMS = np.zeros((1, 1, 1, 1), np.float32)      # placeholders for a set without a specular lobe
_NO_SCALE = np.zeros((1, 3), np.float32)
#: Default bands of the glossy part (in and out): 9 x 9 per colour.
GLOSSY_BANDS = 3
#: Rows of an exit table scaled at a time (level1_exit).
EXIT_BLOCK = 1 << 18


def relight_shared_colour(st) -> bool:
    """Whether the glossy rows are stored once for all colours (tuning auto:
    exr_io.expand_shared_glossy; 147 instead of 291 channels at the default
    bands; the room's relit-vs-rebaked error within 0.04 percentage points of
    the per-colour rows', docs/benchmarks.md). Tuning fixed keeps one per colour."""
    return st.tuning == "auto"


@dataclasses.dataclass
class RelightRows:
    """One receiver set's relightable bounce light at M texels (float32):
    ``dc`` (M, 3, K), ``glossy`` (M, 3, Kg - 1, Kg) or None."""

    dc: np.ndarray
    glossy: np.ndarray | None


@dataclasses.dataclass
class RelightExit:
    """Radiance leaving one source set as linear forms of the light.

    Diffuse: per hit ``d_scale[row] (3,) * d_rows[row] (Cd, K)`` with Cd = 1
    (level 1: the transfer, colour by the scale) or 3 (later levels), on
    ``diffuse_grid``. Glossy (None without a specular lobe): per hit
    ``g_scale[row] (3,) * sum_o y_o(r) g_rows[row] (Cg, Kg, Kg)[:, o, :]``
    with the shading ``normal[row]``, on ``glossy_grid``. Each table has a
    last row of zeros (empty texels)."""

    diffuse_grid: TexelRows
    d_rows: np.ndarray
    d_scale: np.ndarray
    glossy_grid: TexelRows | None = None
    g_rows: np.ndarray | None = None
    g_scale: np.ndarray | None = None
    normal: np.ndarray | None = None


def _with_zero_row(a: np.ndarray) -> np.ndarray:
    out = np.zeros((a.shape[0] + 1,) + a.shape[1:], np.float32)
    out[:-1] = a
    return out


#: A last block of rows shorter than this joins the one before it (transfer_product_rows):
#: numpy multiplies a single row by another BLAS routine, whose sums round differently.
MIN_TAIL_ROWS = 64


def row_blocks(n: int, block: int | None = None) -> list[tuple[int, int]]:
    """[(a, b)] blocks of ``block`` (default EXIT_BLOCK) rows covering 0 .. n - 1,
    a short last block (under MIN_TAIL_ROWS) joined to the one before it."""
    edges = list(range(0, n, block or EXIT_BLOCK))
    if len(edges) > 1 and n - edges[-1] < MIN_TAIL_ROWS:
        edges.pop()
    return list(zip(edges, edges[1:] + [n]))


def transfer_product_rows(T: np.ndarray, kg: int, out: np.ndarray | None = None,
                          consume: bool = False) -> np.ndarray:
    """(M, Kg, Kg) float32: M(T)_o,i = sum_j tau_o,i,j T_j for o, i < Kg, per row
    of ``T`` (M, K) (every j: the transfer keeps all its bands); one (K, Kg²)
    product with the Gaunt tensor's slab, written into ``out`` (M, Kg, Kg)
    C-contiguous float32 when given, a block of rows at a time (the same
    values as one product: BLAS sums each element over j alike, checked in
    tests/test_relight.py). ``consume`` (with ``out``; ``T`` C-contiguous
    float32 the caller is done with): each block of ``T`` gives its pages back
    once multiplied (base/memory.discard_pages) and reads as zeros
    afterwards, so ``T`` and the table are not both whole (#35)."""
    K = T.shape[1]
    g = sparse_gaunt(int(round(math.sqrt(K))))
    sel = (g.i < kg) & (g.j < kg)
    C = np.zeros((K, kg * kg))
    np.add.at(C, (g.k[sel], g.i[sel].astype(np.int64) * kg + g.j[sel]), g.value[sel])
    T = np.asarray(T, np.float32)
    if out is None:
        return (T @ C.astype(np.float32)).reshape(-1, kg, kg)
    C32 = C.astype(np.float32)
    flat = out.reshape(T.shape[0], kg * kg)
    consume = consume and T.flags.c_contiguous
    for a, b in row_blocks(T.shape[0]):
        np.matmul(T[a:b], C32, out=flat[a:b])
        if consume:
            discard_pages(T[a:b])
    return out


def level1_exit(surf: SurfaceTexels, T_rows: np.ndarray, glossy_bands: int,
                fine: tuple[SurfaceTexels, np.ndarray] | None = None, *,
                consume_surface: bool = False) -> RelightExit:
    """Level 1's exit forms from the transfer ``T_rows`` (M + 1, K) float32 at
    ``surf``'s M valid texels, then a row of zeros (bounce.IncidentSet.at(..., padded=True):
    the diffuse table is that array itself, not a copy); ``fine`` =
    (SurfaceTexels, T rows alike) of a finer grid the diffuse term leaves
    from (as bounce.exit_textures' ``diffuse_at``). With ``fine`` both are
    consumed: the fine SurfaceTexels' albedo and valid become None and,
    when ``surf`` is glossy, ``T_rows``' whole pages are given back as the
    glossy table is made from them (#35: neither is held beside it). ``consume_surface`` (the last level: nothing reads ``surf``
    after it): its float64 shading arrays become None once the exit's own
    float32 copies are made, before the glossy table is."""
    dsurf, dT = (surf, T_rows) if fine is None else fine
    if dT.dtype != np.float32 or dT.shape[0] != dsurf.valid.size + 1 or dT[-1].any():
        raise ValueError("level1_exit: transfer rows must be (M + 1, K) float32 with a last row of zeros")
    grid = TexelRows.of(surf)
    dgrid = grid if fine is None else TexelRows.of(dsurf)
    # Scales and lobes in blocks of rows (the same values): no whole-grid float64
    # temporaries beside the tables (they made the bounce's peak at 2048², #35).
    d_scale = np.zeros((dsurf.valid.size + 1, 3), np.float32)
    for a in range(0, dsurf.valid.size, EXIT_BLOCK):
        b = min(a + EXIT_BLOCK, dsurf.valid.size)
        d_scale[a:b] = dsurf.albedo[a:b] / math.pi
    if fine is not None:
        # Consumed: the fine grid's albedo and texel list (32 B a texel) are done with
        # before the glossy table is made; its row lookup stays in dgrid.
        dsurf.albedo = dsurf.valid = None
    ex = RelightExit(dgrid, np.ascontiguousarray(dT)[:, None, :], d_scale)
    if surf.glossy:
        kg = glossy_bands * glossy_bands
        # lobe_factors per distinct exponent, gathered a block at a time.
        u, inv = np.unique(np.asarray(surf.exponent, np.float64), return_inverse=True)
        A = lobe_factors(u, glossy_bands).astype(np.float32)                          # (U, Kg)
        ex.g_scale = _with_zero_row(surf.spec)
        ex.normal = _with_zero_row(surf.normal)
        M = surf.valid.size
        if consume_surface:
            # 80 B a texel of float64 not held beside the table (#35).
            surf.albedo = surf.spec = surf.exponent = surf.normal = None
        # Built in the table with its zero row, in place: no (M, Kg, Kg) temporaries.
        g_rows = np.zeros((M + 1, 1, kg, kg), np.float32)
        # With a finer diffuse grid T_rows is this grid's own (the block means): consumed as
        # the table is made. Otherwise it is the diffuse table itself, kept.
        E = transfer_product_rows(T_rows[:-1], kg, out=g_rows[:-1, 0], consume=fine is not None)
        inv = inv.reshape(-1)
        for a in range(0, inv.size, EXIT_BLOCK):
            E[a:a + EXIT_BLOCK] *= A[inv[a:a + EXIT_BLOCK]][:, :, None]
        inv = None
        ex.glossy_grid = grid
        ex.g_rows = g_rows
    elif consume_surface:
        surf.albedo = surf.spec = surf.exponent = surf.normal = None
    return ex


def later_exit(surf: SurfaceTexels, rows: RelightRows, glossy_bands: int) -> RelightExit:
    """Level n > 1's exit forms from level n - 1's relightable rows at ``surf``'s
    valid texels (``rows.glossy`` None: the lobe reads the DC row alone)."""
    grid = TexelRows.of(surf)
    ex = RelightExit(grid, _with_zero_row(rows.dc), _with_zero_row(surf.albedo * (SQRT_4PI / math.pi)))
    if surf.glossy:
        kg = glossy_bands * glossy_bands
        M = surf.valid.size
        # Made in place with its zero row (M + 1 rows): the rows are 3 Kg² floats a
        # texel, and a product and a padded copy of them tripled the level's peak.
        R = np.zeros((M + 1, 3, kg, kg), np.float32)
        R[:M, :, 0, :] = rows.dc[:, :, :kg]
        if rows.glossy is not None:
            R[:M, :, 1:, :] = rows.glossy[:, :, :kg - 1, :kg]
        A = lobe_factors(surf.exponent, glossy_bands).astype(np.float32)               # (M, Kg)
        R[:M] *= A[:, None, :, None]
        ex.glossy_grid = grid
        ex.g_rows = R
        ex.g_scale = _with_zero_row(surf.spec)
        ex.normal = _with_zero_row(surf.normal)
    return ex


@dataclasses.dataclass
class HitForms:
    """The light's coefficients in the radiance leaving hits, factored, one row
    per hit that leaves any (``index`` (n,): which of the hits passed in):
    ``d_scale`` (n, 3) * ``d_rows`` (n, Cd, K) + ``g_scale`` (n, 3) * ``g_w``
    (n, Cg, Kg) (zeros where the hit has no lobe); Cd, Cg = 1 shares the row
    between the colours (level 1), 3 gives one per colour."""

    index: np.ndarray
    d_scale: np.ndarray
    d_rows: np.ndarray
    g_scale: np.ndarray
    g_w: np.ndarray

    def full(self) -> np.ndarray:
        """(n, 3, K) float32, the coefficients themselves."""
        out = self.d_scale[:, :, None] * self.d_rows
        kg = self.g_w.shape[2]
        out[:, :, :kg] += self.g_scale[:, :, None] * self.g_w
        return out


class RelightShader:
    """The exit forms of every source set (set index -> RelightExit; sets
    without are black), evaluated at hits like bounce.ExitShader."""

    def __init__(self, sc, exits: dict, bands: int, glossy_bands: int, glossy_tri: np.ndarray):
        self.sc, self.exits = sc, exits
        self.K, self.bands, self.glossy_bands = bands * bands, bands, glossy_bands
        self.uv_frame = uv_frames(sc)
        self.glossy_tri = glossy_tri
        self.cd = max((ex.d_rows.shape[1] for ex in exits.values()), default=1)
        self.cg = max((ex.g_rows.shape[1] for ex in exits.values() if ex.g_rows is not None), default=1)
        # The compiled loop when numba is there (hit_jit.relight_project), else forms()' numpy.
        self.compiled = hit_kernel.available()
        self.consts = hit_kernel.recurrence_constants(max(glossy_bands, 1))

    def path(self) -> str:
        """How hits are evaluated: "compiled" or "numpy" (the manifest says which)."""
        return "compiled" if self.compiled and hit_kernel.usable("relight", self.glossy_bands, self.bands) else "numpy"

    def project(self, ch: ChunkHits, glossy_out: bool, shared_colour: bool = False):
        """The chunk's hits projected as they are shaded (hit_jit.relight_project;
        the compiled path only): (dc (n, 3, K), local glossy (n, C, Kg, Kg) in
        the texels' frames, C = 1 (the colours' mean) with ``shared_colour``,
        else 3, or None unless ``glossy_out``), float32."""
        kg, n = self.glossy_bands ** 2, ch.n
        dc = np.zeros((n, 3, self.K), np.float32)
        loc = np.zeros((n if glossy_out else 0, 1 if shared_colour else 3, kg, kg), np.float32)
        w0 = np.ascontiguousarray(ch.table[:, 0], dtype=np.float32)
        table = np.ascontiguousarray(ch.table[:, :kg], dtype=np.float32)
        sets = self.sc.set_id[ch.prim]
        for s, ex in self.exits.items():
            sel = np.flatnonzero(sets == s)
            if sel.size == 0:
                continue
            has = ex.g_rows is not None
            tex, gtex, g = hit_kernel.hit_texels(sel, ch.prim, ch.u, ch.v, self.uv_frame, self.glossy_tri,
                                                 ex.diffuse_grid, ex.glossy_grid if has else None)
            shared_exit = ex.d_rows.shape[1] == 1 and (not has or ex.g_rows.shape[1] == 1)
            loop = hit_kernel.relight_loop(self.bands, self.glossy_bands, shared_exit)
            loop(tex, gtex, ex.diffuse_grid.row_of, g.row_of, sel, ch.hit, ch.D, ex.d_rows, ex.d_scale,
                 ex.g_rows if has else _NO_FORMS, ex.g_scale if has else _NO_SCALE,
                 ex.normal if has else _NO_SCALE, self.glossy_bands, *self.consts, ch.S, w0, table, dc, loc)
        return dc, (loc if glossy_out else None)

    def forms(self, tri: np.ndarray, u: np.ndarray, v: np.ndarray, view: np.ndarray) -> HitForms:
        """The exit forms at hits on triangles ``tri`` at Embree's (u, v),
        ``view`` (n, 3) unit vectors from the hit towards the ray origin; rows
        in texel order (HitForms.index says whose)."""
        kg = self.glossy_bands ** 2
        parts = []
        for ex, sel, near, x, y in hits_by_set(self.sc, self.uv_frame, self.exits, tri, u, v):
            d_rows = np.take(ex.d_rows, near, axis=0)
            if d_rows.shape[1] < self.cd:
                d_rows = np.repeat(d_rows, self.cd, axis=1)
            part = HitForms(sel, np.take(ex.d_scale, near, axis=0), d_rows, np.zeros((sel.size, 3), np.float32),
                            np.zeros((sel.size, self.cg, kg), np.float32))
            g = np.flatnonzero(self.glossy_tri[tri[sel]]) if ex.g_rows is not None else np.zeros(0, np.int64)
            if g.size:
                gnear = ex.glossy_grid.rows_at(x[g], y[g])
                r = reflect_rows(np.ascontiguousarray(np.take(ex.normal, gnear, axis=0).T),
                                 np.ascontiguousarray(view[sel[g]].T))
                yb = basis_unchecked((r[0], r[1], r[2]), self.glossy_bands, np.float32)        # (m, Kg)
                G = np.take(ex.g_rows, gnear, axis=0)                                         # (m, Cg, Kg, Kg)
                if G.shape[1] < self.cg:
                    G = np.repeat(G, self.cg, axis=1)
                part.g_w[g] = np.einsum("mcoi,mo->mci", G, yb)
                part.g_scale[g] = np.take(ex.g_scale, gnear, axis=0)
            parts.append(part)
        if len(parts) == 1:
            return parts[0]
        if not parts:
            return HitForms(np.zeros(0, np.int64), np.zeros((0, 3), np.float32),
                            np.zeros((0, self.cd, self.K), np.float32), np.zeros((0, 3), np.float32),
                            np.zeros((0, self.cg, kg), np.float32))
        return HitForms(*(np.concatenate([getattr(p, f.name) for p in parts])
                          for f in dataclasses.fields(HitForms)))


def _glossy_channels(world: np.ndarray, n: int, kg: int, colours: int = 3) -> np.ndarray:
    """The glossy rows' channels (colours (Kg - 1) Kg, n), colour, then out
    coefficient o >= 1, then light coefficient, from world SH (n colours Kg,
    Kg) ordered texel, colour, light coefficient i (rows) by out coefficient o."""
    w = world.reshape(n, colours, kg, kg)                                          # (n, c, i, o)
    return np.ascontiguousarray(w[:, :, :, 1:].transpose(0, 1, 3, 2)).reshape(n, -1).T


@dataclasses.dataclass(eq=False)
class RelightProjection:
    """A relightable level's projection of one chunk (bounce.trace_bounce_level):
    (DC rows (3K, n), glossy rows (C (Kg - 1) Kg, n) or None unless
    ``glossy_out``) for the chunk's texel columns; channel order colour, then
    out coefficient, then light coefficient. C = 3, or 1 with
    ``shared_colour``: the colours' mean (exr_io.expand_shared_glossy tints
    it back), projected and turned to the world once instead of three times."""

    shader: RelightShader
    K: int
    kg: int
    glossy_out: bool
    shared_colour: bool = False

    def __call__(self, ch: ChunkHits):
        K, kg = self.K, self.kg
        n, S = ch.n, ch.S
        nc = 1 if self.shared_colour else 3
        if self.shader.path() == "compiled":
            dc, loc = self.shader.project(ch, self.glossy_out, self.shared_colour)
            gl = None
            if loc is not None:
                gl = _glossy_channels(ch.local_to_world(loc.reshape(n * nc * kg, kg), kg, nc * kg), n, kg, nc)
            return dc.reshape(n, 3 * K).T, gl
        f = self.shader.forms(ch.prim, ch.u, ch.v, -ch.D[ch.hit])
        cd, cg = f.d_rows.shape[1], f.g_w.shape[1]
        # Per ray (zeros where it missed): the DC weight folded into the colour scales.
        ad = np.zeros((n * S, 3), np.float32)
        ag = np.zeros((n * S, 3), np.float32)
        at = ch.hit[f.index]                  # the rays the forms' rows belong to
        ad[at] = f.d_scale
        ag[at] = f.g_scale
        w0 = np.ascontiguousarray(ch.table[:, 0])
        ad = ad.reshape(n, S, 3)
        ag = ag.reshape(n, S, 3)
        Y = gl = None
        if cd == 1 and cg == 1:
            # Level 1: one row per hit for all colours, so the DC row is a
            # (3, S) @ (S, K) product per texel; no (rays, 3, K) array.
            rows = np.zeros((n * S, K), np.float32)
            wg = np.zeros((n * S, kg), np.float32)
            rows[at] = f.d_rows[:, 0]
            wg[at] = f.g_w[:, 0]
            rows = rows.reshape(n, S, K)
            wg = wg.reshape(n, S, kg)
            # Contiguous operands: numpy's stacked matmul takes BLAS only for those.
            out = np.matmul(np.ascontiguousarray((ad * w0[:, None]).transpose(0, 2, 1)), rows)   # (n, 3, K)
            out[:, :, :kg] += np.matmul(np.ascontiguousarray((ag * w0[:, None]).transpose(0, 2, 1)), wg)
            dc = out.reshape(n, 3 * K).T
            if self.glossy_out:
                Y = ad[:, :, :, None] * rows[:, :, None, :kg] + ag[:, :, :, None] * wg[:, :, None, :]
        else:
            X = np.zeros((n * S, 3, K), np.float32)
            X[at] = f.full()
            X = X.reshape(n, S, 3 * K)
            # The DC row: the estimator's DC weights (rotation leaves the DC alone).
            dc = (w0 @ X).T
            if self.glossy_out:
                Y = X.reshape(n, S, 3, K)[:, :, :, :kg]
        if Y is not None:
            if self.shared_colour:
                Y = Y.mean(axis=2, keepdims=True)
            # Rows (texel, colour, light coefficient i < Kg) projected on Kg out coefficients.
            Yt = np.ascontiguousarray(Y.transpose(0, 2, 3, 1)).reshape(n * nc * kg, S)
            gl = _glossy_channels(ch.to_world(Yt, kg, nc * kg), n, kg, nc)
        return dc, gl


def bake_relight_set(rs: RayScene, gb: GBuffer, pts: Points, skip: np.ndarray, shader: RelightShader,
                     st: TransferSettings, level: int, *, glossy_out: bool, shared_colour: bool = False,
                     spill_folder: str | None = None, progress=None, cancel=None, remote=None):
    """One set's relightable level. Returns (rows (3K + G, N) float32, column
    i for covered texel ``gb.texel[i]``: the DC rows' 3K channels, then the G
    = C (Kg - 1) Kg glossy rows' (G = 0 when not ``glossy_out``); coverage mask
    (H, W); stats). Only the covered texels are held (texels.dilate.DilatedRows
    makes the dilated planes a band at a time as they are written). Channel
    order colour, then out coefficient, then light coefficient; C = 1 with
    ``shared_colour`` (RelightProjection), else 3.

    ``spill_folder``: the rows are this level's whole texture, read only to be
    written: they are kept in a temporary file there
    (estimators.column_spill.ColumnSpill, returned in place of the array; the DC
    responses c K stay in memory), not in memory (#35: 1.0 GB at a 4096²
    atlas). The caller closes it."""
    K, kg = shader.K, shader.glossy_bands ** 2
    nc = 1 if shared_colour else 3
    C = 3 * K + (nc * (kg - 1) * kg if glossy_out else 0)
    column = np.zeros(gb.height * gb.width, np.int64)       # texel -> its column
    column[gb.texel] = np.arange(gb.n, dtype=np.int64)
    projection = RelightProjection(shader, K, kg, glossy_out, shared_colour)
    if spill_folder is not None:
        table = ColumnSpill(C, gb.texel, gb.width, gb.height, spill_folder, exact_channels=range(0, 3 * K, K))

        def store_spill(cols, result):
            at = column[cols]
            table.store(at, result[0])
            if glossy_out:
                table.store(at, result[1], first=3 * K)

        try:
            stats = trace_bounce_level(rs, gb, pts, skip, st, level, projection, store_spill,
                                       progress=progress, cancel=cancel, remote=remote)
        except BaseException:
            table.close()
            raise
        stats["hit_shading"] = shader.path()
        return table, gb.mask(), stats
    planes = np.zeros((C, gb.n), np.float32)
    dc = planes[:3 * K]
    gl = planes[3 * K:] if glossy_out else None

    def store(cols, result):
        at = column[cols]
        hit_kernel.store_columns(dc, at, result[0])
        if gl is not None:
            hit_kernel.store_columns(gl, at, result[1])

    stats = trace_bounce_level(rs, gb, pts, skip, st, level, projection, store,
                               progress=progress, cancel=cancel, remote=remote)
    stats["hit_shading"] = shader.path()
    return planes, gb.mask(), stats


def uniform_energy(dc: np.ndarray) -> float:
    """bounce.level_energy of the incident light that DC rows ``dc`` (M, C, K)
    (C = 3 colours, or 1 for the transfer T itself) give under a uniform white
    light of unit DC coefficient, per colour: sum of dc[:, :, 0] over texels
    and colours (x 3 for C = 1), over sqrt(4 pi) for the transfer. Relightable
    bakes judge the early stop by it, so the stored levels do not depend on
    the light they will be shown under."""
    # Only the DC column in float64: the whole (M, C, K) converted was ~0.1 s on the room.
    d = np.asarray(np.asarray(dc)[:, :, 0], np.float64)
    if d.shape[1] == 1:                       # the transfer: M(L)T's DC is L.T / sqrt(4 pi)
        return 3.0 * float(d[:, 0].sum()) / SQRT_4PI
    return float(d.sum())
