"""Gaunt tensor vs sympy.physics.wigner.gaunt (exact complex integrals), TPFL."""
import math

import numpy as np
import pytest
from sympy import N as sym_n
from sympy.physics.wigner import gaunt

from prtt_addon.core import sh


def complex_to_real(bands):
    """U with y_real[k] = sum_m' U[k, (l,m')] Y_l^m' (scipy/sympy complex SH).

    m > 0:  y = (Y^m + (-1)^m Y^-m) / sqrt2;  m < 0: y = (Y^|m| - (-1)^|m| Y^-|m|) / (i sqrt2).
    """
    K = bands * bands
    U = np.zeros((K, K), dtype=complex)
    for l in range(bands):
        for m in range(-l, l + 1):
            k = l * l + l + m
            if m == 0:
                U[k, k] = 1
            elif m > 0:
                U[k, l * l + l + m] = 1 / math.sqrt(2)
                U[k, l * l + l - m] = (-1) ** m / math.sqrt(2)
            else:
                a = -m
                U[k, l * l + l + a] = 1 / (1j * math.sqrt(2))
                U[k, l * l + l - a] = -((-1) ** a) / (1j * math.sqrt(2))
    return U


def sympy_real_gaunt(bands):
    K = bands * bands
    lm = [sh.lm_of(k) for k in range(K)]
    G = np.zeros((K, K, K))   # complex Gaunt integral of Y Y Y (no conjugates), real-valued
    for a, (l1, m1) in enumerate(lm):
        for b, (l2, m2) in enumerate(lm):
            for l3 in range(abs(l1 - l2), min(l1 + l2, bands - 1) + 1):
                m3 = -m1 - m2
                if abs(m3) <= l3 and (l1 + l2 + l3) % 2 == 0:
                    G[a, b, l3 * l3 + l3 + m3] = float(sym_n(gaunt(l1, l2, l3, m1, m2, m3), 30))
    U = complex_to_real(bands)
    T = np.einsum("ia,jb,kc,abc->ijk", U, U, U, G)
    assert np.abs(T.imag).max() < 1e-12
    return T.real


def test_gaunt_matches_sympy_band_5():
    ref = sympy_real_gaunt(5)
    ours = sh.triple_product_tensor(5)
    assert ours.shape == (25, 25, 25)
    assert np.abs(ours - ref).max() <= 1e-12


def test_gaunt_known_values_and_symmetry():
    t = sh.triple_product_tensor(3)
    # tau_{i,j,0} = delta_ij / sqrt(4 pi)
    np.testing.assert_allclose(t[:, :, 0], np.eye(9) / math.sqrt(4 * math.pi), atol=1e-15)
    for perm in [(1, 0, 2), (2, 1, 0), (0, 2, 1)]:
        assert np.abs(t - t.transpose(perm)).max() < 1e-15


def test_sparse_storage_drops_only_zeros():
    g = sh.sparse_gaunt(6)
    dense = g.dense()
    assert g.nnz < dense.size / 10
    # An independent dense quadrature: nothing outside the stored entries.
    d, w = sh.gauss_sphere(15)
    y = sh.eval_basis(d, 6)
    full = np.einsum("q,qi,qj,qk->ijk", w, y, y, y)
    assert np.abs(full - dense).max() < 1e-13


def test_tpfl_matrix_is_product_with_light(rng):
    bands = 4
    K = bands * bands
    L = rng.standard_normal((K, 3))
    T = rng.standard_normal(K)
    M = sh.tpfl_matrix(L, bands)
    assert M.shape == (3, K, K)
    # Independent: project the pointwise product of the two functions.
    d, w = sh.gauss_sphere(3 * (bands - 1))
    y = sh.eval_basis(d, bands)
    for c in range(3):
        prod = (y @ T) * (y @ L[:, c])
        ref = y.T @ (w * prod)
        np.testing.assert_allclose(M[c] @ T, ref, atol=1e-12)
        np.testing.assert_allclose(M[c], M[c].T, atol=1e-15)
        np.testing.assert_allclose(M[c], np.einsum("ijk,j->ik", sh.triple_product_tensor(bands), L[:, c]), atol=1e-14)
    np.testing.assert_allclose(sh.tpfl_matrix(L[:, 0], bands), M[0])
    np.testing.assert_allclose(sh.triple_product(T, L[:, 1]), M[1] @ T, atol=1e-13)


def test_tpfl_bad_input():
    with pytest.raises(ValueError, match="not a square"):
        sh.tpfl_matrix(np.ones(7))
    with pytest.raises(ValueError, match="bands=3 needs 9"):
        sh.tpfl_matrix(np.ones(16), 3)
    with pytest.raises(ValueError, match="NaN"):
        sh.tpfl_matrix(np.full(9, np.nan), 3)
    with pytest.raises(ValueError, match="up to 16 bands"):
        sh.triple_product_tensor(17)
