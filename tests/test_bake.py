"""bake_scene end to end: outputs, manifest, atomicity, cancel, overlaps, vertex mode, mips."""
import json
import os
import subprocess
import sys
import threading

import numpy as np
import pytest

from prtt_addon.core.bake.estimators.transfer import unoccluded_transfer
from prtt_addon.core.bake.pipeline.context import BakeSettings
from prtt_addon.core.bake.pipeline.runner import bake_scene
from prtt_addon.core.base.errors import BakeError, Cancelled
from prtt_addon.core.base.memory import MemoryLimitError
from prtt_addon.core.io import exr_io
from prtt_addon.dev.bench import meshgen as mg
from tests.scenes_util import floor_and_box, planar_uvs, scene_from

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_outputs_manifest_and_header(tmp_path):
    sc = floor_and_box(res=32)
    m = bake_scene(sc, tmp_path, BakeSettings(rays=64, bounce_mode="baked"))
    assert sorted(os.listdir(tmp_path)) == ["box.transfer.exr", "floor.transfer.exr", "manifest.json"]
    man = json.loads((tmp_path / "manifest.json").read_text())
    assert man == m and man["skipped"] is False
    assert man["settings"]["rays"] == 64 and man["input_hash"] and man["settings_hash"]
    for s in man["sets"]:
        assert s["rays_traced"] <= s["rays_naive"] and s["texels"] > 0
    for k in ("bvh", "gbuffer", "trace", "dilate", "write", "total"):
        assert man["seconds"][k] >= 0
    data, attrs = exr_io.read_sh_exr(tmp_path / "floor.transfer.exr")
    assert data.shape == (32, 32, 25)
    assert attrs["kind"] == "transfer" and attrs["bands"] == 5 and attrs["rays"] == 64
    assert attrs["storage"] == "half" and attrs["input_hash"] == man["input_hash"]
    assert attrs["format_version"] == exr_io.TEXTURE_FORMAT_VERSION
    import OpenEXR
    with OpenEXR.File(str(tmp_path / "floor.transfer.exr")) as f:
        h = dict(f.header())
        chans = list(f.channels())
    assert h["compression"] == OpenEXR.ZIP_COMPRESSION
    assert sorted(chans) == [f"sh{k:03d}" for k in range(25)]


def test_texels_hold_transfer_and_dilation_fills_borders(tmp_path):
    f = mg.plane(2.0)
    uvs = planar_uvs(f) * 0.5 + 0.25                # island in the middle, empty border
    sc = scene_from([("floor", f, uvs)], 32)
    bake_scene(sc, tmp_path, BakeSettings(rays=64, half=False, dilate=3))
    data, _ = exr_io.read_sh_exr(tmp_path / "floor.transfer.exr")
    want = unoccluded_transfer(np.array([[0, 0, 1.0]]), 5)[0]
    island = data[8:24, 8:24]
    assert np.abs(island - want).max() < 1e-5
    ring = data[5:27, 5:27].copy()
    assert np.abs(ring - want).max() < 1e-5        # 3 texels of dilation around the island
    assert np.all(data[:4] == 0) and np.all(data[:, :4] == 0)


def test_float_storage_and_strided_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    base = rng.standard_normal((20, 30, 25 * 2)).astype(np.float32)
    strided = base[:, :, ::2]                      # a non-contiguous view
    assert not strided.flags.c_contiguous
    exr_io.write_sh_exr(tmp_path / "t.exr", strided, kind="transfer", half=False)
    back, attrs = exr_io.read_sh_exr(tmp_path / "t.exr")
    np.testing.assert_array_equal(back, strided)
    exr_io.write_sh_exr(tmp_path / "h.exr", strided, kind="transfer", half=True)
    back, attrs = exr_io.read_sh_exr(tmp_path / "h.exr")
    np.testing.assert_allclose(back, strided, rtol=1e-3, atol=1e-4)
    rgb = rng.standard_normal((6, 5, 3, 9)).astype(np.float32)[:, :, :, :]
    exr_io.write_sh_exr(tmp_path / "rgb.exr", rgb[::1, ::1], kind="bounce", half=False, rgb=True)
    back, _ = exr_io.read_sh_exr(tmp_path / "rgb.exr")
    np.testing.assert_array_equal(back, rgb)


def test_exr_write_is_atomic(tmp_path, monkeypatch):
    good = np.zeros((4, 4, 9), np.float32)
    exr_io.write_sh_exr(tmp_path / "t.exr", good, kind="transfer")
    before = (tmp_path / "t.exr").read_bytes()
    import OpenEXR

    class Exploding:
        """The scanline writer failing after its first bytes (a full disk mid-file)."""

        def __init__(self, path, header):
            with open(path, "wb") as fh:
                fh.write(b"half a texture")

        def writePixels(self, *a):
            raise OSError("disk full")

        def close(self):
            pass

    monkeypatch.setattr(OpenEXR, "OutputFile", Exploding)
    with pytest.raises(OSError, match="disk full"):
        exr_io.write_sh_exr(tmp_path / "t.exr", good + 1, kind="transfer")
    assert (tmp_path / "t.exr").read_bytes() == before
    assert os.listdir(tmp_path) == ["t.exr"]


