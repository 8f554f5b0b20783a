"""exr_io.write_sh_planes writes a band of rows at a time through OpenEXR's
scanline writer (#35): the bytes are those of OpenEXR's whole-file API given
every channel at once (as the writer did before), for every compression,
precision and channel layout PRTT writes, whatever the band height; what it
refuses leaves no file."""
import os
import sys

import numpy as np
import pytest

from prtt_addon.core.io import exr_io


def _whole_file(path, planes, *, kind, half, names, attrs, mantissa_bits, exact):
    """The writer before #35's bands: OpenEXR.File with every channel at once."""
    import OpenEXR
    dtype = np.float16 if half else np.float32
    chans = {}
    for c, n in enumerate(names):
        p = np.ascontiguousarray(planes[c][::-1], dtype=dtype)
        if half and mantissa_bits < 10 and not exact[c]:
            p = exr_io.quantize_half(p, mantissa_bits)
        chans[n] = p
    C, H, W = planes.shape
    header = {"compression": exr_io.compression_of(kind), "type": OpenEXR.scanlineimage,
              "prtt_format_version": exr_io.TEXTURE_FORMAT_VERSION, "prtt_kind": kind, "prtt_bands": attrs.pop("bands"),
              "prtt_convention": exr_io.CONVENTION, "prtt_resolution": f"{W}x{H}",
              "prtt_storage": "half" if half else "float"}
    if half and mantissa_bits < 10:
        header["prtt_mantissa_bits"] = mantissa_bits
    header.update({"prtt_" + k: v for k, v in attrs.items()})
    with OpenEXR.File(header, chans) as f:
        f.write(str(path))


CASES = [
    # kind, C, H, W, half, mantissa bits, band bytes (small: several bands, the last one short)
    ("transfer", 9, 100, 70, True, 10, 1 << 16),
    ("transfer", 16, 77, 33, True, 6, 1 << 15),
    ("transfer", 4, 64, 64, False, 10, 1 << 14),
    ("relight", 12, 101, 40, True, 6, 1 << 16),
    ("relight", 12, 45, 40, False, 10, 1 << 30),
]


