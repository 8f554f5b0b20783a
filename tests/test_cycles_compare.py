"""PRTT's diffuse preview against Cycles, an independent renderer (bench/cycles_compare.py).

Small settings (160x90, 2 x 32 spp, 256^2 atlas, 128 rays) so it runs in
seconds; the full-size numbers are in docs/benchmarks.md. Under a band-limited
light the diffuse PRT integral is exact, so the only differences allowed are
Cycles' own noise, PRTT's ray noise and texture sampling: the mean over the
image within 1 %, every large object within 3 %, and the per-pixel RMSE within
Cycles' measured noise plus 3 %.
"""
import math

import pytest


@pytest.mark.parametrize("bounces, mode, turn", [(0, "baked", 0.0), (1, "relightable", 120.0)],
                         ids=["direct", "relit-bounce-world-turned"])
def test_diffuse_prtt_matches_cycles_under_band_limited_light(tmp_path, bounces, mode, turn):
    """Direct light; and one bounce baked relightable, the World turned by 120
    degrees after the bake (Cycles renders the turned World, PRTT relights)."""
    pytest.importorskip("bpy")
    from prtt_addon.dev.bench.cycles_compare import compare
    r = compare((160, 90), samples=32, resolution=256, rays=128, bounces=bounces, work_dir=str(tmp_path),
                bounce_mode=mode, turn=turn)
    assert r["pixels_compared"] > 5000
    assert abs(r["mean_ratio_minus_1"]) < 0.01, r["mean_ratio_minus_1"]
    assert r["per_object_mean_ratio_minus_1"], "no object had enough pixels"
    for name, v in r["per_object_mean_ratio_minus_1"].items():
        assert abs(v) < 0.03, (name, v)
    noise = r["cycles_noise_rel_rmse_of_mean"]
    assert r["rel_rmse"] < math.hypot(noise, 0.03), (r["rel_rmse"], noise)
