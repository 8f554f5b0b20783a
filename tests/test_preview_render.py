"""The viewport preview's shaders against the numpy reference, pixel by pixel.

Real Blender, real GLSL on Mesa llvmpipe (one tiny Workbench render
initialises the gpu module), offscreen float32 targets. The reference
(core/preview/reference.py) finds each pixel's surface by Embree ray casting
and shades it with core.shading.shade in float64.
"""
import math

import numpy as np
import pytest

from tests.preview_util import baked_blend, open_blend

pytestmark = pytest.mark.blender

W, H = 128, 96
EXPOSURE = 1.3
EDGE_MARGIN_PX = 0.02


@pytest.fixture(scope="module")
def blend(tmp_path_factory):
    return baked_blend(str(tmp_path_factory.mktemp("preview")))


def frame(bpy, bounces=True):
    from prtt_addon.blender.preview.drawlist import collect
    from prtt_addon.blender.preview.offscreen import camera_view, ensure_gpu
    ensure_gpu()
    ps, status = collect(bpy.context, use_bounces=bounces)
    assert ps is not None, status.messages
    dg = bpy.context.evaluated_depsgraph_get()
    vp, cam = camera_view(bpy.context.scene.camera, dg, W, H, bpy.context.scene)
    return ps, status, vp, cam


def test_scene_exercises_every_feature(blend):
    bpy = open_blend(blend)
    ps, status, _, _ = frame(bpy)
    assert [lvl for lvl, _ in status.messages if lvl != "INFO"] == []
    assert sorted(m.name for m in ps.meshes) == ["Ball", "Block", "Floor"]
    floor = next(m for m in ps.meshes if m.name == "Floor")
    assert floor.triangles == 2
    flags = {ps.materials[r[0]].flags for m in ps.meshes for r in m.ranges}
    assert 7 in flags                                   # base texture + roughness texture + normal map
    block = next(m for m in ps.meshes if m.name == "Block")
    assert np.linalg.det(block.matrix[:3, :3]) < 0      # mirrored
    assert all(m.has_vertex_transfer() for m in ps.meshes)
    assert all(s.bounces and s.vertex for s in ps.sets.values())


@pytest.mark.parametrize("bounces", [True, False], ids=["bounce", "direct"])
@pytest.mark.parametrize("mode", ["tpfl", "tp", "diffuse", "vertex-tpfl", "vertex-tp"])
def test_gpu_matches_reference(blend, mode, bounces):
    from prtt_addon.blender.preview.renderer import Renderer, render_offscreen
    from prtt_addon.core.preview.reference import reference_image, relative_error
    bpy = open_blend(blend)
    ps, _, vp, cam = frame(bpy, bounces)
    px, stats = render_offscreen(Renderer(), ps, mode, vp, cam, W, H, exposure=EXPOSURE)
    assert sorted(stats.drawn) == ["Ball", "Block", "Floor"] and not stats.skipped
    assert np.all(np.isfinite(px))
    ref, hits = reference_image(ps, mode, vp, cam, W, H, exposure=EXPOSURE)
    interior = hits.hit & (hits.edge_px > EDGE_MARGIN_PX)
    covered = px[..., 3] > 0.5
    # Visibility: rasterisation agrees with ray casting wherever the pixel centre
    # is not on a triangle edge; background pixels stay background.
    assert np.array_equal(covered[interior], hits.hit[interior])
    assert hits.hit.sum() > 0.3 * W * H
    assert (hits.hit & ~interior).sum() < 0.03 * hits.hit.sum()
    assert (covered & ~hits.hit).sum() <= 0.002 * W * H
    floor = 1e-2 * ref[..., :3][hits.hit].mean()
    err = relative_error(px[..., :3][interior], ref[..., :3][interior], floor)
    assert err.max() <= 1e-3, f"{mode}: max relative error {err.max():.2e} (p99 {np.quantile(err, 0.99):.2e})"


@pytest.fixture(scope="module")
def sun_blend(tmp_path_factory):
    return baked_blend(str(tmp_path_factory.mktemp("preview_sun")), sun=True, bounce_mode="RELIGHTABLE")