@pytest.mark.parametrize("kind,C,H,W,half,bits,band", CASES)
def test_bands_write_the_whole_file_apis_bytes(tmp_path, monkeypatch, kind, C, H, W, half, bits, band):
    monkeypatch.setattr(exr_io, "WRITE_BAND_BYTES", band)
    rng = np.random.default_rng(C * H)
    planes = (rng.standard_normal((C, H, W)) * 10.0 ** rng.uniform(-4, 2, (C, 1, 1))).astype(np.float32)
    planes[:, : H // 5] = 0.0
    attrs = {"rays": 256, "seed": 3, "sampler": "sobol", "input_hash": "ab" * 32, "scale": 0.25}
    if kind == "relight":
        names = [f"R.dc.i{i:03d}" for i in range(C)]
        full = [i % 5 == 0 for i in range(C)]
        extra = dict(names=names, bands=2, full_bits=full)
        ref_exact = full
    else:
        names = exr_io.channel_names(C)
        extra = {}
        ref_exact = [c % C == 0 for c in range(C)]
    got = tmp_path / "bands.exr"
    seen = []
    exr_io.write_sh_planes(got, planes, kind=kind, half=half, attrs=dict(attrs), mantissa_bits=bits,
                           visit=lambda y0, b: seen.append((y0, b.shape[1])), **extra)
    ref = tmp_path / "whole.exr"
    _whole_file(ref, planes, kind=kind, half=half, names=names, attrs=dict(attrs, bands=extra.get("bands", int(C ** 0.5))),
                mantissa_bits=bits, exact=ref_exact)
    assert got.read_bytes() == ref.read_bytes()
    # The bands cover every row once, top first (file order), in whole 32-row blocks but the last.
    assert sorted(r for y0, n in seen for r in range(y0, y0 + n)) == list(range(H))
    assert [y0 for y0, _ in seen] == sorted((y0 for y0, _ in seen), reverse=True)
    assert all(n % exr_io.WRITE_BAND_BLOCK == 0 for _, n in seen[:-1])


def test_consume_gives_the_planes_back_band_by_band(tmp_path, monkeypatch):
    monkeypatch.setattr(exr_io, "WRITE_BAND_BYTES", 1 << 18)         # four bands of 64 rows
    planes = np.ones((5, 256, 512), np.float32)
    exr_io.write_sh_planes(tmp_path / "t.exr", planes[:4].copy(), kind="transfer")
    p = planes[:4].copy()
    exr_io.write_sh_planes(tmp_path / "c.exr", p, kind="transfer", consume=True)
    assert (tmp_path / "c.exr").read_bytes() == (tmp_path / "t.exr").read_bytes()
    # Every whole page inside a band was given back (reads as zero); pages across two bands' rows stay.
    if sys.platform.startswith("linux"):          # madvise zeroes given-back pages there
        assert np.count_nonzero(p) < 0.05 * p.size


@pytest.mark.parametrize("bad", [[b"a", b"b"], ["a"], {"k": 1}, None])
def test_an_attribute_the_writer_cannot_hold_is_refused_before_any_file(tmp_path, bad):
    with pytest.raises(TypeError, match="prtt_bad"):
        exr_io.write_sh_planes(tmp_path / "x.exr", np.zeros((1, 4, 4), np.float32), kind="transfer",
                               attrs={"bad": bad})
    assert os.listdir(tmp_path) == []


def test_band_rows_are_whole_blocks_of_32_mib():
    assert exr_io.write_band_rows(25, 4096, True) == 160
    assert exr_io.write_band_rows(147, 2048, True) == 32
    assert exr_io.write_band_rows(147, 2048, False) == 32     # at least one block
    assert exr_io.write_band_rows(1, 64, True) % exr_io.WRITE_BAND_BLOCK == 0


_WRITER_CHILD = r"""
import json, sys
import numpy as np
from prtt_addon.core.base.memory import large_frees_to_os, resident_bytes
from prtt_addon.core.io import exr_io
large_frees_to_os()                      # as the bake worker does
import OpenEXR  # noqa: F401,E402 - imported before the measurement, as in a bake (the writer imports it)
kind, C, W, H, threads = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
exr_io.WRITE_THREADS = threads
names = exr_io.relight_channel_names(25, 9) if kind == "relight" else None
planes = np.random.default_rng(1).random((C, H, W), dtype=np.float32)
before = resident_bytes()
with open("/proc/self/clear_refs", "w") as f:      # the high-water mark from here (Linux)
    f.write("5")
exr_io.write_sh_planes(sys.argv[6], planes, kind=kind, names=names, bands=5, atomic=False)
hwm = next(int(l.split()[1]) * 1024 for l in open("/proc/self/status") if l.startswith("VmHWM:"))
print(json.dumps({"growth": hwm - before, "threads": exr_io.write_threads()}))
"""


@pytest.mark.parametrize("kind, C", [("relight", 291), ("transfer", 25)])
def test_the_writers_line_buffers_are_what_the_memory_plan_counts(tmp_path, kind, C):
    """OpenEXR's scanline writer keeps line buffers that grow with its threads
    (what memory_plan's write stages add: exr_io.writer_bytes). The resident
    growth of a real write of a wide texture (its band plus the writer) stays
    within the model (and 4 MiB), and the model is not far above it (>= 0.6 of it)."""
    import json
    import subprocess
    if not os.access("/proc/self/clear_refs", os.W_OK):
        pytest.skip("no /proc/self/clear_refs (Linux) to measure a peak from")
    W, H = 512, 512
    got = {}
    for threads in (1, 2):
        r = subprocess.run([sys.executable, "-c", _WRITER_CHILD, kind, str(C), str(W), str(H), str(threads),
                            str(tmp_path / f"{kind}{threads}.exr")], capture_output=True, text=True,
                           cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))), timeout=300)
        assert r.returncode == 0, r.stderr
        out = json.loads(r.stdout.strip().splitlines()[-1])
        t = out["threads"]
        band = exr_io.write_band_rows(C, W, True) * C * W * 2
        model = exr_io.writer_bytes(C, W, True, kind, t) + min(band, C * W * H * 2)
        got[t] = (out["growth"], model)
        print(f"{kind}, {C} channels x {W}, {t} thread(s): grew {out['growth'] / 2**20:.0f} MB, "
              f"model {model / 2**20:.0f} MB")
        # 4 MiB: the header, the value-range checks' temporaries, the allocator's pages.
        assert 0.6 * model <= out["growth"] <= model + (4 << 20), (t, out["growth"], model)
    if len(got) == 2:                      # a 1-core machine runs one thread twice
        assert got[2][0] > got[1][0]
