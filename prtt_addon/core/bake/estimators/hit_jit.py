"""numba-compiled loop of :mod:`.hit_kernel` (imported only when numba is
there and a bounce bake shades its first hits).

Why a prefetch: the profile of the compiled loop on the room (one thread,
data hot from the same chunk; docs/benchmarks.md) put most of each hit's time
in waiting for the hit's 312-byte glossy row, read at random from a table of
tens of MB, not in the basis and the 75 multiply-adds. The rows of
all the set's hits are found first, and each hit asks the memory system for
the row it will read PREFETCH_DISTANCE hits later, so the waits overlap the
arithmetic of the hits between.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

PREFETCH_DISTANCE = 8          # hits ahead: ~ memory latency / compute per hit
#: LLVM may reassociate and fuse the sums (the 25-term dots no longer wait on
#: one add after another) and use reciprocals; no NaN/Inf assumptions.
FASTMATH = {"reassoc", "contract", "nsz", "arcp"}


@intrinsic
def prefetch(typingctx, arr, idx):
    """Hint the cache to load arr[idx] (1-D contiguous array) for reading: LLVM's llvm.prefetch."""
    if not isinstance(arr, types.Array) or arr.ndim != 1 or not isinstance(idx, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        ptr = builder.gep(ary.data, [args[1]])
        i8p, i32 = ir.IntType(8).as_pointer(), ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0i8")
        builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])    # read, keep, data
        return context.get_dummy_value()

    return types.void(arr, idx), codegen


def _vector(builder, arr_struct, offset, n):
    """Pointer to the <n x float> at element ``offset`` of a float32 array's data."""
    vt = ir.VectorType(ir.FloatType(), n)
    return builder.bitcast(builder.gep(arr_struct.data, [offset]), vt.as_pointer())


def _splat(builder, value, n):
    vt = ir.VectorType(ir.FloatType(), n)
    v = builder.insert_element(ir.Constant(vt, None), value, ir.IntType(32)(0))
    return builder.shuffle_vector(v, ir.Constant(vt, None), ir.Constant(ir.VectorType(ir.IntType(32), n), [0] * n))


# The relightable loop's short sums as LLVM vector operations. Written as
# loops over 9 or 25 floats, numba's code stayed scalar (LLVM vectorises
# loops for long trip counts, and cannot prove that the accumulator and the
# table it reads do not overlap, so it neither reorders nor packs them). The
# caller guarantees the ranges are inside the arrays (1-D, contiguous
# float32; unaligned loads and stores). Results equal the scalar loop's to
# float32 rounding (each element is still summed in hit order; the products
# may fuse).


@intrinsic
def axpy(typingctx, dst, doff, src, soff, a, n):
    """dst[doff:doff + n] += a * src[soff:soff + n], ``n`` a literal int."""
    if not isinstance(n, types.IntegerLiteral):
        return None
    N = n.literal_value

    def codegen(context, builder, signature, args):
        d = context.make_array(signature.args[0])(context, builder, args[0])
        s = context.make_array(signature.args[2])(context, builder, args[2])
        dp = _vector(builder, d, args[1], N)
        prod = builder.fmul(_splat(builder, args[4], N), builder.load(_vector(builder, s, args[3], N), align=4),
                            flags=("contract",))
        builder.store(builder.fadd(builder.load(dp, align=4), prod, flags=("contract",)), dp, align=4)
        return context.get_dummy_value()

    return types.void(dst, doff, src, soff, a, n), codegen


@intrinsic
def rows_combine(typingctx, dst, src, soff, y, m, n):
    """dst[0:n] = sum over o < m of y[o] * src[soff + o n: soff + o n + n]
    (``m``, ``n`` literal ints), summed in registers."""
    if not (isinstance(m, types.IntegerLiteral) and isinstance(n, types.IntegerLiteral)):
        return None
    M, N = m.literal_value, n.literal_value

    def codegen(context, builder, signature, args):
        d = context.make_array(signature.args[0])(context, builder, args[0])
        s = context.make_array(signature.args[1])(context, builder, args[1])
        ya = context.make_array(signature.args[3])(context, builder, args[3])
        acc = ir.Constant(ir.VectorType(ir.FloatType(), N), [0.0] * N)
        for o in range(M):
            row = builder.load(_vector(builder, s, builder.add(args[2], ir.IntType(64)(o * N)), N), align=4)
            yo = builder.load(builder.gep(ya.data, [ir.IntType(64)(o)]))
            acc = builder.fadd(acc, builder.fmul(_splat(builder, yo, N), row, flags=("contract",)),
                               flags=("contract",))
        builder.store(acc, _vector(builder, d, ir.IntType(64)(0), N), align=4)
        return context.get_dummy_value()

    return types.void(dst, src, soff, y, m, n), codegen


