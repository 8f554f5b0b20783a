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