@pytest.mark.parametrize("mode", ["tpfl", "tp", "diffuse"])
def test_gpu_matches_reference_with_the_sun(sun_blend, mode):
    """A Sun lamp's direct light (its mask, the GGX highlight on the glossy,
    roughness-textured floor and the metallic ball) and its bounce (the
    relightable bounce relit with its SH projection): the GLSL against the
    numpy twin pixel by pixel, as without the sun; the sun is in the picture
    (the forest World is bright: a twentieth of the pixels 1.2x or more)."""
    from prtt_addon.blender.preview.renderer import Renderer, render_offscreen
    from prtt_addon.core.preview.reference import reference_image, relative_error
    bpy = open_blend(sun_blend)
    ps, _, vp, cam = frame(bpy)
    assert ps.sun is not None and all(s.sun for s in ps.sets.values())
    px, stats = render_offscreen(Renderer(), ps, mode, vp, cam, W, H, exposure=EXPOSURE)
    assert sorted(stats.drawn) == ["Ball", "Block", "Floor"] and not stats.skipped
    ref, hits = reference_image(ps, mode, vp, cam, W, H, exposure=EXPOSURE)
    interior = hits.hit & (hits.edge_px > EDGE_MARGIN_PX)
    floor = 1e-2 * ref[..., :3][hits.hit].mean()
    err = relative_error(px[..., :3][interior], ref[..., :3][interior], floor)
    assert err.max() <= 1e-3, f"{mode}: max relative error {err.max():.2e} (p99 {np.quantile(err, 0.99):.2e})"
    import dataclasses
    dark, _ = reference_image(dataclasses.replace(ps, sun=None), mode, vp, cam, W, H, exposure=EXPOSURE)
    gain = ref[..., :3][interior].sum(axis=1) / np.maximum(dark[..., :3][interior].sum(axis=1), 1e-9)
    more = ref[..., :3][interior].mean() / dark[..., :3][interior].mean()
    assert more > 1.05 and np.quantile(gain, 0.95) > 1.2, (more, np.quantile(gain, 0.95))


@pytest.fixture(scope="module")
def lamp_blend(tmp_path_factory):
    return baked_blend(str(tmp_path_factory.mktemp("preview_lamps")), lamps=True, bounces=0)


@pytest.mark.parametrize("mode", ["tpfl", "diffuse"])
def test_gpu_matches_reference_with_lamps(lamp_blend, mode):
    """A point and a spot lamp's direct light (their masks, the spot's cone,
    the glossy floor's and the ball's highlights): the GLSL against the numpy
    twin pixel by pixel; the lamps are in the picture and a recoloured lamp
    changes it without a bake."""
    import dataclasses

    from prtt_addon.blender.preview.renderer import Renderer, render_offscreen
    from prtt_addon.core.preview.reference import reference_image, relative_error
    bpy = open_blend(lamp_blend)
    ps, status, vp, cam = frame(bpy, False)
    assert [lp.name for lp in ps.lamps] == ["Spot", "Bulb"] and all(s.lamps for s in ps.sets.values()), status.messages
    assert "Spot 'Spot'" in status.lamps_description
    r = Renderer()
    for p in (ps, dataclasses.replace(ps, lamps=(dataclasses.replace(ps.lamps[0], color=(1.0, 0.1, 0.1)),
                                                   ps.lamps[1]))):
        px, stats = render_offscreen(r, p, mode, vp, cam, W, H, exposure=EXPOSURE)
        assert sorted(stats.drawn) == ["Ball", "Block", "Floor"] and not stats.skipped
        ref, hits = reference_image(p, mode, vp, cam, W, H, exposure=EXPOSURE)
        interior = hits.hit & (hits.edge_px > EDGE_MARGIN_PX)
        floor = 1e-2 * ref[..., :3][hits.hit].mean()
        err = relative_error(px[..., :3][interior], ref[..., :3][interior], floor)
        assert err.max() <= 1e-3, f"{mode}: max relative error {err.max():.2e} (p99 {np.quantile(err, 0.99):.2e})"
    dark, _ = reference_image(dataclasses.replace(ps, lamps=()), mode, vp, cam, W, H, exposure=EXPOSURE)
    lit, _ = reference_image(ps, mode, vp, cam, W, H, exposure=EXPOSURE)
    gain = lit[..., :3][interior].sum(axis=1) / np.maximum(dark[..., :3][interior].sum(axis=1), 1e-9)
    assert np.quantile(gain, 0.9) > 1.3 and np.quantile(gain, 0.1) < 1.05, np.quantile(gain, [0.1, 0.9])