@intrinsic
def outer_acc(typingctx, dst, doff, x, tile, toff, n):
    """dst[doff + i n + o] += x[i] * tile[toff + i n + o] for i, o < n (``n``
    a literal int): an outer product with a row tiled n times, one op."""
    if not isinstance(n, types.IntegerLiteral):
        return None
    N = n.literal_value

    def codegen(context, builder, signature, args):
        d = context.make_array(signature.args[0])(context, builder, args[0])
        xa = context.make_array(signature.args[2])(context, builder, args[2])
        ta = context.make_array(signature.args[3])(context, builder, args[3])
        xv = builder.load(_vector(builder, xa, ir.IntType(64)(0), N), align=4)
        rep = builder.shuffle_vector(xv, ir.Constant(xv.type, None), ir.Constant(
            ir.VectorType(ir.IntType(32), N * N), [i for i in range(N) for _ in range(N)]))
        dp = _vector(builder, d, args[1], N * N)
        prod = builder.fmul(rep, builder.load(_vector(builder, ta, args[4], N * N), align=4), flags=("contract",))
        builder.store(builder.fadd(builder.load(dp, align=4), prod, flags=("contract",)), dp, align=4)
        return context.get_dummy_value()

    return types.void(dst, doff, x, tile, toff, n), codegen


@numba.njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _cell(f, n):
    """The texel column (row) of texture coordinate times size ``f``, as numpy's
    clip(int64(f), 0, n - 1) for finite f; NaN gives 0 and +-inf or huge
    values the nearest edge (numpy's cast is undefined there; numba's would
    index out of bounds)."""
    if not f >= 0.0:
        return 0
    if f >= n:
        return n - 1
    return min(np.int64(f), n - 1)


@numba.njit(nogil=True, cache=True, error_model="numpy")
def texel_indices(sel, prim, u, v, frames, W, H, has_glossy, glossy_tri, Wg, Hg):
    """(tex, gtex) (n,) int64 of the hits ``sel``: the flat index of the
    nearest texel on the diffuse grid (W x H), and on the glossy grid
    (Wg x Hg; -1: the hit reads no glossy row). Strict float32, the numpy
    path's arithmetic, and compiled on its own: inlined into a fastmath loop,
    LLVM fused its multiply-adds and moved hits on a texel's edge to the
    neighbouring texel (1 in ~10^4 hits on the room)."""
    f32 = np.float32
    fW, fH, fWg, fHg = f32(W), f32(H), f32(Wg), f32(Hg)
    n = sel.size
    tex = np.empty(n, np.int64)
    gtex = np.full(n, -1, np.int64)
    for j in range(n):
        i = sel[j]
        t = prim[i]
        x = frames[t, 0] + u[i] * frames[t, 2] + v[i] * frames[t, 4]
        yy = frames[t, 1] + u[i] * frames[t, 3] + v[i] * frames[t, 5]
        tex[j] = _cell(yy * fH, H) * W + _cell(x * fW, W)
        if has_glossy and glossy_tri[t]:
            gtex[j] = _cell(yy * fHg, Hg) * Wg + _cell(x * fWg, Wg)
    return tex, gtex


