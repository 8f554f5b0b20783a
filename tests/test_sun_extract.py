"""An environment image's sun taken out (core/light/sun_extract.py, issue 48
item 3): against images whose sun is known (a disc drawn by supersampled
pixel coverage on a constant sky), Blender's bundled HDRIs, and bad input;
in Blender, the option that bakes it (HDRI Sun) and what it gains against
Cycles on the city HDRI."""
import json
import math

import numpy as np
import pytest

from prtt_addon.core.light.envmap import pixel_solid_angles, project_equirect, uv_to_direction
from prtt_addon.core.light.sun_extract import MIN_SHARE, extract_sun


def sky_with_disc(H, W, direction, angle, radiance, sky=0.5, supersample=8):
    """(H, W, 3) equirect: a constant sky and a uniform disc (full angle
    ``angle``) of ``radiance`` above it, each pixel's coverage by supersampling."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    s = supersample
    v = 1.0 - (np.arange(H * s) + 0.5) / (H * s)
    u = (np.arange(W * s) + 0.5) / (W * s)
    uu, vv = np.meshgrid(u, v)
    dirs = uv_to_direction(np.stack([uu.ravel(), vv.ravel()], -1)).reshape(H * s, W * s, 3)
    inside = (dirs @ d) >= math.cos(angle / 2)
    cover = inside.reshape(H, s, W, s).mean(axis=(1, 3))
    img = np.full((H, W, 3), sky, np.float64)
    img += cover[..., None] * np.asarray(radiance, float)
    return img.astype(np.float32)


@pytest.mark.parametrize("direction", [(0.3, -0.5, 0.8), (1.0, 0.0, 0.2), (0.2, 0.1, -0.5)])
def test_a_known_disc_is_found_with_its_energy_and_the_sky_is_left(direction):
    H, W = 256, 512
    angle = math.radians(2.0)
    L = np.array([4000.0, 3000.0, 2000.0])
    img = sky_with_disc(H, W, direction, angle, L)
    sun, rest, why = extract_sun(img)
    assert why == "" and sun is not None
    d = np.asarray(direction) / np.linalg.norm(direction)
    off = math.degrees(math.acos(min(1.0, float(np.dot(sun.direction, d)))))
    assert off < 0.05, off                                    # 0.7-degree pixels
    disc = 2 * math.pi * (1 - math.cos(angle / 2))
    assert np.allclose(sun.energy, L * disc, rtol=0.01), (sun.energy, L * disc)
    assert abs(math.degrees(sun.angle) - 2.0) < 0.25, math.degrees(sun.angle)
    # the sky behind it: only pixels the disc covers by under REGION_FRACTION keep a little of it
    om = pixel_solid_angles(H, W)[:, None, None]
    left = ((rest.astype(np.float64) - 0.5) * om).sum(axis=(0, 1))
    assert rest.min() >= 0.5 - 1e-6 and np.all(left < 0.005 * L * disc), (left, L * disc)
    # and the image's SH are the sky's plus the disc's: nothing lost, nothing added
    full, sky = project_equirect(img, 3), project_equirect(rest, 3)
    assert np.allclose((full - sky)[0], L * disc / math.sqrt(4 * math.pi), rtol=0.01)


def test_a_sun_across_the_seam_is_one_region():
    """A disc on the image's left and right edges at once (u = 0): one sun, its direction right."""
    d = (-1.0, 0.0, 0.3)                                       # u = 0.5 - atan2(0, -1) / 2 pi = 0: the seam
    img = sky_with_disc(128, 256, d, math.radians(3.0), (500.0, 500.0, 500.0))
    sun, rest, _ = extract_sun(img)
    assert sun is not None
    assert math.degrees(math.acos(min(1.0, float(np.dot(sun.direction, np.asarray(d) / np.linalg.norm(d)))))) < 0.1
    assert rest.min() >= 0.5 - 1e-6 and (rest > 0.5 + 1e-6).sum() < 40      # the disc's faintest edge pixels


