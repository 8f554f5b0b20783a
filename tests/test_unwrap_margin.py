"""Unwrap leaves room for the bake's coarse bounce grid: under tuning auto no
texel of the 1/2 grid sees two UV islands, so the bounce is baked there
(before, the demo room's Smart UV Project atlas at 4 texels of margin had
3,701 such texels and the bake fell back to the full grid, 1.6x slower)."""
import types

import numpy as np
import pytest

from tests.blender_util import addon_bpy, select_only

pytestmark = pytest.mark.blender


def test_margin_follows_the_bounce_grid_the_bake_asks_for():
    addon_bpy()
    from prtt_addon.blender.scene.uv_maps import bake_downscale, margin_texels
    assert margin_texels(4, 3) == 4 and margin_texels(4, 3, 1) == 4
    assert margin_texels(4, 3, 2) == 6 and margin_texels(8, 3, 2) == 8 and margin_texels(0, 0, 4) == 12
    st = lambda **kw: types.SimpleNamespace(**{"tuning": "AUTO", "bounces": 1, "bounce_downscale": 1, **kw})  # noqa
    assert bake_downscale(st()) == 2
    assert bake_downscale(st(bounces=0)) == 1                       # no bounce: no coarse grid
    assert bake_downscale(st(tuning="FIXED")) == 1
    assert bake_downscale(st(tuning="FIXED", bounce_downscale=4)) == 4
    assert bake_downscale(st(bounce_downscale=4)) == 4


@pytest.mark.parametrize("tuning,mixed", [("AUTO", False), ("FIXED", True)])
def test_demo_room_unwrap_keeps_the_half_grid_island_safe(tuning, mixed):
    bpy = addon_bpy()
    from prtt_addon.blender.scene.uv_maps import _tri_uvs
    from prtt_addon.core.texels.islands import coarse_grid_conflicts
    from prtt_addon.core.texels.raster import rasterize
    from prtt_addon.dev.bench.scene_build import demo_scene
    objects = demo_scene()
    st = bpy.context.scene.prtt
    st.resolution, st.texture_sets, st.unwrap_method, st.tuning = 1024, "ATLAS", "SMART", tuning
    select_only(bpy, list(objects.values()))
    bpy.context.view_layer.objects.active = objects["floor"]
    assert bpy.ops.prtt.unwrap() == {"FINISHED"}
    uv = np.concatenate([_tri_uvs(ob) for ob in objects.values()])
    mask = np.asarray(rasterize(uv, 1024, 1024).mask()).reshape(1024, 1024)
    conflicts = coarse_grid_conflicts(mask, 2)
    # Fixed tuning asks for no coarse grid: the user's 4 texels stay, and the
    # 1/2 grid would mix islands (what auto's margin avoids).
    assert (conflicts > 0) == mixed, conflicts


def test_generated_uvs_do_not_follow_the_bounce_settings():
    """UVs generated at bake time are part of the geometry's hash: their margin
    must not change with bounce settings (a transfer rebake for a bounce change)."""
    addon_bpy()
    from prtt_addon.blender.scene.uv_maps import generated_margin
    st = lambda **kw: types.SimpleNamespace(**{"padding": 4, "dilate": 3, "tuning": "AUTO", "bounces": 1,  # noqa
                                              "bounce_downscale": 1, **kw})
    got = {generated_margin(st(**kw)) for kw in ({}, {"bounces": 0}, {"tuning": "FIXED"}, {"bounce_downscale": 4})}
    assert got == {6}