def test_non_finite_and_half_overflow(tmp_path):
    with pytest.raises(ValueError, match="non-finite"):
        exr_io.write_sh_exr(tmp_path / "n.exr", np.full((2, 2, 4), np.nan, np.float32), kind="transfer")
    big = np.full((2, 2, 4), 1e5, np.float32)
    assert exr_io.half_overflow(big) == 16
    with pytest.raises(ValueError, match="half-float range"):
        exr_io.write_sh_exr(tmp_path / "o.exr", big, kind="transfer", half=True)
    assert not os.path.exists(tmp_path / "n.exr") and not os.path.exists(tmp_path / "o.exr")


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("channel", [0, 3])
def test_value_range_in_parallel_still_sees_nan_and_inf(bad, channel):
    """One (min, max) pass over the channels feeds both write checks; a NaN in
    any channel must survive the per-channel split (Python's min() would drop it)."""
    import concurrent.futures as cf
    planes = np.random.default_rng(0).normal(size=(4, 8, 8)).astype(np.float32)
    with cf.ThreadPoolExecutor(2) as ex:
        assert exr_io.value_range(planes, ex) == (float(planes.min()), float(planes.max()))
        planes[channel, 3, 5] = bad
        lo, hi = exr_io.value_range(planes, ex)
    assert not (np.isfinite(lo) and np.isfinite(hi))
    with pytest.raises(ValueError, match="non-finite"):
        exr_io.check_finite(planes, "t", (lo, hi))
    assert exr_io.value_range(planes[:0]) == (0.0, 0.0)


def test_unchanged_inputs_skip_and_force(tmp_path):
    sc = floor_and_box(res=16)
    st = BakeSettings(rays=32)
    first = bake_scene(sc, tmp_path, st)
    again = bake_scene(sc, tmp_path, st)
    assert again["skipped"] is True and again["input_hash"] == first["input_hash"]
    changed = bake_scene(sc, tmp_path, BakeSettings(rays=32, threads=1))   # threads do not change results
    assert changed["skipped"] is True
    rebaked = bake_scene(sc, tmp_path, BakeSettings(rays=48))
    assert rebaked["skipped"] is False
    forced = bake_scene(sc, tmp_path, BakeSettings(rays=48), skip_if_unchanged=False)
    assert forced["skipped"] is False


def test_bit_identical_rebake(tmp_path):
    sc = floor_and_box(res=24)
    bake_scene(sc, tmp_path / "a", BakeSettings(rays=64, half=False))
    bake_scene(sc, tmp_path / "b", BakeSettings(rays=64, half=False, threads=1))
    for name in ("floor", "box"):
        a, _ = exr_io.read_sh_exr(tmp_path / "a" / f"{name}.transfer.exr")
        b, _ = exr_io.read_sh_exr(tmp_path / "b" / f"{name}.transfer.exr")
        np.testing.assert_array_equal(a, b)


def test_cancel_keeps_previous_outputs(tmp_path):
    sc = floor_and_box(res=16)
    bake_scene(sc, tmp_path, BakeSettings(rays=32))
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    cancel = threading.Event()
    events = []

    def progress(e):
        events.append(e)
        if e.get("stage") == "trace":
            cancel.set()

    with pytest.raises(Cancelled):
        bake_scene(floor_and_box(res=32), tmp_path, BakeSettings(rays=64), progress=progress, cancel=cancel)
    after = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert after == before                          # no temporaries, nothing replaced


def test_overlapping_uvs_warn_or_fail(tmp_path):
    f1 = mg.plane(1.0)
    f2 = mg.plane(1.0).transformed(translate=(3, 0, 0))
    m = mg.merge([f1, f2])
    uvs = np.concatenate([planar_uvs(f1), planar_uvs(f2)])     # both islands fill [0, 1]^2
    sc = scene_from([("floors", m, uvs)], 16)
    man = bake_scene(sc, tmp_path / "warn", BakeSettings(rays=16))
    assert man["sets"][0]["overlap_texels"] == 256
    assert any("overlapping UV islands" in w for w in man["warnings"])
    with pytest.raises(BakeError, match="256 texels are covered by overlapping UV islands"):
        bake_scene(sc, tmp_path / "err", BakeSettings(rays=16, overlap="error"))
    assert not os.listdir(tmp_path / "err")