@numba.njit(nogil=True, cache=True, error_model="numpy", fastmath=FASTMATH, inline="always")
def _reflected_basis(nx, ny, nz, wx, wy, wz, bands, sect, ca, cb, y):
    """y[k] (K = bands², float32) = the real SH at r, the unit reflection of the
    view w about the (dilated, not unit) normal n: r = 2 (n.w) n / |n|² - w
    (bounce.reflect_rows), by sh.basis.basis_unchecked's recurrence."""
    f32 = np.float32
    sqrt2 = f32(math.sqrt(2.0))
    d = f32(2.0) * (nx * wx + ny * wy + nz * wz) / max(nx * nx + ny * ny + nz * nz, f32(1e-30))
    rx, ry, rz = d * nx - wx, d * ny - wy, d * nz - wz
    inv = f32(1.0) / math.sqrt(max(rx * rx + ry * ry + rz * rz, f32(1e-30)))
    rx, ry, rz = rx * inv, ry * inv, rz * inv
    cm, sm = f32(1.0), f32(0.0)
    for m in range(bands):
        if m > 0:
            cm, sm = rx * cm - ry * sm, rx * sm + ry * cm
        p_prev = sect[m]
        p_cur = f32(0.0)
        for l in range(m, bands):
            if l == m:
                p = p_prev
            elif l == m + 1:
                p_cur = ca[m, l] * rz * p_prev
                p = p_cur
            else:
                p = ca[m, l] * (rz * p_cur - cb[m, l] * p_prev)
                p_prev, p_cur = p_cur, p
            if m == 0:
                y[l * l + l] = p
            else:
                y[l * l + l + m] = sqrt2 * p * cm
                y[l * l + l - m] = sqrt2 * p * sm


@numba.njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _prefetch_row(flat, row, stride):
    """Ask for the cache lines of row ``row`` of a (M, stride) table seen flat."""
    base = row * stride
    for off in range(0, stride, 16):
        prefetch(flat, base + off)
    prefetch(flat, base + stride - 1)


@numba.njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _first_rows(tex, gtex, row_of, grow_of):
    """(rows, grows) (n,) int64 for the hits' texels ``tex``/``gtex`` (-1: no
    glossy row), filled for the first PREFETCH_DISTANCE hits; the loops'
    :func:`_next_rows` fills the rest PREFETCH_DISTANCE hits ahead."""
    n = tex.size
    rows = np.empty(n, np.int64)
    grows = np.empty(n, np.int64)
    for j in range(min(PREFETCH_DISTANCE, n)):
        rows[j] = row_of[tex[j]]
        grows[j] = grow_of[gtex[j]] if gtex[j] >= 0 else -1
    return rows, grows


@numba.njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _next_rows(j, tex, gtex, row_of, grow_of, rows, grows, dflat, dstride, gflat, gstride):
    """The load pipeline at hit j: ask for the row maps of hit j + 2d, read
    the rows of hit j + d and ask for their exit rows (``dflat`` rows of
    ``dstride`` floats; ``gflat`` of ``gstride``), d = PREFETCH_DISTANCE."""
    n, pd = tex.size, PREFETCH_DISTANCE
    a2 = j + 2 * pd
    if a2 < n:
        prefetch(row_of, tex[a2])
        if gtex[a2] >= 0:
            prefetch(grow_of, gtex[a2])
    a = j + pd
    if a < n:
        ra = row_of[tex[a]]
        ga = grow_of[gtex[a]] if gtex[a] >= 0 else -1
        rows[a] = ra
        grows[a] = ga
        _prefetch_row(dflat, ra, dstride)
        if ga >= 0:
            _prefetch_row(gflat, ga, gstride)


@numba.njit(nogil=True, cache=True, error_model="numpy", fastmath=FASTMATH, inline="always")
def _shade(tex, gtex, row_of, grow_of, sel, ray_of, D, diffuse, glossy, bands, sect, ca, cb, out):
    """For the hits ``sel`` (indices into ray_of) of one set, on the texels
    :func:`texel_indices` found, whose rows row_of / grow_of give: out[ray, c] = max(0, D_c + [glossy] sum_k
    G_c,k y_k(r)), ray = ray_of[i] the hit's row in the chunk's rays, ``D``
    (rays, 3) their directions (view = -D), ``diffuse`` (M + 1, 3) and
    ``glossy`` (M' + 1, 3 + 3K) float32 C-contiguous (a placeholder when no
    gtex[j] >= 0). Arithmetic in float32, as bounce.ExitShader's numpy.

    A pipeline of loads: at hit j, the row maps of hit j + 2d are asked for
    (prefetch), the rows of hit j + d are read from them and their exit rows
    asked for, and hit j is shaded from rows that should be in cache by now
    (d = PREFETCH_DISTANCE).

    Inlined into :data:`BY_BANDS`' functions, each with ``bands`` a constant:
    LLVM then unrolls the basis recurrence and the sums (docs/benchmarks.md
    has the gain)."""
    K = bands * bands
    C = glossy.shape[1]
    f32 = np.float32
    gflat = glossy.reshape(-1)
    dflat = diffuse.reshape(-1)
    rows, grows = _first_rows(tex, gtex, row_of, grow_of)
    y = np.empty(K, np.float32)
    for j in range(sel.size):
        _next_rows(j, tex, gtex, row_of, grow_of, rows, grows, dflat, 3, gflat, C)
        i = sel[j]
        ray = ray_of[i]
        row = rows[j]
        r0 = diffuse[row, 0]
        r1 = diffuse[row, 1]
        r2 = diffuse[row, 2]
        grow = grows[j]
        if grow >= 0:
            _reflected_basis(glossy[grow, 0], glossy[grow, 1], glossy[grow, 2], -D[ray, 0], -D[ray, 1], -D[ray, 2],
                             bands, sect, ca, cb, y)
            s0, s1, s2 = f32(0.0), f32(0.0), f32(0.0)
            for k in range(K):
                yk = y[k]
                s0 += glossy[grow, 3 + k] * yk
                s1 += glossy[grow, 3 + K + k] * yk
                s2 += glossy[grow, 3 + 2 * K + k] * yk
            r0 += s0
            r1 += s1
            r2 += s2
        out[ray, 0] = max(r0, f32(0.0))
        out[ray, 1] = max(r1, f32(0.0))
        out[ray, 2] = max(r2, f32(0.0))


