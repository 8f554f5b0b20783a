"""Any World as the light (issue 48, item 1): node trees PRTT does not read
directly are rendered by Cycles as an equirectangular panorama
(blender/scene/world_panorama.py) and projected like an HDRI."""
import numpy as np
import pytest

from prtt_addon.core.light import envmap
from tests.blender_util import fresh_bpy

pytestmark = pytest.mark.blender


def _world(bpy, name="W"):
    w = bpy.data.worlds.new(name)
    if bpy.app.version < (5, 0, 0):
        w.use_nodes = True
    bpy.context.scene.world = w
    return w, w.node_tree, w.node_tree.nodes["Background"]


def test_an_hdri_behind_a_node_prtt_does_not_read_gives_the_hdris_light():
    """The forest HDRI through a Gamma node of gamma 1 (an identity PRTT does
    not parse): the panorama Cycles renders projects to the SH of the image
    itself within 1 % (orientation, scale and the pixels' areas) at 5 and at
    16 bands, and the light says how it was made."""
    from prtt_addon.blender.scene.world import world_light
    bpy = fresh_bpy()
    w, nt, bg = _world(bpy)
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.image = bpy.data.images.load(envmap.builtin_environment_path("forest"))
    gamma = nt.nodes.new("ShaderNodeGamma")
    gamma.inputs["Gamma"].default_value = 1.0
    nt.links.new(env.outputs["Color"], gamma.inputs["Color"])
    nt.links.new(gamma.outputs["Color"], bg.inputs["Color"])
    bg.inputs["Strength"].default_value = 1.5
    light, desc = world_light(bpy.context.scene, 5)
    want = 1.5 * envmap.project_equirect(envmap.builtin_environment_path("forest"), 5)
    rel = np.linalg.norm(light - want) / np.linalg.norm(want)
    print(f"panorama vs the image's own SH: {rel:.3%}")
    assert rel < 0.01, rel
    assert "rendered by Cycles" in desc and "Gamma" in desc, desc
    # Band 16 (the most PRTT bakes): 0.37 % in all, 0.84 % in band 16 alone.
    L16, _ = world_light(bpy.context.scene, 16)
    want16 = 1.5 * envmap.project_equirect(envmap.builtin_environment_path("forest"), 16)
    assert np.linalg.norm(L16 - want16) / np.linalg.norm(want16) < 0.01
    top = slice(15 ** 2, 16 ** 2)
    assert np.linalg.norm(L16[top] - want16[top]) / np.linalg.norm(want16[top]) < 0.02


def test_a_sky_texture_lights_a_plane_as_cycles_does(tmp_path):
    """A Sky Texture World (Blender's default sky, sun 30 degrees up): the
    irradiance PRTT's light gives an open up-facing plane against Cycles'
    render of a white diffuse plane under the same World (orthographic camera
    straight down, Standard view, linear EXR): radiance = albedo E / pi within 3 %."""
    from prtt_addon.blender.scene.world import world_light
    from prtt_addon.core.bake.estimators.transfer import unoccluded_transfer
    from prtt_addon.core.io.image_io import read_hdr_image
    bpy = fresh_bpy()
    sc = bpy.context.scene
    w, nt, bg = _world(bpy, "Sky")
    sky = nt.nodes.new("ShaderNodeTexSky")
    if hasattr(sky, "sun_elevation"):
        sky.sun_elevation = np.radians(30.0)
    nt.links.new(sky.outputs["Color"], bg.inputs["Color"])
    bg.inputs["Strength"].default_value = 0.2
    from prtt_addon.blender.scene import lamps, world_panorama
    from prtt_addon.core.light.envmap import project_equirect
    light, desc = world_light(sc, 5)
    assert "Sky Texture" in desc and "its sun disc is the sun" in desc, desc
    up = unoccluded_transfer(np.array([[0.0, 0.0, 1.0]]), 5)
    # the sky's SH without its disc, and its disc as the bake's sun (direct light on the plane)
    sun = lamps.scene_sun(sc)[0]
    E = float((up @ light).mean() + sun.irradiance.mean() * max(sun.direction[2], 0.0))
    # the old way (Sky Sun off): the disc's energy in the SH
    E_sh = float((up @ project_equirect(world_panorama.panorama(w, disc=True), 5)).mean())
    # Cycles: a white (0.8) diffuse plane seen from straight above.
    bpy.ops.mesh.primitive_plane_add(size=2.0)
    mat = bpy.data.materials.new("White")
    if bpy.app.version < (5, 0, 0):
        mat.use_nodes = True
    bsdf = mat.node_tree.nodes.get("Principled BSDF")
    bsdf.inputs["Base Color"].default_value = (0.8, 0.8, 0.8, 1.0)
    bsdf.inputs["Roughness"].default_value = 1.0
    bsdf.inputs["Specular IOR Level"].default_value = 0.0
    bpy.context.object.data.materials.append(mat)
    cam_data = bpy.data.cameras.new("Top")
    cam_data.type = "ORTHO"
    cam_data.ortho_scale = 1.0
    cam = bpy.data.objects.new("Top", cam_data)
    sc.collection.objects.link(cam)
    cam.location = (0.0, 0.0, 3.0)
    sc.camera = cam
    sc.render.engine = "CYCLES"
    sc.cycles.samples = 512
    sc.cycles.use_denoising = False
    sc.render.resolution_x = sc.render.resolution_y = 16
    sc.render.resolution_percentage = 100
    sc.view_settings.view_transform = "Standard"
    sc.render.image_settings.file_format = "OPEN_EXR"
    sc.render.filepath = str(tmp_path / "plane.exr")
    bpy.ops.render.render(write_still=True)
    got = float(read_hdr_image(str(tmp_path / "plane.exr")).mean())
    want, want_sh = 0.8 * E / np.pi, 0.8 * E_sh / np.pi
    print(f"Cycles {got:.5f}, PRTT's light {want:.5f}: {want / got - 1:+.2%} (the disc in the SH: "
          f"{want_sh / got - 1:+.2%})")
    assert abs(want / got - 1) < 0.03, (want, got)
    assert abs(want_sh / got - 1) < 0.03, (want_sh, got)


