"""The paper's central claim, measured: on a 2-triangle floor the per-fragment
method reproduces the contact shadows of ray-traced ground truth, the
per-vertex baseline cannot (python -m prtt_addon.dev.bench contact makes the
full-size figure in docs/images)."""
import pytest

from tests.blender_util import addon_bpy

pytestmark = pytest.mark.blender


def test_fragment_tpfl_sees_contact_shadows_vertex_tpfl_does_not(tmp_path):
    addon_bpy()
    from prtt_addon.dev.bench.contact import experiment
    res = experiment(160, 108, resolution=128, rays=64, ref_rays=256, dense=8, work_dir=str(tmp_path))
    e = res["errors"]
    assert res["floor_triangles"] == {"coarse": 2, "dense": 128}
    assert res["masks"]["floor"].sum() > 5000
    assert e["fragment"]["floor"] < 0.03
    assert e["fragment"]["floor"] < 0.3 * e["vertex"]["floor"]
    # More floor vertices help the baseline, which is the point: it needs them.
    assert e["vertex_dense"]["floor"] < e["vertex"]["floor"]
