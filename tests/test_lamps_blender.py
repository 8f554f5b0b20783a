"""Point and spot lamps against Cycles (issue 49, item 1): the bench's
scene (dev/bench/lamp_cycles.py: a floor, a box and a plank under a dim
band-limited sky) lit by a 10 cm point lamp and a spot, baked by the add-on
in Blender and drawn by its preview, against Cycles' direct light (no
bounce) from the same camera."""
import pytest

pytestmark = pytest.mark.blender


def test_point_and_spot_lamps_match_cycles():
    from tests.blender_util import addon_bpy
    addon_bpy()
    from prtt_addon.dev.bench.lamp_cycles import compare
    r = compare("both", (160, 90), samples=64, resolution=256)
    said = {k: v for k, v in r.items() if k != "images"}
    assert r["lamps"] == ["Spot", "Bulb"], r["notes"]
    assert r["shadow_pixels"] > 300 and r["pixels"] > 4000
    assert r["rel_rmse"] <= 0.02 + 2 * r["cycles_noise"], said
    assert r["rel_rmse_shadow"] <= 0.03 + 2 * r["cycles_noise"], said
    assert abs(r["mean_ratio_minus_1"]) <= 0.01, said


def test_the_lamp_budget_bench_measures_each_lamp():
    """bench lamps --budget at a tiny size: no masks without lamps, one file
    a set with them (bytes growing with the count), their seconds and the
    preview's frame times measured."""
    from tests.blender_util import addon_bpy
    addon_bpy()
    from prtt_addon.dev.bench.lamp_budget import budget
    rows = list(budget(128, counts=(0, 1, 4), size=(64, 36), frames=1))
    assert [r["lamps"] for r in rows] == [0, 1, 4]
    assert rows[0]["mask_bytes"] == 0 and rows[0]["mask_s"] == 0.0
    assert 0 < rows[1]["mask_bytes"] < rows[2]["mask_bytes"] and rows[2]["mask_s"] > 0.0
    assert all(r["tpfl_ms"] > 0 and r["diffuse_ms"] > 0 for r in rows)
