"""The one light composition (core.light.envmap.compose_light and friends), against
independent computations, and both of its callers (the job CLI, the World export)."""
import math

import numpy as np
import pytest

from prtt_addon.core import sh
from prtt_addon.core.light import envmap


def _image(H=32, W=64, seed=0):
    """A lumpy RGB environment with nothing symmetric about it."""
    rng = np.random.default_rng(seed)
    img = rng.uniform(0.0, 1.0, (H, W, 3))
    img[H // 4:H // 2, W // 8:W // 3] += 4.0                       # a bright patch off every axis
    return img


@pytest.mark.parametrize("degrees,columns", [(90, 1), (-90, -1), (180, 2), (270, 3)])
def test_z_rotation_is_the_image_rolled(degrees, columns):
    """A Point Mapping turning lookups by +90 degrees about Z reads column
    j - W/4 for column j: the light is the image rolled by W/4 columns. With
    whole pixels rolled, projecting the rolled image is exact, so it must
    equal the rotated SH to rounding."""
    img = _image()
    W = img.shape[1]
    bands = 5
    got = envmap.environment_light(img, bands, 1.7, degrees)
    want = 1.7 * envmap.project_equirect(np.roll(img, columns * W // 4, axis=1), bands)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-10 * np.abs(want).max())
    # The test tells the directions apart: the other way round is far off.
    wrong = 1.7 * envmap.project_equirect(np.roll(img, -columns * W // 4, axis=1), bands)
    if columns % 4 != 2:
        assert np.abs(got - wrong).max() > 0.05 * np.abs(want).max()


def test_no_rotation_is_projection_times_strength():
    img = _image(seed=1)
    np.testing.assert_array_equal(envmap.environment_light(img, 3, 2.5),
                                  envmap.project_equirect(img, 3) * 2.5)


@pytest.mark.parametrize("rotation", [(0.3, -0.5, 1.1), (math.pi / 2, 0.0, 0.0), (0.0, 0.7, 0.0)])
@pytest.mark.parametrize("vector_type", ["POINT", "TEXTURE"])
def test_lookup_rotation_of_a_band_limited_light(rotation, vector_type):
    """For any Mapping rotation: L(w) = f(R w), evaluated pointwise from the
    unrotated coefficients (no SH rotation involved)."""
    rng = np.random.default_rng(2)
    c = rng.normal(size=(16, 3))
    R = envmap.mapping_rotation(rotation, vector_type)
    L = envmap.compose_light(c, 0.8, R)
    dirs = rng.normal(size=(50, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    want = 0.8 * sh.eval_basis(dirs @ R.T, 4) @ c           # f(R w) for each row w
    np.testing.assert_allclose(sh.eval_basis(dirs, 4) @ L, want, atol=1e-10)


def test_texture_mapping_is_the_inverse_of_point():
    rot = (0.4, -0.2, 1.3)
    np.testing.assert_allclose(envmap.mapping_rotation(rot, "TEXTURE"), envmap.mapping_rotation(rot, "POINT").T)
    R = envmap.mapping_rotation(rot, "POINT")
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)


def test_euler_xyz_is_blenders():
    pytest.importorskip("bpy")
    import mathutils
    for rot in [(0.3, -0.5, 1.1), (2.0, 0.1, -0.7), (0.0, 0.0, math.pi / 2)]:
        want = np.array(mathutils.Euler(rot, "XYZ").to_matrix())
        np.testing.assert_allclose(envmap.euler_xyz_matrix(*rot), want, atol=1e-6)


def test_constant_light_is_the_dc_term():
    L = envmap.constant_light([0.2, 0.4, 0.6], 3)
    assert L.shape == (9, 3) and not L[1:].any()
    dirs = np.array([[0, 0, 1.0], [1, 0, 0], [0, -0.6, 0.8]])
    np.testing.assert_allclose(sh.eval_basis(dirs, 3) @ L, [[0.2, 0.4, 0.6]] * 3, atol=1e-12)


def test_job_cli_light_is_the_core_light():
    from prtt_addon.core.light.envmap import environment_light
    try:
        path = envmap.builtin_environment_path("forest")
    except OSError:
        pytest.skip("Blender's studio lights are not installed")
    np.testing.assert_array_equal(environment_light("forest", 3, 1.5, 40.0), envmap.environment_light(path, 3, 1.5, 40.0))


@pytest.mark.blender
def test_world_export_and_job_cli_agree():
    """A World with the forest HDRI, strength 1.5 and a Point Mapping turned
    40 degrees about Z is the light ``bake-job --env forest --env-strength 1.5
    --env-rotation 40`` uses."""
    from tests.blender_util import addon_bpy
    bpy = addon_bpy()
    from prtt_addon.blender.scene.world import world_light
    from prtt_addon.core.light.envmap import environment_light
    path = envmap.builtin_environment_path("forest")
    world = bpy.data.worlds.new("W")
    bpy.context.scene.world = world
    nt = world.node_tree
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.image = bpy.data.images.load(path)
    bg = nt.nodes["Background"]
    bg.inputs["Strength"].default_value = 1.5
    nt.links.new(env.outputs["Color"], bg.inputs["Color"])
    mp = nt.nodes.new("ShaderNodeMapping")
    mp.inputs["Rotation"].default_value = (0.0, 0.0, math.radians(40.0))
    nt.links.new(nt.nodes.new("ShaderNodeTexCoord").outputs["Generated"], mp.inputs["Vector"])
    nt.links.new(mp.outputs["Vector"], env.inputs["Vector"])
    L, desc = world_light(bpy.context.scene, 4)
    assert "rotated" in desc
    # float32 angle in the node vs float64 on the command line: 1e-7 of a radian
    np.testing.assert_allclose(L, environment_light("forest", 4, 1.5, 40.0), rtol=0, atol=1e-6 * np.abs(L).max())
