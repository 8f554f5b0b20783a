"""The numerical stress suite (prtt_addon/dev/bench/stress.py): every case holds.

Scene scale 1e-3 .. 1e4, grazing and flipped normals, a 10 um slab and
coincident faces, needle / zero-area / zero-UV-area triangles, a texture-sized
island and 400 sub-texel islands, 16 bands, a 1e9 one-pixel sun overflowing half floats.
The preview side (NaN-free pixels for degenerate input) is tests/test_preview_stress.py.
"""
import numpy as np
import pytest

from prtt_addon.dev.bench.stress import CASES, T0_MAX, run_case


@pytest.mark.parametrize("name", list(CASES))
def test_stress_case_holds(name, tmp_path):
    r = run_case(name, str(tmp_path))
    assert r["failures"] == [], r
    assert r.get("t0_max", 0.0) <= T0_MAX * (1 + 1e-3) + 1e-4
    if name.startswith("tiny"):
        assert r["bounce_max"] > 65504 and r["bounce_storage"] == ["float"]
        assert any("half-float range" in w for w in r["warnings"])
        assert np.isfinite(r["bounce_dc_min"])
