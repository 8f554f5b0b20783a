"""texels.half_columns (#35): one relightable level held as float16 with exact
float32 island borders writes the same float16 planes as the float32 table
it replaces, whatever the values' magnitudes, the islands or the order the
chunks arrive in; a value beyond float16 makes the bake trace the level again
into float32 rows, with the same files."""
import hashlib
import os

import bake_identity
import numpy as np
import pytest

from prtt_addon.core.texels import half_columns
from prtt_addon.core.texels.dilate import DilatedRows, dilation_rings
from prtt_addon.core.texels.half_columns import HalfColumns, border_texels
from tests.scenes_util import random_islands


def test_border_texels_are_the_covered_texels_the_first_ring_reads():
    rng = np.random.default_rng(1)
    m = random_islands(rng, 40, 56)
    rings, _ = dilation_rings(m, 1)
    read = np.zeros_like(m)
    for _, _, taps, _ in rings:
        for _, y, x in taps:
            read[y, x] = True
    border = border_texels(m)
    assert (read <= border).all() and (border <= m).all()
    # And nothing more: every border texel has an empty 8-neighbour in the grid.
    assert np.array_equal(border, read)


@pytest.mark.parametrize("seed,dilate", [(2, 3), (3, 1), (4, 0), (5, 6)])
def test_half_table_writes_the_float32_tables_float16_planes(seed, dilate):
    """Every channel, after dilation, converted to float16 as exr_io writes it:
    bit for bit the float32 table's, for values from 1e-7 to 6e4, either sign."""
    rng = np.random.default_rng(seed)
    H, W, C = 48, 64, 7
    mask = random_islands(rng, H, W)
    texel = np.flatnonzero(mask.reshape(-1)).astype(np.int64)
    n = texel.size
    mag = 10.0 ** rng.uniform(-7, np.log10(6e4), (C, n))
    table = (mag * rng.choice([-1.0, 1.0], (C, n))).astype(np.float32)
    half = HalfColumns(C, texel, mask, dilate, exact_channels=[0, 3])
    order = rng.permutation(n)
    for part in np.array_split(order, 9):            # chunks of texels, in any order
        half.store(part, table[:3, part])
        half.store(part, table[3:, part], first=3)
    assert not half.overflow
    ref, got = DilatedRows([table], texel, mask, dilate), DilatedRows([half], texel, mask, dilate)
    for c in range(C):
        a = ref.channel(c).astype(np.float16)
        b = got.channel(c).astype(np.float16)
        assert a.tobytes() == b.tobytes(), c
    for c in (0, 3):                                 # the exact channels are the float32 rows
        assert np.array_equal(half[c], table[c])
    lo, hi = got.value_range()
    assert np.float16(lo) == np.float16(ref.value_range()[0]) and np.float16(hi) == np.float16(ref.value_range()[1])
    assert half.half.nbytes * 2 == table.nbytes and half.border.shape[1] < n


def test_a_value_beyond_float16_is_flagged_and_nan_propagates():
    mask = np.ones((4, 4), bool)
    texel = np.arange(16, dtype=np.int64)
    h = HalfColumns(2, texel, mask, 1)
    h.store(texel[:8], np.ones((2, 8), np.float32))
    assert not h.overflow
    h.store(texel[8:], np.full((2, 8), 70000.0, np.float32))
    assert h.overflow
    n = HalfColumns(1, texel, mask, 1)
    v = np.zeros((1, 16), np.float32)
    v[0, 5] = np.nan
    n.store(texel, v)
    assert np.isnan(n.value_range()[0])


def _hashes(folder):
    return {f: hashlib.sha256(open(os.path.join(folder, f), "rb").read()).hexdigest()
            for f in sorted(os.listdir(folder)) if f.endswith(".exr")}


def test_overflow_retraces_the_level_into_float32_rows_with_the_same_files(tmp_path, monkeypatch):
    """A relightable bake (one level, half) whose table would overflow (the
    limit lowered to 1e-6 here: real responses to unit light stay far below
    65504) traces the level again into float32 rows: the files are the
    ones the float16 table gives."""
    first = tmp_path / "half"
    want = bake_identity.bake_case("relightable-auto-1", str(first))
    made = []
    orig = HalfColumns.__init__

    def spy(self, *a, **k):
        orig(self, *a, **k)
        made.append(self)
    monkeypatch.setattr(HalfColumns, "__init__", spy)
    monkeypatch.setattr(half_columns, "HALF_MAX", 1e-6)
    again = tmp_path / "retraced"
    got = bake_identity.bake_case("relightable-auto-1", str(again))
    assert made and all(h.overflow for h in made)
    assert got == want
    assert _hashes(first) == _hashes(again)
