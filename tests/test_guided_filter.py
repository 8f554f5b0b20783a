"""The guided texels' filter (core/bake/estimators/guided_filter.py): what it
keeps, what it never reads, that its bands do not change its answer, and
that it removes noise on a flat surface by the factor its weights predict."""
import numpy as np
import pytest

from prtt_addon.core.bake.estimators import guided_filter as gf


def _plane(H=40, W=48, step=0.01, holes=()):
    """A flat z = 0 surface gridded at ``step``: (texel, position, normal) of
    every texel but ``holes`` (flat indices)."""
    texel = np.setdiff1d(np.arange(H * W), np.asarray(holes, np.int64))
    y, x = texel // W, texel % W
    pos = np.stack([x * step, y * step, np.zeros(texel.size)], axis=1)
    nrm = np.tile([0.0, 0.0, 1.0], (texel.size, 1))
    return texel, pos, nrm


def test_a_constant_is_kept_and_other_rows_are_untouched():
    H, W = 40, 48
    texel, pos, nrm = _plane(H, W)
    rows = np.tile(np.linspace(0.1, 2.5, 25, dtype=np.float32), (texel.size, 1))
    rows[::7] += np.float32(0.5)                   # rows that are no target: kept bit for bit
    targets = np.arange(1, texel.size, 7)
    before = rows.copy()
    n = gf.smooth_guided(rows, texel, W, H, pos, nrm, targets, np.ones(texel.size, bool), 0.01)
    assert n == targets.size
    others = np.setdiff1d(np.arange(texel.size), targets)
    assert np.array_equal(rows[others], before[others])
    # A target's neighbours are the constant and the +0.5 rows: its value lies between them.
    assert np.all(rows[targets] >= before[targets] - 1e-6) and np.all(rows[targets] <= before[targets] + 0.5)


def test_invalid_texels_are_never_read():
    H, W = 30, 30
    texel, pos, nrm = _plane(H, W)
    rng = np.random.default_rng(0)
    rows = rng.random((texel.size, 9)).astype(np.float32)
    valid = rng.random(texel.size) > 0.2
    rows[~valid] = np.nan
    targets = np.flatnonzero(valid)
    gf.smooth_guided(rows, texel, W, H, pos, nrm, targets, valid, 0.01)
    assert np.isfinite(rows[targets]).all()


def test_other_surfaces_are_not_mixed():
    """Two halves of the atlas, side by side in UV, 1 m apart in the world (two
    islands) or folded at 90 degrees: no target takes the other half's value."""
    H, W = 20, 40
    texel, pos, nrm = _plane(H, W)
    right = (texel % W) >= W // 2
    rows = np.where(right, 1.0, 0.0).astype(np.float32)[:, None].repeat(4, axis=1)
    for far, fold in ((True, False), (False, True)):
        p, n, r = pos.copy(), nrm.copy(), rows.copy()
        if far:
            p[right, 1] += 1.0
        if fold:
            n[right] = [1.0, 0.0, 0.0]
        gf.smooth_guided(r, texel, W, H, p, n, np.arange(texel.size), np.ones(texel.size, bool), 0.01)
        # The left stays exactly 0; the right 1 to float32's rounding of the normalised weights.
        assert np.array_equal(r[~right], rows[~right]) and np.allclose(r[right], 1.0, rtol=0, atol=1e-6), (far, fold)


def test_bands_do_not_change_the_answer(monkeypatch):
    H, W = 70, 33
    texel, pos, nrm = _plane(H, W, holes=np.arange(0, 70 * 33, 11))
    rng = np.random.default_rng(1)
    rows = rng.normal(size=(texel.size, 25)).astype(np.float32)
    targets = np.flatnonzero(rng.random(texel.size) < 0.6)
    a = rows.copy()
    gf.smooth_guided(a, texel, W, H, pos, nrm, targets, np.ones(texel.size, bool), 0.01)
    for band, sub in ((gf.RADIUS, 7), (5, 100), (1000, 1 << 20)):
        monkeypatch.setattr(gf, "BAND_ROWS", band)
        monkeypatch.setattr(gf, "SUB", sub)
        b = rows.copy()
        gf.smooth_guided(b, texel, W, H, pos, nrm, targets, np.ones(texel.size, bool), 0.01)
        assert np.array_equal(a, b), band


