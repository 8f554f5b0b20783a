"""Zonal lobes, convolution with them, and ringing windows.

A zonal function h(cos alpha) around +Z has only m = 0 coefficients
h_l = <h, y_l0>. Convolving a function f with it (Funk-Hecke) scales band l by
    A_l = sqrt(4 pi / (2l + 1)) h_l,
so  (h * f)_lm = A_l f_lm. ``A_l`` are the "convolution factors" returned here;
evaluating the convolved SH at a direction d gives integral f(w) h(w . d) dw.

Lobes, all as functions of t = cos(alpha) on the upper hemisphere, 0 below:

* clamped cosine max(0, t):  A = pi, 2 pi / 3, pi / 4, 0, -pi / 24, 0, pi / 64, ...
* normalised Phong lobe of exponent s >= 0: (s + 1) / (2 pi) t^s, whose integral
  over the sphere is 1 (so a constant environment L reflects to L).

Both reduce to I_l(a) = integral_0^1 t^a P_l(t) dt, computed by the exact and
stable recurrence I_l = (a - l + 2) / (a + l + 1) I_{l-2}, I_0 = 1/(a+1),
I_1 = 1/(a+2), so A_l = 2 pi c I_l(a) for the lobe c t^a.

Windows against ringing (Sloan, "Stupid SH Tricks"), per-band factors w_l that
multiply band l, all off unless asked for (``window=None``):

* "hanning":  w_l = (1 + cos(pi l / W)) / 2 for l < W, else 0;
* "lanczos":  w_l = sinc(l / W) = sin(pi l / W) / (pi l / W), w_0 = 1;
with window width W defaulting to ``bands`` (so no band is fully zeroed).
"""
from __future__ import annotations

import math

import numpy as np

from .basis import band_of_coeffs, bands_of, check_bands, eval_basis


def power_cosine_integrals(a: float, bands: int) -> np.ndarray:
    """I_l(a) = integral_0^1 t^a P_l(t) dt for l < bands, float64, a >= 0."""
    n = check_bands(bands)
    a = float(a)
    if not math.isfinite(a) or a < 0:
        raise ValueError(f"lobe exponent must be finite and >= 0, got {a}")
    out = np.empty(n)
    out[0] = 1.0 / (a + 1.0)
    if n > 1:
        out[1] = 1.0 / (a + 2.0)
    for l in range(2, n):
        out[l] = (a - l + 2.0) / (a + l + 1.0) * out[l - 2]
    return out


def clamped_cosine_factors(bands: int) -> np.ndarray:
    """Convolution factors A_l of max(0, cos): pi, 2pi/3, pi/4, 0, -pi/24, ..."""
    return 2.0 * math.pi * power_cosine_integrals(1.0, bands)


def clamped_cosine_zh(bands: int) -> np.ndarray:
    """ZH coefficients h_l = <max(0, cos theta), y_l0> (about +Z)."""
    l = np.arange(check_bands(bands))
    return clamped_cosine_factors(bands) * np.sqrt((2 * l + 1) / (4.0 * math.pi))


def phong_factors(exponent, bands: int) -> np.ndarray:
    """Convolution factors of the normalised Phong lobe (s+1)/(2 pi) cos^s.

    ``exponent`` may be a scalar (returns (bands,)) or an array of shape S
    (returns S + (bands,)). A_0 = 1 for every s (the lobe integrates to 1);
    A_l ~ exp(-l^2 / (2 s)) for large s.
    """
    n = check_bands(bands)
    s = np.asarray(exponent, dtype=np.float64)
    if not np.all(np.isfinite(s)) or np.any(s < 0):
        raise ValueError("Phong exponents must be finite and >= 0")
    # Vectorised form of power_cosine_integrals, times (s + 1).
    out = np.empty(s.shape + (n,))
    out[..., 0] = 1.0
    if n > 1:
        out[..., 1] = (s + 1.0) / (s + 2.0)
    for l in range(2, n):
        out[..., l] = (s - l + 2.0) / (s + l + 1.0) * out[..., l - 2]
    return out


def convolve(coeffs, factors, *, axis: int = 0) -> np.ndarray:
    """Scale every band l of ``coeffs`` by ``factors[l]`` along ``axis``.

    coeffs : SH coefficients with K = bands**2 along ``axis``.
    factors : (bands,) convolution factors (e.g. from :func:`phong_factors`).
    """
    c = np.asarray(coeffs, dtype=np.float64)
    f = np.asarray(factors, dtype=np.float64)
    n = bands_of(c.shape[axis])
    if f.shape != (n,):
        raise ValueError(f"need {n} per-band factors for {n * n} coefficients, got shape {f.shape}")
    per_k = f[band_of_coeffs(n)]
    shape = [1] * c.ndim
    shape[axis] = n * n
    return c * per_k.reshape(shape)


def zonal_to_sh(factors, direction) -> np.ndarray:
    """SH coefficients of a zonal lobe turned to point along ``direction``.

    By the addition theorem, h(w . d) = sum_lm h_l sqrt(4 pi / (2l+1)) y_lm(d) y_lm(w),
    so the lobe with convolution factors A_l, centred on unit d, has
    c_lm = A_l y_lm(d). ``direction`` (N, 3) or (3,); returns (N, K) or (K,).
    """
    f = np.asarray(factors, dtype=np.float64)
    n = f.shape[-1]
    y = eval_basis(direction, n)
    return y * f[band_of_coeffs(n)]


def window_factors(bands: int, kind: str | None = None, width: float | None = None) -> np.ndarray:
    """Per-band ringing window: ones when ``kind`` is None, else hanning/lanczos."""
    n = check_bands(bands)
    if kind is None or kind == "none":
        return np.ones(n)
    W = float(n if width is None else width)
    if not W > 0:
        raise ValueError(f"window width must be > 0, got {width}")
    l = np.arange(n, dtype=np.float64)
    if kind == "hanning":
        return np.where(l < W, 0.5 * (1.0 + np.cos(math.pi * l / W)), 0.0)
    if kind == "lanczos":
        return np.sinc(l / W)
    raise ValueError(f"unknown window {kind!r}; choose 'hanning', 'lanczos' or None")
