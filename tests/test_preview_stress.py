"""No NaN or Inf pixel from the preview shaders, whatever the input.

Degenerate and cancelling normals, zero tangents, a normal map that encodes
the zero vector, roughness 0 (exponent 10000) and 1 (exponent 0), black and
extremely bright environments, transfer values at the top of the half range:
every mode renders finite pixels, and the glossy mirror case still matches
the numpy reference.
"""
import numpy as np
import pytest

from tests.blender_util import addon_bpy

pytestmark = pytest.mark.blender
W, H = 64, 48


def stress_scene(tmp_path, light, bands=5):
    from prtt_addon.core.io.exr_io import write_sh_exr
    from prtt_addon.core.preview import pack as pp
    rng = np.random.default_rng(0)
    K = bands * bands
    # Six triangles in a row facing the camera (+Y towards -Y camera), each with a problem.
    tris = []
    for i in range(6):
        x = -2.5 + i
        tris.append([[x, 0, -0.5], [x + 0.9, 0, -0.5], [x + 0.45, 0, 0.5]])
    n = np.tile([0.0, -1.0, 0.0], (6, 3, 1))
    n[0] = 0.0                                         # zero corner normals
    n[1, 1] = [0.0, 1.0, 0.0]                          # cancelling corners: interpolation passes zero
    n[1, 2] = [0.0, 1.0, 0.0]
    n[2] = [[1, 0, 0], [-1, 0, 0], [0, 0, 1.0]]        # grazing normals
    tris[3][2] = [tris[3][0][0] + 0.3, 0, -0.5]        # zero-area triangle
    P = np.array(tris, np.float64)
    uv = rng.random((6, 3, 2)) * 0.9 + 0.05
    tangents = np.tile([1.0, 0.0, 0.0, 1.0], (6, 3, 1))
    tangents[4] = 0.0                                  # zero tangents (and sign 0)
    vidx = np.arange(18, dtype=np.float32).reshape(6, 3)
    mesh = pp.build_mesh("Stress", "S", {"positions": P, "normals": n, "uv": uv, "mat_uv": uv, "nm_uv": uv,
                                         "tangents": tangents, "vidx": vidx},
                         np.array([0, 1, 2, 3, 4, 5]) % 3, key="stress")
    # Transfer near the top of the half range, zeros, and ordinary values.
    tex = rng.normal(size=(16, 16, K)).astype(np.float32)
    tex[:8] *= 6.0e4 / np.abs(tex[:8]).max()
    tex[:, :4] = 0.0
    tpath = str(tmp_path / "S.transfer.exr")
    write_sh_exr(tpath, tex, kind="transfer", attrs={"bands": bands})
    bounce = np.abs(rng.normal(size=(16, 16, 3, K))).astype(np.float32)
    bpath = str(tmp_path / "S.bounce1.exr")
    write_sh_exr(bpath, bounce, kind="bounce", rgb=True, attrs={"bands": bands, "level": 1})
    vpath = str(tmp_path / "S.vertex.npz")
    np.savez(vpath, coeffs=np.concatenate([tex[0, :9], tex[15, :9]])[:18].astype(np.float32))
    zero_normal = np.full((4, 4, 3), 0.5, np.float32)  # encodes the zero vector
    mats = [pp.PreviewMaterial(roughness=0.0, metallic=0.0, normal_texture=0),      # mirror, exponent 10000
            pp.PreviewMaterial(base_color=(1.0, 1.0, 1.0), roughness=1.0),           # exponent 0
            pp.PreviewMaterial(base_color=(0.0, 0.0, 0.0), metallic=1.0, roughness=0.2)]   # black metal
    return pp.PreviewScene(bands=bands, meshes=[mesh], materials=mats,
                           sets={"S": pp.PreviewSet("S", tpath, (bpath,), vpath)},
                           light=light, images=[zero_normal], image_keys=["zero_normal"])


def lights(bands=5):
    from prtt_addon.core.light.envmap import project_equirect
    sun = np.zeros((64, 128, 3), np.float32)
    sun[20, 40] = 1.0e5                                 # a tiny, very bright sun
    K = bands * bands
    return {"black": np.zeros((K, 3)), "sun": project_equirect(sun, bands),
            "huge": np.full((K, 3), 1.0e4)}


@pytest.mark.parametrize("light", ["black", "sun", "huge"])
def test_every_mode_renders_finite_pixels(tmp_path, light):
    addon_bpy()
    from prtt_addon.blender.preview.offscreen import ensure_gpu
    from prtt_addon.blender.preview.renderer import Renderer, render_offscreen
    from prtt_addon.core.preview.reference import look_at, perspective, reference_image, relative_error
    ensure_gpu()
    ps = stress_scene(tmp_path, lights()[light])
    vp = perspective(50.0, W / H) @ look_at((0, -4, 0), (0, 0, 0))
    cam = np.array([0.0, -4.0, 0.0, 1.0])
    r = Renderer()
    for mode in ("tpfl", "tp", "diffuse", "vertex-tpfl", "vertex-tp"):
        px, stats = render_offscreen(r, ps, mode, vp, cam, W, H)
        assert stats.drawn == ["Stress"], stats.skipped
        assert np.all(np.isfinite(px)), f"{mode} under {light}: {np.count_nonzero(~np.isfinite(px))} bad values"
        assert (px[..., 3] > 0.5).sum() > 100                 # the triangles are on screen
        assert px[..., :3].min() >= 0.0                       # outgoing radiance is clamped at 0
        if mode in ("tpfl", "vertex-tpfl"):
            ref, hits = reference_image(ps, mode, vp, cam, W, H)
            interior = hits.hit & (hits.edge_px > 0.02)
            floor = 1e-2 * max(ref[..., :3][hits.hit].mean(), 1e-30)
            err = relative_error(px[..., :3][interior], ref[..., :3][interior], floor)
            assert err.max() <= 1e-3, f"{mode} under {light}: {err.max():.2e}"