def test_the_panorama_is_rendered_once_per_change():
    """The viewport asks for the light at every redraw: the same tree renders
    once; a changed setting renders again (a new key)."""
    from prtt_addon.blender.scene import world_panorama
    from prtt_addon.blender.scene.world import project_setup, world_setup
    bpy = fresh_bpy()
    w, nt, bg = _world(bpy, "Gradient")
    grad = nt.nodes.new("ShaderNodeTexGradient")
    nt.links.new(grad.outputs["Color"], bg.inputs["Color"])
    sc = bpy.context.scene
    first = world_setup(sc)
    a = project_setup(first, 3)
    n = world_panorama.renders
    again = world_setup(sc)
    b = project_setup(again, 3)
    assert again.key == first.key and world_panorama.renders == n and np.array_equal(a, b)
    bg.inputs["Strength"].default_value = 2.0
    changed = world_setup(sc)
    c = project_setup(changed, 3)
    assert changed.key != first.key and world_panorama.renders == n + 1
    assert np.allclose(c, 2.0 * a, rtol=1e-3, atol=1e-6)


def test_the_panoramas_key_follows_ramps_curves_and_nothing_cosmetic():
    """A gradient sky (Gradient Texture -> Color Ramp -> Background): the key
    changes with a ramp stop's colour or position and with a curve point, not
    when a node is moved or renamed in the editor."""
    from prtt_addon.blender.scene import world_panorama
    bpy = fresh_bpy()
    w, nt, bg = _world(bpy, "Gradient sky")
    grad = nt.nodes.new("ShaderNodeTexGradient")
    ramp = nt.nodes.new("ShaderNodeValToRGB")
    curves = nt.nodes.new("ShaderNodeRGBCurve")
    nt.links.new(grad.outputs["Fac"], ramp.inputs["Fac"])
    nt.links.new(ramp.outputs["Color"], curves.inputs["Color"])
    nt.links.new(curves.outputs["Color"], bg.inputs["Color"])
    keys = [world_panorama.world_digest(w)]
    ramp.location = (500.0, 300.0)
    ramp.label = "sky colours"
    assert world_panorama.world_digest(w) == keys[0]
    ramp.color_ramp.elements[1].color = (0.2, 0.4, 1.0, 1.0)
    keys.append(world_panorama.world_digest(w))
    ramp.color_ramp.elements[1].position = 0.7
    keys.append(world_panorama.world_digest(w))
    curves.mapping.curves[3].points[0].location = (0.0, 0.2)
    keys.append(world_panorama.world_digest(w))
    assert len(set(keys)) == 4, keys