def test_lamps_change_live_and_go_stale_when_moved(lamp_blend):
    """Power and colour are drawn as they are now (no warning); a moved lamp
    keeps its baked place and says its shadows are stale; a hidden lamp is
    drawn dark and named; a new Point lamp is named as not in the bake."""
    bpy = open_blend(lamp_blend)
    bulb = bpy.data.objects["Bulb"]
    bulb.data.energy, bulb.data.color = 40.0, (0.2, 1.0, 0.2)
    ps, status, _, _ = frame(bpy, False)
    lp = next(x for x in ps.lamps if x.name == "Bulb")
    assert lp.power == pytest.approx(40.0) and lp.color == pytest.approx((0.2, 1.0, 0.2)) and not status.lamps_stale
    baked = lp.position
    bulb.location.x += 0.3
    bpy.context.view_layer.update()
    ps, status, _, _ = frame(bpy, False)
    assert "the lamp 'Bulb' moved 0.3 m" in status.lamps_stale
    assert next(x for x in ps.lamps if x.name == "Bulb").position == baked
    assert any("lamps' shadows are stale" in t for _, t in status.messages)
    bulb.hide_render = True
    new = bpy.data.objects.new("Extra", bpy.data.lights.new("Extra", "POINT"))
    bpy.context.scene.collection.objects.link(new)
    bpy.context.view_layer.update()
    ps, status, _, _ = frame(bpy, False)
    assert next(x for x in ps.lamps if x.name == "Bulb").power == 0.0
    text = " ".join(t for _, t in status.messages)
    assert "gone from the scene" in text and "'Bulb'" in text and "not in the bake: 'Extra'" in text


def test_tp_equals_tpfl_and_prepass_changes_nothing(blend):
    from prtt_addon.blender.preview.renderer import Renderer, render_offscreen
    bpy = open_blend(blend)
    ps, _, vp, cam = frame(bpy)
    r = Renderer()
    tpfl, _ = render_offscreen(r, ps, "tpfl", vp, cam, W, H)
    tp, _ = render_offscreen(r, ps, "tp", vp, cam, W, H)
    no_pre, _ = render_offscreen(r, ps, "tpfl", vp, cam, W, H, prepass=False)
    scale = tpfl[..., :3].max()
    assert np.abs(tp - tpfl).max() <= 1e-5 * scale
    np.testing.assert_array_equal(no_pre, tpfl)


def test_bounces_add_light_and_vertex_modes_miss_the_contact_shadow(blend):
    from prtt_addon.blender.preview.renderer import Renderer, render_offscreen
    from prtt_addon.core.preview.reference import trace_pixels
    bpy = open_blend(blend)
    ps, _, vp, cam = frame(bpy)
    r = Renderer()
    ps_direct, _, _, _ = frame(bpy, bounces=False)
    # Diffuse: the bounce's DC terms are >= 0, so bounce light only adds light.
    # (Glossy lobes of band-limited bounce light may ring slightly below zero.)
    d_with, _ = render_offscreen(r, ps, "diffuse", vp, cam, W, H)
    d_direct, _ = render_offscreen(r, ps_direct, "diffuse", vp, cam, W, H)
    hit = d_with[..., 3] > 0.5
    assert (d_with - d_direct)[..., :3][hit].min() >= -1e-6 * d_with.max()
    with_b, _ = render_offscreen(r, ps, "tpfl", vp, cam, W, H)
    direct, _ = render_offscreen(r, ps_direct, "tpfl", vp, cam, W, H)
    extra = (with_b - direct)[..., :3][hit]
    assert extra.mean() > 0.01 * direct[..., :3][hit].mean()
    # Floor pixels: the fragment method sees the shadows under the ball and the
    # block, the 4 vertices of the floor cannot.
    hits = trace_pixels(ps, vp, W, H)
    k = [m.name for m in ps.meshes].index("Floor")
    on_floor = (hits.mesh == k) & (hits.edge_px > EDGE_MARGIN_PX)
    vert, _ = render_offscreen(r, ps_direct, "vertex-tpfl", vp, cam, W, H)
    lum = lambda a: a[..., :3].mean(axis=-1)        # noqa: E731
    # The contact shadows: floor pixels whose transfer's DC is under 20 % of
    # the floor's most open (its 95th percentile): geometry, not shading.
    from prtt_addon.core.preview.reference import _interp, _texture_pm, bilinear
    floor = ps.meshes[k]
    transfer = ps.sets[floor.set_name].load_transfer()
    uv = _interp(floor.uv[floor.indices].astype(np.float64), hits.tri[on_floor], hits.bary[on_floor])
    dc = np.zeros((H, W))
    dc[on_floor] = bilinear(_texture_pm(transfer), transfer.shape[1], transfer.shape[0], uv)[:, 0]
    dark = on_floor & (dc < 0.2 * np.percentile(dc[on_floor], 95))
    assert dark.sum() > 20
    assert np.median(lum(direct)[dark]) < 0.6 * np.median(lum(direct)[on_floor & ~dark])  # the shadow is there per fragment...
    # The 4 vertices' colours are bilinear over the floor: against them, the
    # fragments are darker in the contacts than elsewhere (0.70 of it).
    q = lum(direct) / np.maximum(lum(vert), 1e-6)
    assert np.median(q[dark]) < 0.8 * np.median(q[on_floor & ~dark])     # ...and not per vertex