_KW = dict(nogil=True, cache=True, error_model="numpy", fastmath=FASTMATH)

# One function per band count, written out rather than generated: numba's
# cache keeps only functions defined in a source file, and a generated one
# would compile again (1-2 s) in every bake's worker process.


@numba.njit(**_KW)
def shade_any(tex, gtex, row_of, grow_of, sel, ray_of, D, diffuse, glossy, bands, sect, ca, cb, out):
    """:func:`_shade` for any band count."""
    _shade(tex, gtex, row_of, grow_of, sel, ray_of, D, diffuse, glossy, bands, sect, ca, cb, out)


@numba.njit(**_KW)
def shade_b3(tex, gtex, row_of, grow_of, sel, ray_of, D, diffuse, glossy, bands, sect, ca, cb, out):
    """:func:`_shade` for 3 bands (``bands`` must be 3)."""
    _shade(tex, gtex, row_of, grow_of, sel, ray_of, D, diffuse, glossy, 3, sect, ca, cb, out)


@numba.njit(**_KW)
def shade_b4(tex, gtex, row_of, grow_of, sel, ray_of, D, diffuse, glossy, bands, sect, ca, cb, out):
    """:func:`_shade` for 4 bands (``bands`` must be 4)."""
    _shade(tex, gtex, row_of, grow_of, sel, ray_of, D, diffuse, glossy, 4, sect, ca, cb, out)


@numba.njit(**_KW)
def shade_b5(tex, gtex, row_of, grow_of, sel, ray_of, D, diffuse, glossy, bands, sect, ca, cb, out):
    """:func:`_shade` for 5 bands, the default (``bands`` must be 5)."""
    _shade(tex, gtex, row_of, grow_of, sel, ray_of, D, diffuse, glossy, 5, sect, ca, cb, out)


@numba.njit(**_KW)
def shade_b6(tex, gtex, row_of, grow_of, sel, ray_of, D, diffuse, glossy, bands, sect, ca, cb, out):
    """:func:`_shade` for 6 bands (``bands`` must be 6)."""
    _shade(tex, gtex, row_of, grow_of, sel, ray_of, D, diffuse, glossy, 6, sect, ca, cb, out)


#: band count -> the loop compiled for it (others: shade_any).
BY_BANDS = {3: shade_b3, 4: shade_b4, 5: shade_b5, 6: shade_b6}


def for_bands(bands: int):
    """The compiled loop for ``bands`` bands."""
    return BY_BANDS.get(bands, shade_any)


@numba.njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _prefetch_scales(row, grow, dsflat, gsflat, nflat):
    """Ask for a hit's colour scales (d_scale row, and g_scale and normal rows
    when grow >= 0: (M + 1, 3) tables seen flat). They are small but read at
    random from tables of MBs: unprefetched, these three loads were half of
    the relightable loop's time per hit in the profile (docs/benchmarks.md)."""
    prefetch(dsflat, row * 3)
    if grow >= 0:
        prefetch(gsflat, grow * 3)
        prefetch(nflat, grow * 3)