def test_vertex_mode_matches_texels(tmp_path):
    sc = floor_and_box(res=32, subdiv=4)
    bake_scene(sc, tmp_path, BakeSettings(rays=512, vertex_mode=True))
    v = np.load(tmp_path / "floor.vertex.npz")
    assert v["coeffs"].shape == (v["positions"].shape[0], 25)
    assert v["corner_vertex"].shape == (int((sc.set_id == 0).sum()), 3)
    # a floor vertex far from the box sees nearly the whole sky
    far = np.flatnonzero(np.abs(v["positions"][:, 0]) > 1.9)
    want = unoccluded_transfer(np.array([[0, 0, 1.0]]), 5)[0]
    assert np.abs(v["coeffs"][far][:, 0] - want[0]).max() < 0.05
    # corner_vertex maps every corner to its own vertex
    P = sc.positions[sc.set_id == 0]
    np.testing.assert_allclose(v["positions"][v["corner_vertex"]], P, atol=1e-6)


def test_mips_average_only_covered_texels(tmp_path):
    f = mg.plane(2.0)
    uvs = planar_uvs(f) * 0.5                       # island in the lower-left quarter
    sc = scene_from([("floor", f, uvs)], 32)
    m = bake_scene(sc, tmp_path, BakeSettings(rays=32, mips=True, half=False))
    assert "floor.transfer.mip1.exr" in m["files"] and "floor.transfer.mip5.exr" in m["files"]
    want = unoccluded_transfer(np.array([[0, 0, 1.0]]), 5)[0]
    mip, _ = exr_io.read_sh_exr(tmp_path / "floor.transfer.mip1.exr")
    assert mip.shape == (16, 16, 25)
    assert np.abs(mip[:8, :8] - want).max() < 1e-5  # no dilated or empty texel bled in
    top, _ = exr_io.read_sh_exr(tmp_path / "floor.transfer.mip5.exr")
    assert np.abs(top[0, 0] - want).max() < 1e-5


def test_atlas_and_per_object_sets(tmp_path):
    objs = [("a", mg.box((1, 1, 1))), ("b", mg.box((1, 1, 1), (3, 0, 0)))]
    per = mg.assemble(objs, resolution=128)
    atlas = mg.assemble(objs, resolution=128, atlas=True)
    assert per.set_names == ["a", "b"] and atlas.set_names == ["atlas"]
    m1 = bake_scene(per, tmp_path / "per", BakeSettings(rays=16, bounce_mode="baked"))
    m2 = bake_scene(atlas, tmp_path / "atlas", BakeSettings(rays=16, bounce_mode="baked"))
    assert m1["files"] == ["a.transfer.exr", "b.transfer.exr"]
    assert m2["files"] == ["atlas.transfer.exr"] and m2["sets"][0]["overlap_texels"] == 0


def test_absurd_resolution_is_refused_before_allocating(tmp_path):
    sc = floor_and_box(res=16)
    sc.set_resolution[0] = [16384, 16384]
    with pytest.raises(MemoryLimitError, match="needs about .* GiB"):
        bake_scene(sc, tmp_path, BakeSettings(rays=16, bands=16))
    assert not os.listdir(tmp_path)


def test_output_path_is_a_file(tmp_path):
    (tmp_path / "taken").write_text("not a folder")
    with pytest.raises(BakeError, match="cannot create output folder"):
        bake_scene(floor_and_box(res=8), tmp_path / "taken" / "sub", BakeSettings(rays=8))