def test_no_dominant_light_and_bad_images_are_said():
    H, W = 64, 128
    grad = np.repeat(np.linspace(2.0, 0.1, H)[:, None, None], W, axis=1).repeat(3, axis=2).astype(np.float32)
    sun, rest, why = extract_sun(grad)
    assert sun is None and rest is grad and "no dominant light" in why
    faint = sky_with_disc(H, W, (0, 0, 1), math.radians(2.0), (3.0, 3.0, 3.0), sky=1.0)
    sun, _, why = extract_sun(faint)
    assert sun is None and f"under {MIN_SHARE:.0%}" in why
    sun, _, why = extract_sun(np.zeros((H, W, 3), np.float32))
    assert sun is None and "black" in why
    bad = faint.copy()
    bad[3, 4, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        extract_sun(bad)
    with pytest.raises(ValueError, match="equirect"):
        extract_sun(np.zeros((4, 4), np.float32))


def test_blenders_outdoor_hdris_give_their_sun():
    """city: the sun 47.8 degrees up, a fifth of the light in 6 pixels; sunset's
    brightest spot is too faint to be one (2.3 %); courtyard's sky has none."""
    from prtt_addon.core.io.image_io import read_hdr_image
    from prtt_addon.core.light.envmap import builtin_environment_path
    got = {}
    for name in ("city", "sunrise", "sunset", "courtyard"):
        got[name] = extract_sun(read_hdr_image(builtin_environment_path(name)))
    city = got["city"][0]
    assert abs(math.degrees(math.asin(city.direction[2])) - 47.8) < 0.3 and 0.2 < city.share < 0.23
    assert math.degrees(city.angle) < 1.0
    assert got["sunrise"][0] is not None and got["sunrise"][0].share > 0.5
    assert got["sunset"][0] is None and got["courtyard"][0] is None
    # energy is conserved: the image = its rest + the sun's excess
    img = read_hdr_image(builtin_environment_path("city"))
    H, W = img.shape[:2]
    om = pixel_solid_angles(H, W)[:, None, None]
    lost = ((img.astype(np.float64) - got["city"][1]) * om).sum(axis=(0, 1))
    assert np.allclose(lost, city.energy, rtol=1e-6)


# --- in Blender -------------------------------------------------------------------------------------

@pytest.mark.blender
def test_hdri_sun_bakes_the_images_sun_turned_with_the_world(tmp_path):
    """HDRI Sun on: the bake names "city.exr: sun", at the image's sun turned by
    the World's Mapping node (w = R^T d), its energy times the strength, the
    World's light made without it; off (the default): no sun and the light as before."""
    from prtt_addon.core.io.image_io import read_hdr_image
    from prtt_addon.core.light.envmap import builtin_environment_path, compose_light, mapping_rotation
    from prtt_addon.dev.bench.scene_build import environment_world
    from tests import real_scenes as rs
    from tests.blender_util import addon_bpy
    from tests.test_headless_chain import run
    bpy = addon_bpy()
    rs.floor_and_box(bpy)
    scene = bpy.context.scene
    scene.world = environment_world("City", builtin_environment_path("city"), strength=1.5,
                                    rotation_z=math.radians(30))
    scene.prtt.light_source = "WORLD"
    from prtt_addon.blender.scene.lamps import scene_sun
    from prtt_addon.blender.scene.world import world_light
    before, desc = world_light(scene, 5)
    assert scene_sun(scene)[0] is None and "extracted" not in desc         # off by default
    image = read_hdr_image(builtin_environment_path("city"))
    R = mapping_rotation((0.0, 0.0, math.radians(30)), "POINT")
    assert np.allclose(before, compose_light(project_equirect(image, 5), 1.5, R), rtol=1e-5, atol=1e-7)
    scene.prtt.hdri_sun = True
    sun, _, notes = scene_sun(scene)
    found, rest, _ = extract_sun(image)
    assert sun.name == "city.exr: sun" and not notes
    assert np.allclose(sun.direction, R.T @ np.asarray(found.direction), atol=1e-9)
    assert np.allclose(sun.irradiance, 1.5 * np.asarray(found.energy), rtol=1e-6)
    after, desc = world_light(scene, 5)
    assert "its sun extracted" in desc
    assert np.allclose(after, compose_light(project_equirect(rest, 5), 1.5, R), rtol=1e-5, atol=1e-7)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    r = run("bake", "scene.blend", "--out", "tex", "--unwrap", "SMART", "--resolution", "32", "--rays", "16",
            "--bounces", "0", cwd=tmp_path, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    m = json.load(open(tmp_path / "tex" / "manifest.json"))
    assert m["sun"]["name"] == "city.exr: sun" and np.allclose(m["sun"]["direction"], sun.direction)
    # turning the World turns its sun: the masks are stale until the next bake
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "scene.blend"))
    m_node = next(n for n in bpy.context.scene.world.node_tree.nodes if n.bl_idname == "ShaderNodeMapping")
    m_node.inputs["Rotation"].default_value[2] = math.radians(50)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    r = run("render", "scene.blend", "--size", "32x18", "--out", "a.png", cwd=tmp_path, timeout=600)
    assert r.returncode == 0 and "the sun's shadows are stale" in r.stderr and "turned" in r.stderr, r.stderr


@pytest.mark.blender
def test_the_extracted_sun_matches_cycles_better_than_the_sun_in_sh(tmp_path):
    """bench sun --hdri city at small sizes: with the sun extracted the shadowed
    floor is several times closer to Cycles than with the sun in the SH, and
    the image closer too."""
    pytest.importorskip("bpy")
    from prtt_addon.dev.bench.sun_cycles import compare
    on = compare(0.0, (160, 90), samples=64, resolution=256, work_dir=str(tmp_path / "a"), light="hdri:city")
    off = compare(0.0, (160, 90), samples=64, resolution=256, work_dir=str(tmp_path / "b"), light="hdri:city",
                  sky_sun=False)
    assert on["sun"] is not None and off["sun"] is None and on["shadow_pixels"] >= 20
    print(f"city: extracted {on['rel_rmse']:.2%} (shadow {on['rel_rmse_shadow']:.2%}), in SH {off['rel_rmse']:.2%} "
          f"(shadow {off['rel_rmse_shadow']:.2%})")
    assert on["rel_rmse"] < 0.02 and on["rel_rmse"] < off["rel_rmse"]
    assert on["rel_rmse_shadow"] < off["rel_rmse_shadow"] / 2.5