@numba.njit(nogil=True, cache=True, error_model="numpy", fastmath=FASTMATH)
def relight_project(tex, gtex, row_of, grow_of, sel, ray_of, D, d_rows, d_scale, g_rows, g_scale, normal, gbands,
                    sect, ca, cb, S, w0, table, dc, loc):
    """Relightable bounces (relight.RelightProjection): the hits ``sel`` of
    one set projected as they are shaded, with no per-ray array. Hit i (ray
    = ray_of[i] = t S + s: texel t of the chunk, ray s of its pattern) leaves
    X[c, k] = d_scale[row, c] d_rows[row, c or 0, k] + (k < Kg) g_scale[grow,
    c] sum_o y_o(r) g_rows[grow, c or 0, o, k] (r the view reflected about
    normal[grow]; the glossy term on hits with a lobe); then
    dc[t, c, k] += w0[s] X[c, k] (the DC row), and when loc has texels,
    loc[t, c, i, o] += X[c, i] table[s, o] for i, o < Kg (the estimator's
    local projection; the caller turns it to the world; loc with one colour,
    (n, 1, Kg, Kg), takes the colours' mean: shared glossy rows). What estimators/relightable.py's
    numpy path computes from the per-ray forms; rows of the texels
    :func:`texel_indices` found, prefetched as in :func:`_shade`."""
    cds, K = d_rows.shape[1], d_rows.shape[2]
    cgs = g_rows.shape[1]
    kg = table.shape[1]
    glossy_out = loc.shape[0] > 0
    f32 = np.float32
    dflat = d_rows.reshape(-1)
    gflat = g_rows.reshape(-1)
    dsflat = d_scale.reshape(-1)
    gsflat = g_scale.reshape(-1)
    nflat = normal.reshape(-1)
    prow, pgrow = _first_rows(tex, gtex, row_of, grow_of)
    for j in range(min(PREFETCH_DISTANCE, sel.size)):
        _prefetch_scales(prow[j], pgrow[j], dsflat, gsflat, nflat)
    y = np.empty(kg, np.float32)
    wg = np.empty((cgs, kg), np.float32)
    x = np.empty((3, K), np.float32)
    for j in range(sel.size):
        _next_rows(j, tex, gtex, row_of, grow_of, prow, pgrow, dflat, cds * K, gflat, cgs * kg * kg)
        if j + PREFETCH_DISTANCE < sel.size:
            _prefetch_scales(prow[j + PREFETCH_DISTANCE], pgrow[j + PREFETCH_DISTANCE], dsflat, gsflat, nflat)
        ray = ray_of[sel[j]]
        t = ray // S
        s = ray - t * S
        row = prow[j]
        for c in range(3):
            cs = c if cds == 3 else 0
            a = d_scale[row, c]
            for k in range(K):
                x[c, k] = a * d_rows[row, cs, k]
        grow = pgrow[j]
        if grow >= 0:
            _reflected_basis(normal[grow, 0], normal[grow, 1], normal[grow, 2], -D[ray, 0], -D[ray, 1], -D[ray, 2],
                             gbands, sect, ca, cb, y)
            for cs in range(cgs):
                for ii in range(kg):
                    acc = f32(0.0)
                    for o in range(kg):
                        acc += y[o] * g_rows[grow, cs, o, ii]
                    wg[cs, ii] = acc
            for c in range(3):
                cs = c if cgs == 3 else 0
                a = g_scale[grow, c]
                for ii in range(kg):
                    x[c, ii] += a * wg[cs, ii]
        w = w0[s]
        for c in range(3):
            for k in range(K):
                dc[t, c, k] += w * x[c, k]
        if glossy_out and loc.shape[1] == 1:
            for ii in range(kg):
                xi = (x[0, ii] + x[1, ii] + x[2, ii]) * f32(1.0 / 3.0)
                for o in range(kg):
                    loc[t, 0, ii, o] += xi * table[s, o]
        elif glossy_out:
            for c in range(3):
                for ii in range(kg):
                    xi = x[c, ii]
                    for o in range(kg):
                        loc[t, c, ii, o] += xi * table[s, o]


