"""The bake's stages called alone (core/bake/{context,plan,stages,bounce_stage}.py)
give what bake_scene writes; the context declares every field it holds."""
import dataclasses
import os

import numpy as np
import pytest

from prtt_addon.core.bake.pipeline import bounce_stage, stages
from prtt_addon.core.bake.pipeline.context import BakeContext, BakeSettings
from prtt_addon.core.bake.pipeline.plan import plan_bake
from prtt_addon.core.bake.pipeline.runner import bake_scene, check_out_dir
from prtt_addon.core.io import exr_io
from prtt_addon.dev.bench import meshgen as mg
from tests.scenes_util import floor_and_box, planar_uvs, scene_from
from tests.test_bounce import corner_scene, sky


@pytest.fixture
def context():
    made = []

    def make(*args, **kw):
        ctx = BakeContext.create(*args, **kw)
        made.append(ctx)
        return ctx
    yield make
    for ctx in made:
        ctx.staging.abort()
        ctx.close()


def planes_of(path):
    data, attrs = exr_io.read_sh_exr(path)
    return np.moveaxis(data, 2, 0), attrs


def island_scene(res=24):
    """A floor whose UV island leaves an empty border (dilation fills it), with a box on it."""
    f = mg.plane(4.0)
    b = mg.box((1.0, 1.0, 1.0), (0, 0, 0.5))
    return scene_from([("floor", f, planar_uvs(f) * 0.5 + 0.25), ("box", b, mg.box_face_uvs(b))], res)


def test_geometry_gbuffer_trace_projection_give_the_written_texture(tmp_path, context):
    sc = island_scene(24)
    # The stages below transfer_set: texel validity and the guided texels'
    # filter are transfer_set's own steps (tests/test_contact_profile.py,
    # tests/test_guided_filter.py).
    st = BakeSettings(rays=32, half=False, mips=True, threads=2, texel_validity=False,
                      guided_filter=False).validate()
    m = bake_scene(sc, tmp_path / "full", st)
    ctx = context(sc, check_out_dir(tmp_path / "alone"), st)
    geo = stages.build_geometry(ctx)
    T = sc.n_triangles
    assert geo.face_normal.shape == (T, 3) and geo.normal_group.shape == (T,) and geo.clear.dtype == bool
    floor = sc.set_names.index("floor")
    gb = stages.gbuffer_stage(ctx, floor)
    assert stages.check_gbuffer(ctx, gb)["name"] == "floor" and ctx.warnings == []
    assert 0 < gb.n < 24 * 24
    traced = stages.trace_set(ctx, geo, gb)
    assert traced.rows.shape == (gb.n, 25) and traced.rows.dtype == np.float32
    assert traced.info["rays_traced"] == m["sets"][floor]["rays_traced"] > 0
    sp = stages.project_rows(ctx, traced, keep_rows=False)
    assert traced.rows is None and traced.points is None and gb.position is None      # released
    assert sp.planes.shape == (25, 24, 24) and sp.mask.sum() == gb.n
    assert not sp.planes[:, ~sp.mask].any()                     # undilated: zero off the texels
    stages.mip_and_dilate(ctx, sp, gb)
    want, attrs = planes_of(tmp_path / "full" / "floor.transfer.exr")
    assert attrs["storage"] == "float"
    assert sp.planes[:, ~sp.mask].any()                          # dilated into the border
    np.testing.assert_array_equal(sp.planes, want)
    assert len(sp.mips) == 5                                    # 12, 6, 3, 2, 1 texels
    for level, (mt, _) in enumerate(sp.mips, start=1):
        np.testing.assert_array_equal(mt, planes_of(tmp_path / "full" / f"floor.transfer.mip{level}.exr")[0])
    # Writing stages temporaries only; nothing has a final name before the commit.
    plan = plan_bake(ctx)
    written = stages.write_set(ctx, plan, gb, sp, traced.info)
    assert written.files[0] == "floor.transfer.exr" and written.half is False
    names = os.listdir(tmp_path / "alone")
    assert len(names) == 6 and all(n.startswith(".prtt-tmp-") for n in names)
    ctx.staging.abort()
    assert os.listdir(tmp_path / "alone") == []


