"""Triple products of real SH: the Gaunt tensor and the fixed-light product matrix.

tau_ijk = integral over the sphere of y_i y_j y_k, for i, j, k < K = bands**2.

It is computed once per band count by the Gauss-Legendre x uniform-phi rule of
``quadrature.gauss_sphere`` with degree 3 (bands - 1): a product of three SH of
degree <= bands - 1 is a polynomial of that degree, so the rule is exact and the
only error is float64 rounding (~1e-16 per entry). Entries that the selection
rules make exactly zero are dropped; the rest are kept in coordinate (sparse)
form. Selection rules for real SH:

* triangle: |l_i - l_j| <= l_k <= l_i + l_j, and l_i + l_j + l_k even;
* |m_k| is |m_i| + |m_j| or ||m_i| - |m_j||;
* an even number of the three m are negative (sin sin cos survives the phi
  integral, sin cos cos and sin sin sin do not).

Triple product (TP, Ng et al.): given transfer T and light L,
    Lp_k = sum_ij tau_ijk T_i L_j        (the product of the two functions).
Fixed light (TPFL, Sloan's "Stupid SH Tricks"): precompute
    M_ik = sum_j tau_ijk L_j,  then Lp_k = sum_i M_ik T_i,
i.e. ``Lp = M.T @ T``; M is symmetric because tau is, so ``Lp = M @ T`` too.
The product is truncated to the same ``bands`` as its inputs.
"""
from __future__ import annotations

import dataclasses
import functools

import numpy as np

from .basis import bands_of, check_bands, eval_basis, lm_of
from .quadrature import gauss_sphere

#: Band counts above this would make the dense accessor huge (K**3 float64);
#: 16 bands is 256**3 * 8 B = 134 MB.
MAX_TENSOR_BANDS = 16


@dataclasses.dataclass(frozen=True)
class SparseGaunt:
    """Gaunt tensor in coordinate form: tau[i[n], j[n], k[n]] = value[n].

    Symmetric under any permutation of (i, j, k); every non-zero entry is
    stored (all permutations), so sums over any index need no symmetry logic.
    """

    bands: int
    i: np.ndarray      # (nnz,) int32
    j: np.ndarray      # (nnz,) int32
    k: np.ndarray      # (nnz,) int32
    value: np.ndarray  # (nnz,) float64

    @property
    def size(self) -> int:
        return self.bands ** 2

    @property
    def nnz(self) -> int:
        return int(self.value.shape[0])

    def dense(self) -> np.ndarray:
        """(K, K, K) float64 dense copy."""
        t = np.zeros((self.size,) * 3)
        t[self.i, self.j, self.k] = self.value
        return t


def _allowed_mask(n: int) -> np.ndarray:
    """(K, K, K) bool: entries not forced to zero by the selection rules."""
    K = n * n
    lm = np.array([lm_of(k) for k in range(K)])
    l, m = lm[:, 0], lm[:, 1]
    li, lj, lk = l[:, None, None], l[None, :, None], l[None, None, :]
    mi, mj, mk = m[:, None, None], m[None, :, None], m[None, None, :]
    tri = (lk >= np.abs(li - lj)) & (lk <= li + lj) & ((li + lj + lk) % 2 == 0)
    ai, aj, ak = np.abs(mi), np.abs(mj), np.abs(mk)
    mrule = (ak == ai + aj) | (ak == np.abs(ai - aj))
    neg = (mi < 0).astype(int) + (mj < 0) + (mk < 0)
    return tri & mrule & (neg % 2 == 0)


@functools.lru_cache(maxsize=None)
def sparse_gaunt(bands: int) -> SparseGaunt:
    """The Gaunt tensor of ``bands`` bands in sparse form (cached, read-only)."""
    n = check_bands(bands)
    if n > MAX_TENSOR_BANDS:
        raise ValueError(f"triple products are supported up to {MAX_TENSOR_BANDS} bands, got {n}")
    K = n * n
    d, w = gauss_sphere(3 * (n - 1))
    y = eval_basis(d, n)
    allowed = _allowed_mask(n)
    ii, jj, kk, vv = [], [], [], []
    for i in range(K):
        # tau[i] = sum_q w_q y_i(q) y_j(q) y_k(q), one (K, K) slab at a time.
        slab = (y * (w * y[:, i])[:, None]).T @ y
        j, k = np.nonzero(allowed[i])
        ii.append(np.full(j.shape, i))
        jj.append(j)
        kk.append(k)
        vv.append(slab[j, k])
    arrays = [np.concatenate(a).astype(np.int32) for a in (ii, jj, kk)]
    value = np.concatenate(vv)
    for a in (*arrays, value):
        a.setflags(write=False)
    return SparseGaunt(n, *arrays, value)


def triple_product_tensor(bands: int) -> np.ndarray:
    """Dense Gaunt tensor tau_ijk = integral y_i y_j y_k, shape (K, K, K), float64."""
    return sparse_gaunt(bands).dense()


def tpfl_matrix(light, bands: int | None = None) -> np.ndarray:
    """Fixed-light product matrix M_ik = sum_j tau_ijk L_j.

    light : (K,) SH light, or (K, 3) RGB light (coefficient axis first).
    bands : the light's band count (checked against K); inferred when None.
    Returns (K, K) for (K,) light, (3, K, K) for (K, 3) light, float64.
    Apply as ``Lp = M @ T`` (M is symmetric).
    """
    L = np.asarray(light, dtype=np.float64)
    if L.ndim not in (1, 2) or L.shape[0] == 0:
        raise ValueError(f"light must have shape (K,) or (K, C), got {L.shape}")
    if not np.all(np.isfinite(L)):
        raise ValueError("light coefficients contain NaN or Inf")
    n = bands_of(L.shape[0]) if bands is None else check_bands(bands)
    if L.shape[0] != n * n:
        raise ValueError(f"light has {L.shape[0]} coefficients but bands={n} needs {n * n}")
    g = sparse_gaunt(n)
    K = n * n
    flat_ik = g.i.astype(np.int64) * K + g.k
    if L.ndim == 1:
        return np.bincount(flat_ik, weights=g.value * L[g.j], minlength=K * K).reshape(K, K)
    out = np.empty((L.shape[1], K, K))
    for c in range(L.shape[1]):
        out[c] = np.bincount(flat_ik, weights=g.value * L[g.j, c], minlength=K * K).reshape(K, K)
    return out


def triple_product(a, b, bands: int | None = None) -> np.ndarray:
    """SH coefficients of the product of two SH functions, truncated to ``bands``.

    a, b : (K,) or (K, C) (broadcast over C). O(nnz) with the sparse tensor.
    """
    A = np.asarray(a, dtype=np.float64)
    B = np.asarray(b, dtype=np.float64)
    n = bands_of(A.shape[0]) if bands is None else check_bands(bands)
    if A.shape[0] != n * n or B.shape[0] != n * n:
        raise ValueError(f"both inputs need {n * n} coefficients, got {A.shape[0]} and {B.shape[0]}")
    g = sparse_gaunt(n)
    terms = g.value.reshape((-1,) + (1,) * (max(A.ndim, B.ndim) - 1)) * A[g.i] * B[g.j]
    out = np.zeros((n * n,) + terms.shape[1:])
    np.add.at(out, g.k, terms)
    return out