@numba.njit(nogil=True, cache=True, error_model="numpy", fastmath=FASTMATH, inline="always")
def _relight_level1(tex, gtex, row_of, grow_of, sel, ray_of, D, d_rows, d_scale, g_rows, g_scale, normal, sect, ca,
                    cb, S, w0, table, dc, loc, K, gbands, kg):
    """:func:`relight_project` for exit forms shared between the colours
    (d_rows (M, 1, K), g_rows (M', 1, Kg, Kg): level 1, the transfer), with
    ``K``, ``gbands`` and ``kg`` = gbands² constants (the wrappers below;
    numba types a product of constants as a variable): the sums are the
    vector operations above and the basis recurrence unrolls. Same values
    as relight_project to float32 rounding (docs/benchmarks.md has the
    time per hit)."""
    kk = kg * kg
    nloc = loc.shape[1]
    glossy_out = loc.shape[0] > 0
    f32 = np.float32
    third = f32(1.0 / 3.0)
    dflat = d_rows.reshape(-1)
    gflat = g_rows.reshape(-1)
    dsflat = d_scale.reshape(-1)
    gsflat = g_scale.reshape(-1)
    nflat = normal.reshape(-1)
    dcf = dc.reshape(-1)
    locf = loc.reshape(-1)
    # tile[s, i Kg + o] = table[s, o]: the estimator row beside each light coefficient i.
    tile = np.empty(table.shape[0] * kk, np.float32)
    for s in range(table.shape[0]):
        for i in range(kg):
            for o in range(kg):
                tile[s * kk + i * kg + o] = table[s, o]
    prow, pgrow = _first_rows(tex, gtex, row_of, grow_of)
    for j in range(min(PREFETCH_DISTANCE, sel.size)):
        _prefetch_scales(prow[j], pgrow[j], dsflat, gsflat, nflat)
    y = np.empty(kg, np.float32)
    wg = np.zeros(kg, np.float32)
    xl = np.zeros(kg, np.float32)
    for j in range(sel.size):
        _next_rows(j, tex, gtex, row_of, grow_of, prow, pgrow, dflat, K, gflat, kk)
        if j + PREFETCH_DISTANCE < sel.size:
            _prefetch_scales(prow[j + PREFETCH_DISTANCE], pgrow[j + PREFETCH_DISTANCE], dsflat, gsflat, nflat)
        ray = ray_of[sel[j]]
        t = ray // S
        s = ray - t * S
        row = prow[j]
        grow = pgrow[j]
        w = w0[s]
        a0, a1, a2 = d_scale[row, 0], d_scale[row, 1], d_scale[row, 2]
        g0, g1, g2 = f32(0.0), f32(0.0), f32(0.0)
        base = t * 3 * K
        axpy(dcf, base, dflat, row * K, w * a0, K)
        axpy(dcf, base + K, dflat, row * K, w * a1, K)
        axpy(dcf, base + 2 * K, dflat, row * K, w * a2, K)
        if grow >= 0:
            _reflected_basis(normal[grow, 0], normal[grow, 1], normal[grow, 2], -D[ray, 0], -D[ray, 1], -D[ray, 2],
                             gbands, sect, ca, cb, y)
            rows_combine(wg, gflat, grow * kk, y, kg, kg)
            g0, g1, g2 = g_scale[grow, 0], g_scale[grow, 1], g_scale[grow, 2]
            axpy(dcf, base, wg, 0, w * g0, kg)
            axpy(dcf, base + K, wg, 0, w * g1, kg)
            axpy(dcf, base + 2 * K, wg, 0, w * g2, kg)
        if not glossy_out:
            continue
        if nloc == 1:
            _exit_rows(xl, dflat, row * K, wg, (a0 + a1 + a2) * third, (g0 + g1 + g2) * third, grow >= 0, kg)
            outer_acc(locf, t * kk, xl, tile, s * kk, kg)
        else:
            _exit_rows(xl, dflat, row * K, wg, a0, g0, grow >= 0, kg)
            outer_acc(locf, t * 3 * kk, xl, tile, s * kk, kg)
            _exit_rows(xl, dflat, row * K, wg, a1, g1, grow >= 0, kg)
            outer_acc(locf, t * 3 * kk + kk, xl, tile, s * kk, kg)
            _exit_rows(xl, dflat, row * K, wg, a2, g2, grow >= 0, kg)
            outer_acc(locf, t * 3 * kk + 2 * kk, xl, tile, s * kk, kg)