def test_world_rotation_is_an_sh_rotation_of_a_cached_projection(blend):
    """Turning the environment must not re-project it, and must equal an
    independent projection of the turned image (90 deg = a quarter roll)."""
    from prtt_addon.blender.preview import drawlist as preview_scene
    from prtt_addon.core.io.image_io import read_hdr_image
    from prtt_addon.core.light import envmap
    bpy = open_blend(blend)
    scene = bpy.context.scene
    mapping = next(n for n in scene.world.node_tree.nodes if n.bl_idname == "ShaderNodeMapping")
    strength = scene.world.node_tree.nodes["Background"].inputs["Strength"].default_value
    mapping.inputs["Rotation"].default_value[2] = 0.0
    L0, _ = preview_scene.current_light(scene, 5)
    cached = len(preview_scene._PROJECTIONS)
    mapping.inputs["Rotation"].default_value[2] = math.pi / 2
    L90, _ = preview_scene.current_light(scene, 5)
    assert len(preview_scene._PROJECTIONS) == cached
    img = read_hdr_image(envmap.builtin_environment_path("forest"))
    assert img.shape[1] % 4 == 0
    # Lookups turn by +90 deg: u(phi + 90 deg) = u(phi) - 1/4, so the seen image is rolled right.
    want = envmap.project_equirect(np.roll(img, img.shape[1] // 4, axis=1), 5) * strength
    # Blender stores the angle in float32 (pi/2 + 4.4e-8): that, times |L| and l, is the tolerance.
    np.testing.assert_allclose(L90, want, rtol=0, atol=1e-6 * np.abs(want).max())
    assert np.abs(L90 - L0).max() > 0.05 * np.abs(L0).max()


def test_stale_and_moved_warnings(blend):
    from prtt_addon.blender.preview.drawlist import collect
    bpy = open_blend(blend)
    scene = bpy.context.scene

    def warnings():
        _, status = collect(bpy.context, with_meshes=False)
        return " | ".join(t for lvl, t in status.messages if lvl == "WARNING")

    assert warnings() == ""
    bg = scene.world.node_tree.nodes["Background"]
    bg.inputs["Strength"].default_value = 2.0
    assert "the World light changed" in warnings()
    bg.inputs["Strength"].default_value = 1.5
    assert warnings() == ""
    mat = bpy.data.materials["BallMat"]
    mat.node_tree.nodes["Principled BSDF"].inputs["Roughness"].default_value = 0.9
    bpy.context.view_layer.update()
    assert "materials changed" in warnings()
    mat.node_tree.nodes["Principled BSDF"].inputs["Roughness"].default_value = 0.35
    bpy.context.view_layer.update()
    assert warnings() == ""
    bpy.data.objects["Ball"].location.x += 0.5
    bpy.context.view_layer.update()
    w = warnings()
    assert "moved since the bake" in w and "Ball" in w


def test_viewport_draw_path_and_resources(blend):
    """draw_view (what the POST_VIEW handler runs) draws the same picture as
    the offscreen render; GPU resources go when their objects go."""
    import gpu

    from prtt_addon.blender.preview import draw as preview_draw
    from prtt_addon.blender.preview.colour_management import display_of
    from prtt_addon.blender.preview.renderer import Renderer, read_pixels, render_offscreen
    from prtt_addon.core.io.image_write import srgb_encode
    bpy = open_blend(blend)
    assert preview_draw._HANDLE is None                       # background mode: no draw handler
    assert preview_draw._on_depsgraph in bpy.app.handlers.depsgraph_update_post   # survived the load
    ps, _, vp, cam = frame(bpy)
    want, _ = render_offscreen(Renderer(), ps, "tpfl", vp, cam, W, H)

    class RegionData:       # what a 3D viewport's region_data provides
        perspective_matrix = vp
        view_matrix = np.linalg.inv(np.array(bpy.context.scene.camera.matrix_world))
        is_perspective = True

    scene = bpy.context.scene
    scene.prtt.preview, scene.prtt.preview_mode = True, "TPFL"

    def draw():
        off = gpu.types.GPUOffScreen(W, H, format="RGBA32F")
        with off.bind():
            fb = gpu.state.active_framebuffer_get()
            fb.clear(color=(0, 0, 0, 0), depth=1.0)
            stats = preview_draw.draw_view(bpy.context, RegionData())
            got = read_pixels(fb, W, H)
        off.free()
        return stats, got

    scene.view_settings.view_transform = "Standard"       # linear out: the colour buffer encodes sRGB
    stats, got = draw()
    assert sorted(stats.drawn) == ["Ball", "Block", "Floor"]
    assert np.abs(got - want).max() <= 1e-5 * want.max()
    # AgX (the scene's own view transform): what the buffer stores is the table's encode of the same frame
    scene.view_settings.view_transform = "AgX"
    _, shown = draw()
    table = display_of(scene)
    covered = want[..., 3] > 0.5
    stored = srgb_encode(shown[covered][:, :3])
    assert np.abs(stored - table.encode(want[covered][:, :3])).max() * 255 < 1.0
    r = Renderer()
    render_offscreen(r, ps, "tpfl", vp, cam, W, H)
    keys = r.resource_keys()
    assert any(k[0] == "mesh" and "Ball" in k[1] for k in keys)
    ps.meshes = [m for m in ps.meshes if m.name != "Ball"]
    ps.sets = {k: v for k, v in ps.sets.items() if k != "Ball"}
    render_offscreen(r, ps, "tpfl", vp, cam, W, H)
    keys = r.resource_keys()
    assert not any(k[0] == "mesh" and "Ball" in k[1] for k in keys)
    assert not any(k[0] == "transfer" and "Ball.transfer" in k[1] for k in keys)


@pytest.fixture(scope="module")
def relit_blend(tmp_path_factory):
    return baked_blend(str(tmp_path_factory.mktemp("preview-relit")), bounce_mode="RELIGHTABLE")


@pytest.mark.parametrize("mode", ["tpfl", "diffuse"])
def test_relightable_bounces_follow_the_world(relit_blend, mode):
    """Relightable bounces: a turned or brighter World is no staleness, the
    frame follows it, and the GPU still matches the reference pixel by pixel
    (its bounce light under the World as it is now); a material change is."""
    from prtt_addon.blender.preview.drawlist import collect
    from prtt_addon.blender.preview.renderer import Renderer, render_offscreen
    from prtt_addon.core.preview.reference import reference_image, relative_error
    bpy = open_blend(relit_blend)
    scene = bpy.context.scene

    def warnings():
        _, status = collect(bpy.context, with_meshes=False)
        return " | ".join(t for lvl, t in status.messages if lvl == "WARNING")

    ps, _, _, _ = frame(bpy)
    assert all(s.relight and not s.bounces for s in ps.sets.values())
    # Tuning auto's shared glossy rows: the relight pass tints them on the GPU
    # (RELIGHT_SHARED), the reference expands them on the CPU.
    from prtt_addon.core.io.exr_io import open_sh_channels
    shared = []
    for s in ps.sets.values():
        with open_sh_channels(s.relight) as (_, attrs):
            shared.append(attrs.get("glossy_colour") == "shared")
    assert any(shared)
    renderer = Renderer()
    images = []
    for turn in (0.0, math.pi / 2):
        mapping = next(n for n in scene.world.node_tree.nodes if n.bl_idname == "ShaderNodeMapping")
        mapping.inputs["Rotation"].default_value[2] = 0.6 + turn
        scene.world.node_tree.nodes["Background"].inputs["Strength"].default_value = 1.5 + turn
        assert warnings() == ""
        ps, _, vp, cam = frame(bpy)
        px, stats = render_offscreen(renderer, ps, mode, vp, cam, W, H, exposure=EXPOSURE)
        assert sorted(stats.drawn) == ["Ball", "Block", "Floor"] and not stats.skipped
        ref, hits = reference_image(ps, mode, vp, cam, W, H, exposure=EXPOSURE)
        interior = hits.hit & (hits.edge_px > EDGE_MARGIN_PX)
        floor = 1e-2 * ref[..., :3][hits.hit].mean()
        err = relative_error(px[..., :3][interior], ref[..., :3][interior], floor)
        assert err.max() <= 1e-3, f"{mode}: max relative error {err.max():.2e}"
        images.append(px)
        # Without its bounce light the frame is darker: the relit bounce is drawn.
        ps_direct, _, _, _ = frame(bpy, bounces=False)
        direct, _ = render_offscreen(renderer, ps_direct, mode, vp, cam, W, H, exposure=EXPOSURE)
        assert px[..., :3][interior].mean() > 1.01 * direct[..., :3][interior].mean()
    assert np.abs(images[1] - images[0]).max() > 0.05
    mat = bpy.data.materials["BallMat"]
    mat.node_tree.nodes["Principled BSDF"].inputs["Roughness"].default_value = 0.9
    bpy.context.view_layer.update()
    assert "materials changed" in warnings()
