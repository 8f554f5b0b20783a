"""The World as SH light, checked against what Cycles renders from the same World."""
import math

import numpy as np
import pytest

from prtt_addon.core import sh
from prtt_addon.core.light import envmap
from tests.blender_util import addon_bpy, cycles_looker, new_float_image

pytestmark = pytest.mark.blender

C0 = np.zeros((9, 3))
C0[0] = [3.0, 3.2, 3.5]
C0[1] = [0.4, -0.2, 0.1]
C0[2] = [0.9, 0.7, 0.5]
C0[3] = [-0.6, 0.3, 0.2]
C0[5] = [0.3, 0.1, -0.2]
C0[8] = [-0.2, 0.25, 0.3]


def cycles_radiance(bpy, dirs, tmp_path):
    """Radiance Cycles sees along each direction (a 0.01-rad camera, 1 sample)."""
    look = cycles_looker(bpy, tmp_path)
    return np.array([look(d)[1:3, 1:3, :3].mean(axis=(0, 1)) for d in dirs])


def world_with_image(bpy, rotation=None, strength=1.0, vector_type="POINT"):
    H, W = 64, 128
    px = envmap.reconstruct_equirect(C0, H, W).astype(np.float32)
    img = new_float_image(bpy, "env", px)
    world = bpy.data.worlds.new("W")
    bpy.context.scene.world = world
    nt = world.node_tree
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.image = img
    bg = nt.nodes["Background"]
    bg.inputs["Strength"].default_value = strength
    nt.links.new(env.outputs["Color"], bg.inputs["Color"])
    if rotation is not None:
        tc = nt.nodes.new("ShaderNodeTexCoord")
        mp = nt.nodes.new("ShaderNodeMapping")
        mp.vector_type = vector_type
        mp.inputs["Rotation"].default_value = rotation
        nt.links.new(tc.outputs["Generated"], mp.inputs["Vector"])
        nt.links.new(mp.outputs["Vector"], env.inputs["Vector"])
    return world


@pytest.mark.parametrize("rotation,vtype", [(None, "POINT"), ((0.0, 0.0, math.radians(90)), "POINT"),
                                            ((math.radians(35), math.radians(-20), math.radians(60)), "POINT"),
                                            ((math.radians(35), math.radians(-20), math.radians(60)), "TEXTURE")])
def test_world_light_matches_cycles(tmp_path, rotation, vtype):
    bpy = addon_bpy()
    world_with_image(bpy, rotation, strength=1.5, vector_type=vtype)
    from prtt_addon.blender.scene.world import world_light
    L, desc = world_light(bpy.context.scene, 3)
    assert "x1.5" in desc and ("rotated" in desc) == (rotation is not None)
    # Not at a pole: Cycles' equirect lookup wraps vertically, blending in the
    # opposite pole's row within half a pixel of it.
    dirs = np.array([[1, 0, 0], [0, 1, 0], [0.2, 0.05, 0.98], [-0.6, 0.5, 0.62], [0.3, -0.8, -0.52], [-1, 0, 0.001]])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    ref = cycles_radiance(bpy, dirs, tmp_path)
    ours = sh.eval_basis(dirs, 3) @ L
    # pixel-sampled (bilinear) image vs its exact band-limited source: ~1 %
    np.testing.assert_allclose(ours, ref, rtol=0.03, atol=0.02)


def test_constant_world_and_errors(tmp_path):
    bpy = addon_bpy()
    from prtt_addon.blender.scene.world import WorldLightError, world_light
    world = bpy.data.worlds.new("W")
    bpy.context.scene.world = world
    bg = world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (0.2, 0.4, 0.6, 1)
    bg.inputs["Strength"].default_value = 2.0
    L, _ = world_light(bpy.context.scene, 2)
    np.testing.assert_allclose(L[0], np.array([0.4, 0.8, 1.2]) * math.sqrt(4 * math.pi))
    assert np.all(L[1:] == 0)
    sky = world.node_tree.nodes.new("ShaderNodeTexSky")
    world.node_tree.links.new(sky.outputs["Color"], bg.inputs["Color"])
    L_sky, desc = world_light(bpy.context.scene, 2)         # rendered by Cycles (test_world_panorama.py)
    assert "Sky Texture" in desc and "rendered by Cycles" in desc and np.isfinite(L_sky).all() and L_sky[0, 2] > 0
    L2, desc = world_light(bpy.context.scene, 2, source="BUILTIN", builtin="forest")
    assert "forest" in desc and L2.shape == (4, 3)
    bpy.context.scene.world = None
    with pytest.raises(WorldLightError, match="no World"):
        world_light(bpy.context.scene, 2)


def test_world_image_without_pixels_is_a_clear_error(tmp_path):
    """An Environment Texture whose file is gone: WorldLightError naming it, no crash."""
    bpy = addon_bpy()
    from prtt_addon.blender.scene.world import WorldLightError, world_light
    world = bpy.data.worlds.new("W")
    bpy.context.scene.world = world
    nt = world.node_tree
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.image = bpy.data.images.new("gone", 4, 2)
    env.image.source = "FILE"
    env.image.filepath = str(tmp_path / "gone.png")
    nt.links.new(env.outputs["Color"], nt.nodes["Background"].inputs["Color"])
    with pytest.raises(WorldLightError, match="'gone' has no pixels"):
        world_light(bpy.context.scene, 2)


def test_non_finite_world_settings_are_clear_errors(tmp_path):
    """A Background strength or Mapping angle that is NaN, or a colour Blender
    clamped to 3.4e38: WorldLightError naming the setting (the fuzz target
    `world` found the core making NaN or float32-overflowing lights of them)."""
    bpy = addon_bpy()
    from prtt_addon.blender.scene.world import WorldLightError, world_light
    world_with_image(bpy, strength=float("nan"))
    with pytest.raises(WorldLightError, match="strength is nan"):
        world_light(bpy.context.scene, 2)
    world_with_image(bpy, strength=1e6)
    L, _ = world_light(bpy.context.scene, 2)                   # bright but representable: a light
    assert np.isfinite(L).all()
    world_with_image(bpy, strength=3e38)
    with pytest.raises(WorldLightError, match="beyond 1e.30.*float32"):
        world_light(bpy.context.scene, 2)
    w = world_with_image(bpy, rotation=(float("nan"), 0.0, 0.0))
    mapping = next(n for n in w.node_tree.nodes if n.bl_idname == "ShaderNodeMapping")
    if math.isnan(mapping.inputs["Rotation"].default_value[0]):        # Blender keeps a NaN angle
        with pytest.raises(WorldLightError, match="Mapping.*not three finite angles"):
            world_light(bpy.context.scene, 2)
    bg = world_with_image(bpy).node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (float("inf"), 0.0, 0.0, 1.0)
    for link in list(bg.inputs["Color"].links):
        bpy.context.scene.world.node_tree.links.remove(link)
    with pytest.raises(WorldLightError, match="beyond 1e.30.*float32"):    # Blender stored 3.4e38
        world_light(bpy.context.scene, 2)
