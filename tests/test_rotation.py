"""SH rotation: Ivanic recurrence and the ZYZ fast path vs quadrature projection."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from prtt_addon.core import sh
from tests.conftest import random_dirs


def quadrature_rotation(R, bands):
    """D_kk' = integral y_k(w) y_k'(R^T w) dw, computed by exact quadrature."""
    d, w = sh.gauss_sphere(2 * (bands - 1))
    return sh.eval_basis(d, bands).T @ (w[:, None] * sh.eval_basis(d @ R, bands))


@pytest.mark.parametrize("seed", range(4))
def test_ivanic_matches_quadrature(seed):
    R = Rotation.random(random_state=seed).as_matrix()
    for bands in (1, 2, 5, 9):
        assert np.abs(sh.sh_rotation(R, bands) - quadrature_rotation(R, bands)).max() < 1e-12


def test_rotate_project_commutes(rng):
    """rotate(project(f)) == project(f o R^-1) for a band-limited f."""
    R = Rotation.random(random_state=7).as_matrix()
    f = lambda d: 1 + d[:, 0] * d[:, 1] - 0.5 * d[:, 2] ** 3 + d[:, 1]   # degree 3
    lhs = sh.rotate(sh.project_function(f, 4), R)
    rhs = sh.project_function(lambda d: f(d @ R), 4)              # f(R^T w)
    assert np.abs(lhs - rhs).max() < 1e-13


def test_special_rotations():
    for R in (np.eye(3), np.diag([-1.0, -1.0, 1.0]), np.diag([1.0, -1.0, -1.0]),
              Rotation.from_euler("z", 90, degrees=True).as_matrix()):
        assert np.abs(sh.sh_rotation(R, 6) - quadrature_rotation(R, 6)).max() < 1e-12
    np.testing.assert_allclose(sh.sh_rotation(np.eye(3), 4), np.eye(16), atol=1e-15)


def test_rotation_preserves_norm_and_band(rng):
    R = Rotation.random(random_state=3).as_matrix()
    D = sh.sh_rotation(R, 8)
    np.testing.assert_allclose(D @ D.T, np.eye(64), atol=1e-12)
    band = sh.band_of_coeffs(8)
    assert np.all(np.abs(D[band[:, None] != band[None, :]]) == 0)


def test_batched_and_zyz_fast_path(rng):
    B = 50
    a, b, g = rng.uniform(-np.pi, np.pi, B), rng.uniform(0, np.pi, B), rng.uniform(-np.pi, np.pi, B)
    b[:3] = [0.0, np.pi, 1e-12]                    # poles: no Euler singularity on this path
    R = sh.rotation_zyz(a, b, g)
    ref = Rotation.from_euler("ZYZ", np.stack([a, b, g], 1)).as_matrix()
    np.testing.assert_allclose(R, ref, atol=1e-14)
    D = sh.sh_rotation(R, 5)
    c = rng.standard_normal((B, 25))
    want = np.einsum("bij,bj->bi", D, c)
    np.testing.assert_allclose(sh.rotate_zyz(c, a, b, g), want, atol=1e-13)
    c32 = sh.rotate_zyz(c.astype(np.float32), a, b, g)
    assert c32.dtype == np.float32 and np.abs(c32 - want).max() < 1e-5


def test_zyz_frame_normal_is_column_2(rng):
    n = random_dirs(rng, 10)
    R = sh.rotation_zyz(np.arctan2(n[:, 1], n[:, 0]), np.arccos(n[:, 2]), 0.3)
    np.testing.assert_allclose(R[:, :, 2], n, atol=1e-14)


def test_bad_rotations():
    with pytest.raises(ValueError, match="reflection"):
        sh.sh_rotation(np.diag([1.0, 1.0, -1.0]), 3)
    with pytest.raises(ValueError, match="orthonormal"):
        sh.sh_rotation(np.eye(3) * 2, 3)
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        sh.sh_rotation(np.eye(2), 3)
    with pytest.raises(ValueError, match="NaN"):
        sh.sh_rotation(np.full((3, 3), np.nan), 3)