@numba.njit(nogil=True, cache=True, error_model="numpy", fastmath=FASTMATH, inline="always")
def _exit_rows(xl, dflat, doff, wg, a, g, glossy, kg):
    """xl[0:Kg] = a * dflat[doff:doff + Kg] (+ g * wg where the hit has a lobe)."""
    for i in range(kg):
        xl[i] = 0.0
    axpy(xl, 0, dflat, doff, a, kg)
    if glossy:
        axpy(xl, 0, wg, 0, g, kg)


# One function per band count of the transfer, the glossy part at 3 bands
# (relight.GLOSSY_BANDS), written out for numba's cache as BY_BANDS' are.


@numba.njit(**_KW)
def relight_level1_b3(tex, gtex, row_of, grow_of, sel, ray_of, D, d_rows, d_scale, g_rows, g_scale, normal, gbands,
                      sect, ca, cb, S, w0, table, dc, loc):
    """:func:`_relight_level1` for K = 9, 3 glossy bands."""
    _relight_level1(tex, gtex, row_of, grow_of, sel, ray_of, D, d_rows, d_scale, g_rows, g_scale, normal, sect, ca,
                    cb, S, w0, table, dc, loc, 9, 3, 9)


@numba.njit(**_KW)
def relight_level1_b4(tex, gtex, row_of, grow_of, sel, ray_of, D, d_rows, d_scale, g_rows, g_scale, normal, gbands,
                      sect, ca, cb, S, w0, table, dc, loc):
    """:func:`_relight_level1` for K = 16, 3 glossy bands."""
    _relight_level1(tex, gtex, row_of, grow_of, sel, ray_of, D, d_rows, d_scale, g_rows, g_scale, normal, sect, ca,
                    cb, S, w0, table, dc, loc, 16, 3, 9)


@numba.njit(**_KW)
def relight_level1_b5(tex, gtex, row_of, grow_of, sel, ray_of, D, d_rows, d_scale, g_rows, g_scale, normal, gbands,
                      sect, ca, cb, S, w0, table, dc, loc):
    """:func:`_relight_level1` for K = 25 (the default), 3 glossy bands."""
    _relight_level1(tex, gtex, row_of, grow_of, sel, ray_of, D, d_rows, d_scale, g_rows, g_scale, normal, sect, ca,
                    cb, S, w0, table, dc, loc, 25, 3, 9)


@numba.njit(**_KW)
def relight_level1_b6(tex, gtex, row_of, grow_of, sel, ray_of, D, d_rows, d_scale, g_rows, g_scale, normal, gbands,
                      sect, ca, cb, S, w0, table, dc, loc):
    """:func:`_relight_level1` for K = 36, 3 glossy bands."""
    _relight_level1(tex, gtex, row_of, grow_of, sel, ray_of, D, d_rows, d_scale, g_rows, g_scale, normal, sect, ca,
                    cb, S, w0, table, dc, loc, 36, 3, 9)


#: transfer band count -> level 1's vector loop (glossy bands 3); others: relight_project.
LEVEL1_BY_BANDS = {3: relight_level1_b3, 4: relight_level1_b4, 5: relight_level1_b5, 6: relight_level1_b6}


def relight_for(bands: int, glossy_bands: int, shared_exit: bool):
    """The relightable loop for a set's exit forms: level 1's vector loop
    when the forms are shared between colours and the bands have one, else
    :func:`relight_project`."""
    if shared_exit and glossy_bands == 3:
        return LEVEL1_BY_BANDS.get(bands, relight_project)
    return relight_project


@numba.njit(nogil=True, cache=True)
def put_columns(dst, cols, src):
    """dst[c, cols[j]] = src[c, j]: a chunk's rows (C, n) into the texture's
    columns (dst (C, H*W) float32, C-contiguous rows). One channel after the
    other, so each row's writes move forward through one plane."""
    for c in range(src.shape[0]):
        p = dst[c]
        s = src[c]
        for j in range(cols.size):
            p[cols[j]] = s[j]


@numba.njit(nogil=True, cache=True)
def put_texel_rows(dst, cols, src):
    """dst[c, cols[j]] = src[j, c]: a chunk's texel-major rows (n, C) into
    the texture's columns, without the transposed copy. Numpy's fancy
    assignment of the transposed view walked the source across its stride
    (several times slower on the room's 147-channel chunks)."""
    for c in range(src.shape[1]):
        p = dst[c]
        for j in range(cols.size):
            p[cols[j]] = src[j, c]
