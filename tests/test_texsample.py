"""Texture layouts: texel rows (N, C) -> channel planes (C, H*W)."""
import concurrent.futures as cf

import numpy as np
import pytest

from prtt_addon.core.texels.texsample import pixel_major, planes_from_rows


@pytest.mark.parametrize("n_texels,density,block", [
    (1000, 0.7, 64), (4096, 0.02, 16), (777, 1.0, 777), (500, 0.0, 8), (1, 1.0, 4096),
])
@pytest.mark.parametrize("threads", [0, 2])
def test_planes_from_rows_equals_direct_scatter(n_texels, density, block, threads):
    rng = np.random.default_rng(n_texels)
    texel = np.flatnonzero(rng.random(n_texels) < density)
    rows = rng.normal(size=(texel.size, 5)).astype(np.float32)
    want = np.zeros((5, n_texels), np.float32)
    want[:, texel] = rows.T
    ex = cf.ThreadPoolExecutor(threads) if threads else None
    got = planes_from_rows(texel, rows, n_texels, executor=ex, block=block)
    assert got.dtype == np.float32 and got.shape == want.shape
    assert np.array_equal(got, want)
    # and back: pixel-major rows of the covered texels are the input rows
    assert np.array_equal(pixel_major(got.reshape(5, 1, n_texels))[texel], rows)


def test_planes_from_rows_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="texel must have shape"):
        planes_from_rows(np.arange(3), np.zeros((4, 2), np.float32), 10)