def test_a_light_path_node_and_a_missing_image_are_refused_in_one_line():
    from prtt_addon.blender.scene.world import WorldLightError, world_light
    bpy = fresh_bpy()
    w, nt, bg = _world(bpy, "Backdrop")
    lp = nt.nodes.new("ShaderNodeLightPath")
    mix = nt.nodes.new("ShaderNodeMix")
    mix.data_type = "RGBA"
    nt.links.new(lp.outputs["Is Camera Ray"], mix.inputs["Factor"])
    nt.links.new(mix.outputs["Result"], bg.inputs["Color"])
    with pytest.raises(WorldLightError, match="Light Path node .* as a camera sees it"):
        world_light(bpy.context.scene, 3)
    w2, nt2, bg2 = _world(bpy, "Missing")
    env = nt2.nodes.new("ShaderNodeTexEnvironment")
    img = bpy.data.images.new("sky", 4, 4, float_buffer=True)
    img.source, img.filepath = "FILE", "/nonexistent/sky.exr"
    env.image = img
    inv = nt2.nodes.new("ShaderNodeInvert")
    nt2.links.new(env.outputs["Color"], inv.inputs["Color"])
    nt2.links.new(inv.outputs["Color"], bg2.inputs["Color"])
    with pytest.raises(WorldLightError, match="has no pixels"):
        world_light(bpy.context.scene, 3)
    # The same missing image in a node that feeds nothing does not refuse the World.
    grad = nt2.nodes.new("ShaderNodeTexGradient")
    nt2.links.new(grad.outputs["Color"], bg2.inputs["Color"])       # replaces the Invert's link
    L, desc = world_light(bpy.context.scene, 3)
    assert "rendered by Cycles" in desc and np.isfinite(L).all()


def test_inside_blenders_drawing_the_panorama_waits_for_a_timer():
    """The viewport's draw may not make a scene or run a render: there an
    uncached World raises Pending (the panorama is queued for a timer), and
    once rendered outside drawing the draw gets it from the cache."""
    from prtt_addon.blender.scene import world_panorama
    from prtt_addon.blender.scene.world import project_setup, world_setup
    bpy = fresh_bpy()
    w, nt, bg = _world(bpy, "Checker")
    tex = nt.nodes.new("ShaderNodeTexChecker")
    nt.links.new(tex.outputs["Color"], bg.inputs["Color"])
    setup = world_setup(bpy.context.scene)
    n = world_panorama.renders
    with world_panorama.drawing(), pytest.raises(world_panorama.Pending, match="being rendered"):
        project_setup(setup, 3)
    assert world_panorama.renders == n and setup.key[1] in world_panorama._pending
    a = project_setup(setup, 3)                    # what the timer does
    with world_panorama.drawing():
        b = project_setup(setup, 3)
    assert world_panorama.renders == n + 1 and np.array_equal(a, b)


def test_a_sky_world_bakes_renders_and_exports(tmp_path):
    """The chain a user runs, headless, on a scene lit by a Sky Texture World:
    bake, render and export all take the World's light (the export notes that
    it carries the SH light, not an image)."""
    import json

    from tests import real_scenes as rs
    from tests.blender_util import addon_bpy
    from tests.test_headless_chain import run
    bpy = addon_bpy()
    rs.floor_and_box(bpy)
    sc = bpy.context.scene
    sc.prtt.light_source = "WORLD"
    w, nt, bg = _world(bpy, "Sky")
    sky = nt.nodes.new("ShaderNodeTexSky")
    nt.links.new(sky.outputs["Color"], bg.inputs["Color"])
    bg.inputs["Strength"].default_value = 0.3
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    r = run("bake", "scene.blend", "--out", "tex", "--unwrap", "SMART", "--resolution", "64", "--rays", "32",
            "--bounces", "1", "--bounce-rays", "16", cwd=tmp_path, timeout=600)
    assert r.returncode == 0, r.stderr + r.stdout
    # The World's renders (panorama, the sun's views) keep Blender's progress lines to themselves.
    assert "Fra:" not in r.stdout + r.stderr and "Saved: " not in r.stdout + r.stderr, r.stdout
    r = run("render", "scene.blend", "--size", "96x54", "--out", "shot.exr", cwd=tmp_path, timeout=600)
    assert r.returncode == 0, r.stderr + r.stdout
    from prtt_addon.core.io.image_io import read_hdr_image
    img = read_hdr_image(str(tmp_path / "shot.exr"))
    assert np.isfinite(img).all() and img.mean() > 0.01, img.mean()
    r = run("export", "scene.blend", "--out", "scene.glb", cwd=tmp_path, timeout=600)
    assert r.returncode == 0, r.stderr + r.stdout
    assert "rendered by Cycles" in r.stdout + r.stderr and "not an image" in r.stdout + r.stderr, r.stdout
    from prtt_addon.core.io.gltf_prtt import read_glb_json
    doc = read_glb_json(str(tmp_path / "scene.glb"))
    env = json.dumps(doc["extensions"])
    assert "rendered by Cycles" in env