def test_bounce_stage_from_the_transfer_on_disk_matches_the_full_bake(tmp_path, context):
    """What a bounce-only worker would do: G-buffers, the transfer read back,
    the bounce levels; the same textures as the bake that traced them."""
    sc = corner_scene({"name": "w", "base_color": [0.8, 0.4, 0.2], "specular": 0.0}, res=16)
    st = BakeSettings(rays=32, bounces=2, bounce_rays=16, bounce_tolerance=0.0, half=False,
                      threads=2, bounce_mode="baked").validate()
    m = bake_scene(sc, tmp_path, st, light=sky())
    ctx = context(sc, str(tmp_path), st, light=sky())
    plan = plan_bake(ctx)
    assert plan.skipped and plan.bounce_key == m["bounce"]["key"] and plan.input_hash == m["input_hash"]
    geo = stages.build_geometry(ctx)
    sources = []
    for s in ctx.set_ids:
        gb = stages.gbuffer_stage(ctx, s)
        sources.append(stages.load_transfer_set(ctx, geo, gb, {}).bounce)
    held = list(sources)
    result = bounce_stage.bounce_levels(ctx, geo, plan, sources)
    assert all(src.incident is None for src in held)           # dropped once level 1 is lit
    assert sources == [None] * len(held)                       # and the list consumed
    assert result.files == m["bounce"]["files"] and len(result.files) == 4 and result.stopped is None
    staged = {os.path.basename(final): tmp for tmp, final in ctx.staging.files}
    for name in result.files:
        got, _ = planes_of(staged[name])
        want, _ = planes_of(tmp_path / name)
        np.testing.assert_array_equal(got, want)
    strip = lambda r: {k: v for k, v in r.items() if k != "seconds"}  # noqa: E731
    assert [strip(r) for r in result.reports] == [strip(r) for r in m["bounce"]["sets"]]


def test_plan_reuse_decisions(tmp_path, context):
    sc = corner_scene({"name": "w", "base_color": [0.6, 0.6, 0.6]}, res=8)
    st = BakeSettings(rays=16, bounces=1, bounce_rays=8, bounce_mode="baked").validate()
    bake_scene(sc, tmp_path, st, light=sky())

    default_light = sky()

    def plan(settings=st, light=default_light, **kw):
        return plan_bake(context(sc, str(tmp_path), settings, light=light), **kw)

    p = plan()
    assert (p.transfer_reused, p.bounce_reused, p.skipped) == (True, True, True)
    p = plan(light=1.5 * sky())                                  # bounce-only re-bake
    assert (p.transfer_reused, p.bounce_reused, p.bouncing) == (True, False, True)
    p = plan(settings=dataclasses.replace(st, rays=32))
    assert (p.transfer_reused, p.bounce_reused) == (False, False)
    p = plan(skip_if_unchanged=False)
    assert (p.transfer_reused, p.bounce_reused) == (False, False)
    ctx = context(sc, str(tmp_path), st)                         # no light: no bounces, old ones go
    p = plan_bake(ctx)
    assert not p.bouncing and p.bounce_key is None and not p.bounce_reused and p.transfer_reused
    assert ctx.warnings == ["no light given: bounce textures (which bake the light in) are skipped"]
    assert plan().exr_attrs(st) == {"rays": 16, "seed": st.seed, "sampler": st.sampler,
                                    "estimator": st.estimator, "input_hash": p.input_hash}


def test_context_declares_every_field(tmp_path, context):
    sc = floor_and_box(res=8)
    ctx = context(sc, str(tmp_path), BakeSettings(rays=16).validate(), light=sky(), sets=["box"])
    assert ctx.set_ids == [1] and ctx.light.shape == (25, 3) and ctx.n_coeffs == 25
    assert not hasattr(ctx, "__dict__")
    with pytest.raises(AttributeError):
        ctx.rs = None                                            # what the old _Bake took from outside
    with pytest.raises(AttributeError):
        ctx.light_hash = "x"
    stages.start_tables(ctx)                                     # a declared field, set by its stage
    ctx.wait_tables()
    assert ctx.tables.done()
    events = []
    ctx.progress = events.append
    ctx.warn("w")
    assert ctx.warnings == ["w"] and events == [{"type": "warning", "message": "w"}]
    with pytest.raises(Exception, match="unknown texture sets"):
        BakeContext.create(sc, str(tmp_path), BakeSettings(), sets=["nope"])
