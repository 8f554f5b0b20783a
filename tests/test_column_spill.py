"""estimators.column_spill and texels.dilate.DilatedRows.band (#35): one relightable
level waits in a temporary file, not in memory, and the texture written from
it a band of rows at a time is the one the whole in-memory table gives, bit
for bit, whatever the islands, the dilation, the band heights or the order
and threads the chunks arrive from; the file is gone afterwards, also when
the bake is cancelled."""
import concurrent.futures
import os
import threading

import numpy as np
import pytest

from prtt_addon.core.bake.estimators.column_spill import ColumnSpill
from prtt_addon.core.base import atomic
from prtt_addon.core.io import exr_io
from prtt_addon.core.texels.dilate import DilatedRows, dilation_rings, grown_mask
from tests.scenes_util import random_islands


def _table(rng, C, mask, big=False):
    texel = np.flatnonzero(mask.reshape(-1)).astype(np.int64)
    texel = texel[rng.permutation(texel.size)]         # columns in no order of rows, as a G-buffer's
    top = 9e4 if big else 6e4
    mag = 10.0 ** rng.uniform(-7, np.log10(top), (C, texel.size))
    return texel, (mag * rng.choice([-1.0, 1.0], (C, texel.size))).astype(np.float32)


def _spill(tmp_path, rng, texel, table, mask, bucket_rows=5, threads=2):
    H, W = mask.shape
    C, n = table.shape
    sp = ColumnSpill(C, texel, W, H, str(tmp_path), exact_channels=[0, 3], bucket_rows=bucket_rows)
    parts = np.array_split(rng.permutation(n), 11)
    # Stored as the relightable projection stores a chunk: two channel ranges, from two threads.
    with concurrent.futures.ThreadPoolExecutor(threads) as ex:
        list(ex.map(lambda p: (sp.store(p, table[:3, p]), sp.store(p, table[3:, p], first=3)), parts))
    return sp


@pytest.mark.parametrize("seed,dilate,rows", [(2, 3, 7), (3, 1, 32), (4, 0, 5), (5, 6, 3), (6, 2, 64)])
def test_spilled_bands_are_the_in_memory_planes(tmp_path, seed, dilate, rows):
    rng = np.random.default_rng(seed)
    H, W, C = 48, 64, 7
    mask = random_islands(rng, H, W)
    texel, table = _table(rng, C, mask)
    ref = DilatedRows([table], texel, mask, dilate)
    with _spill(tmp_path, rng, texel, table, mask) as sp:
        got = DilatedRows([sp], texel, mask, dilate)
        whole = np.stack([ref.channel(c) for c in range(C)])
        for y0 in range(0, H, rows):
            y1 = min(H, y0 + rows)
            b = got.band(y0, y1)
            assert b.dtype == np.float32 and b.shape == (C, y1 - y0, W)
            assert b.tobytes() == whole[:, y0:y1].tobytes(), (y0, y1)
            # The in-memory table's band is the same too (the path a multi-level bake writes).
            assert ref.band(y0, y1).tobytes() == b.tobytes()
        for c in (0, 3):                                # the DC responses stay in memory, exact
            assert np.array_equal(sp[c], table[c])
        with pytest.raises(KeyError):
            sp[1]
        lo, hi = got.value_range()
        assert (lo, hi) == ref.value_range()
        # Its name is gone while it is open (POSIX: unlinked; Windows: deleted on close).
        if os.name != "nt":
            assert os.listdir(tmp_path) == []
        assert os.path.basename(sp.path).startswith(atomic.TMP_PREFIX)
        assert sp.file_bytes() == sp.bytes_written > table.nbytes
    assert sp.closed and sp.file_bytes() == 0 and os.listdir(tmp_path) == []
    with pytest.raises(ValueError, match="closed"):
        got.band(0, 4)


