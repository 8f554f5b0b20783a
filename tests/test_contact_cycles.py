"""Issue 53's contact and leak profiles confirmed with Cycles
(bench/contact_cycles.py): the floor beside a box resting on it and under a
shed of single-plane walls, 3.6 cm texels (56² over 2 m), under a
band-limited World so that the diffuse transfer is exact; Cycles renders the
floor's strip from 2 cm above with no bounce.

The traced transfer at the same points must agree with Cycles (what makes
it the reference of bench contact-profile); the bake without texel validity
shows the dark crease and the bright leak (so the test can fail), the
default bake has neither."""
import numpy as np
import pytest

pytestmark = pytest.mark.blender


def _profiles(kind, samples):
    pytest.importorskip("bpy")
    from prtt_addon.core.bake.pipeline.context import BakeSettings
    from prtt_addon.dev.bench.contact_cycles import cycles_profile
    variants = {k: BakeSettings(rays=256, bounces=0, texel_validity=k == "now") for k in ("before", "now")}
    return cycles_profile(kind, 56, samples=samples, ref_rays=1024, variants=variants)


def test_no_dark_crease_beside_a_box_against_cycles():
    r = _profiles("box", 64)
    traced, before, now = r["traced"]["out"], r["baked"]["before"]["out"], r["baked"]["now"]["out"]
    assert np.abs(traced - 1).max() < 0.02, traced
    assert before[0] < 0.8, before                    # the crease texel validity removes
    assert now.min() >= 0.9 and now.max() <= 1.1, now


def test_no_bright_leak_under_a_single_plane_wall_against_cycles():
    r = _profiles("shed", 128)
    for side in ("inside", "outside"):
        assert np.abs(r["traced"][side] - 1).max() < 0.06, (side, r["traced"][side])
    before, now = r["baked"]["before"]["inside"], r["baked"]["now"]["inside"]
    assert before[0] > 3.0, before                    # light under the wall, 6x
    assert now.max() < 1.3, now
    # What the fix trades for it: the floor just outside takes the darker side's light.
    assert r["baked"]["now"]["outside"][-1] > 0.95