def test_noise_falls_by_what_the_weights_predict():
    """White noise on a flat surface: the filtered standard deviation is the
    noise's times sqrt(sum w^2) / sum w of the 5 x 5 kernel (computed here
    from its definition), within 5 %."""
    H, W, step = 200, 200, 0.01
    texel, pos, nrm = _plane(H, W, step)
    rng = np.random.default_rng(2)
    rows = rng.normal(size=(texel.size, 1)).astype(np.float32)
    gf.smooth_guided(rows, texel, W, H, pos, nrm, np.arange(texel.size), np.ones(texel.size, bool), step)
    r = gf.RADIUS
    dy, dx = np.mgrid[-r:r + 1, -r:r + 1]
    d2 = dy ** 2 + dx ** 2
    w = np.exp(-d2 / (2 * gf.SIGMA_TEXELS ** 2)) * np.exp(-d2 / (2 * gf.SIGMA_STEPS ** 2))
    expect = np.sqrt((w ** 2).sum()) / w.sum()
    inner = ((texel // W) >= r) & ((texel // W) < H - r) & ((texel % W) >= r) & ((texel % W) < W - r)
    assert rows[inner].std() == pytest.approx(expect, rel=0.05)


def test_the_compiled_band_gives_the_numpy_paths_values():
    """With numba (guided_filter_jit) the same values as the numpy path to
    float32 rounding, on a curved, holed surface with invalid texels, island
    borders in the atlas (a second surface beside the first) and float32
    normals as the G-buffer has them."""
    from prtt_addon.core.base import jit
    if jit.load(gf._JIT) is None:
        pytest.skip("numba is not installed")
    H, W = 48, 64
    rng = np.random.default_rng(3)
    texel = np.sort(rng.choice(H * W, size=int(0.8 * H * W), replace=False))
    y, x = texel // W, texel % W
    second = x >= W // 2                       # another island: far away in the world, turned
    pos = np.stack([x * 0.01, y * 0.01, 0.05 * np.sin(x * 0.2)], axis=1)
    pos[second] += [3.0, 0.0, 1.0]
    nrm = np.stack([-0.01 * np.cos(x * 0.2), np.zeros(x.size), np.ones(x.size)], axis=1)
    nrm[second] = nrm[second][:, [0, 2, 1]]
    nrm = (nrm / np.linalg.norm(nrm, axis=1, keepdims=True)).astype(np.float32)
    rows = rng.normal(1.0, 0.3, (texel.size, 25)).astype(np.float32)
    valid = rng.random(texel.size) > 0.1
    targets = np.flatnonzero(valid & (rng.random(texel.size) > 0.3))
    a, b = rows.copy(), rows.copy()
    assert gf.smooth_guided(a, texel, W, H, pos, nrm, targets, valid, 0.01) == targets.size
    gf.smooth_guided(b, texel, W, H, pos, nrm, targets, valid, 0.01, compiled=False)
    assert not np.array_equal(a[targets], rows[targets])          # it filtered
    np.testing.assert_allclose(a, b, rtol=2e-6, atol=1e-7)
    others = np.setdiff1d(np.arange(texel.size), targets)
    assert np.array_equal(a[others], rows[others])
    print("bit-identical rows:", np.mean(np.all(a[targets] == b[targets], axis=1)))


@pytest.mark.parametrize("compiled", [True, False])
def test_threads_and_groups_do_not_change_the_answer(monkeypatch, compiled):
    """Bands filtered GROUP at a time on two threads (each band from the rows
    as traced, written once its neighbours' bands are done): the bits of one
    band at a time, for groups of 2, 3 and 4 bands of RADIUS rows."""
    import concurrent.futures as cf
    H, W = 90, 41
    texel, pos, nrm = _plane(H, W, holes=np.arange(0, H * W, 13))
    rng = np.random.default_rng(3)
    rows = rng.normal(size=(texel.size, 9)).astype(np.float32)
    targets = np.flatnonzero(rng.random(texel.size) < 0.7)
    monkeypatch.setattr(gf, "BAND_ROWS", gf.RADIUS)
    a = rows.copy()
    gf.smooth_guided(a, texel, W, H, pos, nrm, targets, np.ones(texel.size, bool), 0.01, compiled=compiled)
    with cf.ThreadPoolExecutor(2) as ex:
        for group in (2, 3, 4):
            monkeypatch.setattr(gf, "GROUP", group)
            b = rows.copy()
            gf.smooth_guided(b, texel, W, H, pos, nrm, targets, np.ones(texel.size, bool), 0.01,
                             compiled=compiled, executor=ex)
            assert np.array_equal(a, b), group
    assert not np.array_equal(a, rows)


@pytest.mark.parametrize("W, H, K", [(1024, 64, 16), (2048, 48, 9)])
def test_filter_bytes_bounds_the_numpy_paths_peak(W, H, K):
    """filter_bytes against what the numpy path allocates (tracemalloc's peak)
    with every texel of a set a target: an upper bound."""
    import tracemalloc
    texel, pos, nrm = _plane(H, W)
    rows = np.random.default_rng(0).normal(size=(texel.size, K)).astype(np.float32)
    tracemalloc.start()
    try:
        gf.smooth_guided(rows, texel, W, H, pos, nrm, np.arange(texel.size), np.ones(texel.size, bool), 0.01,
                         compiled=False)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak <= gf.filter_bytes(W, K, H), (peak, gf.filter_bytes(W, K, H))