def test_the_spill_holds_texel_ids_and_values_and_nothing_whole_in_memory(tmp_path):
    rng = np.random.default_rng(9)
    mask = random_islands(rng, 40, 40)
    texel, table = _table(rng, 5, mask)
    with _spill(tmp_path, rng, texel, table, mask) as sp:
        # One int64 texel id per column and record (two records per chunk), the float32 values once.
        assert sp.bytes_written == table.nbytes + 2 * 8 * texel.size
        assert sp.file_bytes() == sp.bytes_written
        assert sp.exact.nbytes == 2 * 4 * texel.size       # the two exact channels, nothing more


def test_grown_mask_is_the_dilations(tmp_path):
    rng = np.random.default_rng(4)
    for d in (0, 1, 3, 40):
        m = random_islands(rng, 30, 50)
        assert np.array_equal(grown_mask(m, d), dilation_rings(m, d)[1])


def test_nan_and_values_beyond_half_reach_the_writer_as_before(tmp_path):
    """A value beyond float16 makes the file float32 (write_planes' rule, from
    the spill's range), the same bytes as from the float32 table; NaN is refused."""
    rng = np.random.default_rng(11)
    H, W, C = 40, 36, 6
    mask = random_islands(rng, H, W)
    texel, table = _table(rng, C, mask, big=True)
    assert np.abs(table).max() > exr_io.HALF_MAX
    names = [f"c{i}" for i in range(C)]
    with _spill(tmp_path, rng, texel, table, mask) as sp:
        a = DilatedRows([sp], texel, mask, 2)
        b = DilatedRows([table], texel, mask, 2)
        assert a.value_range() == b.value_range() and a.value_range()[1] > exr_io.HALF_MAX
        with pytest.raises(ValueError, match="half-float range"):
            exr_io.write_sh_planes(tmp_path / "h.exr", a, kind="relight", names=names, bands=1, rng=a.value_range())
        assert not (tmp_path / "h.exr").exists()
        exr_io.write_sh_planes(tmp_path / "a.exr", a, kind="relight", half=False, names=names, bands=1,
                               rng=a.value_range())
        exr_io.write_sh_planes(tmp_path / "b.exr", b, kind="relight", half=False, names=names, bands=1,
                               rng=b.value_range())
        assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()
    sp = ColumnSpill(1, texel, W, H, str(tmp_path))
    v = np.zeros((1, texel.size), np.float32)
    v[0, 5] = np.nan
    sp.store(np.arange(texel.size), v)
    assert np.isnan(sp.value_range()[0])
    with pytest.raises(ValueError, match="non-finite"):
        exr_io.write_sh_planes(tmp_path / "n.exr", DilatedRows([sp], texel, mask, 1), kind="relight",
                               names=["c0"], bands=1, rng=DilatedRows([sp], texel, mask, 1).value_range())
    sp.close()
    sp.close()                                          # twice is fine
    assert [f for f in os.listdir(tmp_path) if f.endswith(".spill")] == []


def test_a_cancelled_relightable_bake_leaves_no_spill_file(tmp_path, monkeypatch):
    """Cancelled during the bounce's trace: the bake stops, and neither its
    spill file nor any other temporary is left in the output folder."""
    from prtt_addon.core.bake.pipeline.context import BakeSettings
    from prtt_addon.core.bake.pipeline.runner import bake_scene
    from prtt_addon.core.base.errors import Cancelled
    from prtt_addon.dev.bench.scene_library import room_scene

    cancel = threading.Event()
    made = []
    orig = ColumnSpill.store

    def store(self, *a, **k):
        made.append(self)
        orig(self, *a, **k)

    def progress(e):
        if e.get("stage") == "bounce" and e.get("type") == "progress" and made:
            cancel.set()

    monkeypatch.setattr(ColumnSpill, "store", store)
    st = BakeSettings(rays=32, bounce_rays=16, seed=3, threads=2, bounces=1, bounce_mode="relightable")
    with pytest.raises(Cancelled):
        bake_scene(room_scene(64, atlas=True, materials=True), str(tmp_path), st, progress=progress, cancel=cancel)
    assert made and made[0].bytes_written > 0, "the level was spilled before the cancel"
    assert all(s.closed for s in made)
    assert [f for f in os.listdir(tmp_path) if f.startswith(atomic.TMP_PREFIX)] == []