def test_unwritable_output_folder(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        if os.access(ro, os.W_OK):
            pytest.skip("running as a user that ignores permissions")
        with pytest.raises(BakeError, match="not writable"):
            bake_scene(floor_and_box(res=8), ro, BakeSettings(rays=8))
    finally:
        ro.chmod(0o700)


@pytest.mark.parametrize("bad, match", [
    (dict(rays=0), r"rays must be an integer 1\.\.65536, got 0"),
    (dict(rays=10 ** 9), r"rays must be an integer 1\.\.65536, got 1000000000"),
    (dict(rays=64.0), r"rays must be an integer 1\.\.65536, got 64\.0"),
    (dict(rays=True), r"rays must be an integer 1\.\.65536, got True"),
    (dict(bands=0), r"bands must be an integer 1\.\.16, got 0"),
    (dict(bands=17), r"bands must be an integer 1\.\.16, got 17"),
    (dict(threads=1000), r"threads must be an integer 0\.\.256, got 1000"),
    (dict(n_patterns=10 ** 6), r"n_patterns must be an integer 1\.\.1024, got 1000000"),
    (dict(chunk_rays=1), r"chunk_rays must be an integer 1024\.\.4194304, got 1"),
    (dict(seed=2 ** 32), r"seed must be an integer 0\.\.4294967295, got 4294967296"),
    (dict(seed=-1), r"seed must be an integer 0\.\.4294967295, got -1"),
    (dict(min_rays=0), r"min_rays must be an integer 1\.\.65536, got 0"),
    (dict(dilate=-1), r"dilate must be an integer 0\.\.64, got -1"),
    (dict(bounces=9), r"bounces must be an integer 0\.\.8, got 9"),
    (dict(bounce_rays=0), r"bounce_rays must be an integer 1\.\.16384, got 0"),
    (dict(sampler="halton"), "sampler must be one of sobol, stratified, random, got 'halton'"),
    (dict(estimator=["plain"]), r"estimator must be one of .*, got \['plain'\]"),
    (dict(overlap="ignore"), "overlap must be one of warn, error, got 'ignore'"),
    (dict(adaptive_tol=-1.0), r"adaptive_tol must be a number 0\.\.100, got -1\.0"),
    (dict(adaptive_tol=float("nan")), r"adaptive_tol must be a number 0\.\.100, got nan"),
    (dict(half="no"), "half must be true or false, got 'no'"),
    (dict(analytic=0), "analytic must be true or false, got 0"),
])
def test_bad_settings(bad, match, tmp_path):
    """Every setting is bounded and typed: out-of-range values, bools or floats for
    integers and strings for flags are refused, naming the setting, range and value."""
    with pytest.raises(ValueError, match=match):
        bake_scene(floor_and_box(res=8), tmp_path, BakeSettings(**bad))
    assert not os.listdir(tmp_path)


def test_atomic_writes_get_normal_permissions(tmp_path):
    """mkstemp makes 0600 files; outputs must be as readable as open() would make
    them (others on a render farm read the textures), and keep an old file's mode."""
    from prtt_addon.core.base import atomic
    good = np.zeros((4, 4, 9), np.float32)
    exr_io.write_sh_exr(tmp_path / "new.exr", good, kind="transfer")
    assert os.stat(tmp_path / "new.exr").st_mode & 0o777 == 0o666 & ~atomic._UMASK
    os.chmod(tmp_path / "new.exr", 0o640)
    exr_io.write_sh_exr(tmp_path / "new.exr", good + 1, kind="transfer")
    assert os.stat(tmp_path / "new.exr").st_mode & 0o777 == 0o640


def _hugepage_advice_now() -> bool:
    from prtt_addon.core.base.memory import _numpy_hugepage_switch
    switch = _numpy_hugepage_switch()
    now = switch(True)
    switch(now)
    return now


def test_hugepage_advice_off_for_streamed_stages_only(tmp_path):
    """Transfer stages (G-buffer .. EXR) run without numpy's huge-page advice,
    the bounce stage with the caller's setting, and the bake restores it
    (memory.numpy_hugepage_advice: both measured to be faster that way)."""
    from prtt_addon.core.base.memory import numpy_hugepage_advice
    with numpy_hugepage_advice(False):
        with numpy_hugepage_advice(True):
            assert _hugepage_advice_now() is True
        assert _hugepage_advice_now() is False
    before = _hugepage_advice_now()
    seen = {}

    def progress(e):
        if e.get("type") == "progress":
            seen.setdefault(e["stage"], _hugepage_advice_now())

    light = np.zeros((25, 3))
    light[0] = 1.0
    bake_scene(floor_and_box(res=16), tmp_path, BakeSettings(rays=32, bounce_rays=8), light=light,
               progress=progress)
    assert seen["gbuffer"] is False and seen["trace"] is False
    assert seen["bounce"] is before
    assert _hugepage_advice_now() is before


_TRIM_PROBE = """
import sys, threading
import numpy as np
from prtt_addon.core.base.memory import release_free_memory
def rss():
    return next(int(l.split()[1]) for l in open('/proc/self/status') if l.startswith('VmRSS')) / 1024
keep = []
def work():
    big = []
    for i in range(2000):
        big.append(np.ones(12_000))          # 96 KB: below the mmap threshold, in this thread's arena
        keep.append(np.ones(16))             # small survivors pin the arena's freed holes
    del big
t = threading.Thread(target=work); t.start(); t.join()
before = rss(); ran = release_free_memory(); after = rss()
print(ran, before, after)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc; malloc_trim is glibc's")
def test_release_free_memory_returns_a_helper_threads_freed_arena():
    """What the G-buffer's helper threads free stays in their glibc arenas
    (RSS) until core.base.memory.release_free_memory hands it back."""
    r = subprocess.run([sys.executable, "-c", _TRIM_PROBE], capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, PYTHONPATH=ROOT))
    ran, before, after = r.stdout.split()
    assert ran == "True", r.stderr
    assert float(before) - float(after) > 100, (before, after)      # ~190 MB freed but held
