"""Equirect environment projection: exactness, orientation, built-ins, bad input."""
import math

import numpy as np
import pytest

from prtt_addon.core import sh
from prtt_addon.core.io.image_io import ImageReadError, read_hdr_image
from prtt_addon.core.light import envmap
from tests.conftest import random_dirs


def test_uv_mapping_round_trip(rng):
    d = random_dirs(rng, 1000)
    np.testing.assert_allclose(envmap.uv_to_direction(envmap.direction_to_uv(d)), d, atol=1e-12)
    uv = envmap.direction_to_uv(np.eye(3))
    np.testing.assert_allclose(uv, [[0.5, 0.5], [0.25, 0.5], [uv[2, 0], 1.0]])


def test_pixel_solid_angles_sum_to_4pi():
    for h, w in [(1, 1), (7, 13), (512, 1024)]:
        assert abs(envmap.pixel_solid_angles(h, w).sum() * w - 4 * math.pi) < 1e-12


@pytest.mark.parametrize("method", ["area", "samples"])
def test_constant_map_is_exact(method):
    c = envmap.project_equirect(np.full((24, 48, 3), [1.0, 2.0, 0.5]), 6, method=method)
    np.testing.assert_allclose(c[0], np.array([1.0, 2.0, 0.5]) * math.sqrt(4 * math.pi), rtol=1e-14)
    assert np.abs(c[1:]).max() < 1e-13


def test_band_limited_round_trip_is_exact(rng):
    c0 = rng.standard_normal((36, 3))
    c0[0] += 80.0                       # keep it positive, like radiance
    for h in (11, 64):
        img = envmap.reconstruct_equirect(c0, h, 2 * h)
        assert img.min() > 0
        c1 = envmap.project_equirect(img, 6, method="samples")
        assert np.abs(c1 - c0).max() < 1e-12


def test_reconstruction_matches_basis(rng):
    c = rng.standard_normal((16, 3))
    img = envmap.reconstruct_equirect(c, 8, 16)
    d = envmap.pixel_directions(8, 16).reshape(-1, 3)
    np.testing.assert_allclose(img.reshape(-1, 3), sh.eval_basis(d, 4) @ c, atol=1e-13)


def test_area_method_converges_quadratically(rng):
    c0 = rng.standard_normal((25, 3))
    errs = [np.abs(envmap.project_equirect(envmap.reconstruct_equirect(c0, h, 2 * h), 5,
                                           clamp_negative=False) - c0).max() for h in (64, 128)]
    assert 3.5 < errs[0] / errs[1] < 4.5


def test_area_integrals_are_exact_pixel_integrals():
    """One lit pixel: coefficients equal the basis integrated over that pixel."""
    h, w, i, j = 16, 32, 3, 21
    img = np.zeros((h, w, 3))
    img[i, j] = 1.0
    c = envmap.project_equirect(img, 4)[:, 0]
    t0, t1 = math.pi * i / h, math.pi * (i + 1) / h
    p_hi = math.pi - 2 * math.pi * j / w
    p_lo = p_hi - 2 * math.pi / w
    # brute-force 2D Gauss-Legendre over the pixel
    x, wq = np.polynomial.legendre.leggauss(40)
    th = t0 + (t1 - t0) * (x + 1) / 2
    ph = p_lo + (p_hi - p_lo) * (x + 1) / 2
    T, P = np.meshgrid(th, ph, indexing="ij")
    d = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    wt = (np.outer(wq, wq) * np.sin(T)).ravel() * (t1 - t0) * (p_hi - p_lo) / 4
    np.testing.assert_allclose(c, sh.eval_basis(d, 4).T @ wt, atol=1e-15)
    assert abs(c[0] * math.sqrt(4 * math.pi) - envmap.pixel_solid_angles(h, w)[i]) < 1e-16


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_orientation_bright_only_along_axis(axis):
    """A map bright only around +X, +Y or +Z gives a band-1 vector along that axis."""
    d = envmap.pixel_directions(64, 128)
    img = np.repeat((np.clip(d[..., axis], 0, None) ** 16)[..., None], 3, axis=-1)
    c = envmap.project_equirect(img, 2)[:, 0]
    # y(1,-1) = -a y, y(1,0) = a z, y(1,1) = -a x  ->  direction = (-c3, -c1, c2)
    v = np.array([-c[3], -c[1], c[2]])
    assert np.argmax(np.abs(v)) == axis and v[axis] > 0
    assert np.abs(np.delete(v, axis)).max() < 1e-6 * v[axis]


def test_builtin_environments_by_name():
    envs = envmap.builtin_environments()
    if not envs:
        pytest.skip("bpy's studio lights are not installed")
    assert {"forest", "sunset"} <= set(envs)
    c = envmap.project_equirect("forest", 5)
    assert c.shape == (25, 3) and np.all(np.isfinite(c)) and np.all(c[0] > 0)
    img = read_hdr_image(envs["forest"])
    assert img.shape[1] == 2 * img.shape[0] and img.dtype == np.float32


def test_bad_environment_input(tmp_path):
    with pytest.raises(ImageReadError, match="unknown built-in environment 'nowhere'"):
        envmap.project_equirect("nowhere", 3)
    with pytest.raises(ImageReadError, match="no such file"):
        envmap.project_equirect(str(tmp_path / "missing.exr"), 3)
    png = tmp_path / "ldr.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 32)
    with pytest.raises(ImageReadError, match="PNG image is not HDR"):
        envmap.project_equirect(str(png), 3)
    junk = tmp_path / "junk.exr"
    junk.write_bytes(b"v/1\x01" + b"\0" * 20)
    with pytest.raises(ImageReadError, match="unreadable EXR"):
        envmap.project_equirect(str(junk), 3)
    hdr = tmp_path / "trunc.hdr"
    hdr.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 4 +X 8\n\x02\x02\x00\x08\x05")
    with pytest.raises(ImageReadError, match="truncated|corrupt"):
        envmap.project_equirect(str(hdr), 3)
    with pytest.raises(ValueError, match="NaN/Inf"):
        envmap.project_equirect(np.full((4, 8, 3), np.inf), 3)
    with pytest.raises(ValueError, match=r"\(H, W, 3\|4\)"):
        envmap.project_equirect(np.ones((4, 8, 2)), 3)
    with pytest.raises(ValueError, match="unknown projection method"):
        envmap.project_equirect(np.ones((4, 8, 3)), 3, method="cubic")


def test_negative_pixels_clamped():
    img = np.full((8, 16, 3), 1.0)
    img[2, 3] = -5.0
    c = envmap.project_equirect(img, 1)
    ref = envmap.project_equirect(np.where(img < 0, 0.0, img), 1)
    np.testing.assert_array_equal(c, ref)
