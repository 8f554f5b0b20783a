"""The environment orientation and HDR reading checked against Blender itself."""

import numpy as np
import pytest

from prtt_addon.core.io.image_io import read_hdr_image
from prtt_addon.core.light import envmap
from tests.blender_util import cycles_looker, fresh_bpy, new_float_image

pytestmark = pytest.mark.blender


def test_equirect_orientation_matches_cycles(tmp_path):
    """Cycles renders the world through a 0.01-rad camera aimed along several
    directions; the map encodes (u, v) of each pixel centre in R, G. What Cycles
    sees must be the pixel that envmap.direction_to_uv predicts."""
    bpy = fresh_bpy()
    W, H = 64, 32
    u = (np.arange(W) + 0.5) / W
    v_top_first = 1.0 - (np.arange(H) + 0.5) / H
    px = np.zeros((H, W, 3), np.float32)
    px[..., 0] = u[None, :]
    px[..., 1] = v_top_first[:, None]
    img = new_float_image(bpy, "uvmap", px)
    sc = bpy.context.scene
    world = bpy.data.worlds.new("W")
    sc.world = world
    nt = world.node_tree
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.image = img
    env.interpolation = "Closest"
    nt.links.new(env.outputs["Color"], nt.nodes["Background"].inputs["Color"])
    look = cycles_looker(bpy, tmp_path)
    dirs = np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0.001], [0, -1, 0], [0.3, 0.2, 0.93],
                     [-0.5, 0.6, -0.62], [0.7, -0.7, 0.1]], float)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    want = envmap.direction_to_uv(dirs)
    for d, (wu, wv) in zip(dirs, want):
        got = look(d)[2, 2, :2]
        du = abs((got[0] - wu + 0.5) % 1.0 - 0.5)
        assert du <= 1.0 / W and abs(got[1] - wv) <= 1.0 / H, (d, got, (wu, wv))


def test_hdr_reader_matches_blender_writer(tmp_path):
    """Blender writes a Radiance .hdr; our reader gets the same pixels, top row first."""
    bpy = fresh_bpy()
    rng = np.random.default_rng(3)
    H, W = 24, 40
    px = (rng.random((H, W, 3)) * np.array([1.0, 50.0, 0.01])).astype(np.float32)
    px[0, :] = 7.0                       # top row marker
    img = new_float_image(bpy, "hdr", px)
    img.filepath_raw = str(tmp_path / "t.hdr")
    img.file_format = "HDR"
    img.save()
    got = read_hdr_image(str(tmp_path / "t.hdr"))
    assert got.shape == (H, W, 3)
    # RGBE shares one exponent per pixel: 8-bit mantissas relative to the
    # brightest channel of the pixel.
    tol = px.max(axis=-1, keepdims=True) / 128
    assert np.all(np.abs(got - px) <= tol)
    assert np.all(np.abs(got[0] - 7.0) < 7.0 / 128)


def test_exr_reader_is_file_order(tmp_path):
    bpy = fresh_bpy()
    px = np.zeros((4, 8, 3), np.float32)
    px[0] = [1.0, 2.0, 3.0]              # top row
    img = new_float_image(bpy, "exr", px)
    img.filepath_raw = str(tmp_path / "t.exr")
    img.file_format = "OPEN_EXR"
    img.save()
    got = read_hdr_image(str(tmp_path / "t.exr"))
    np.testing.assert_allclose(got, px)
