"""``python -m prtt_addon env``: project an environment to SH and report errors.

Prints the RGB coefficients and two reconstruction errors:

* radiance: solid-angle-weighted relative RMS of the band-limited map against
  the map itself (large for HDRIs with a sun: SH cannot hold a point light);
* irradiance: the clamped-cosine-convolved SH (what diffuse PRT shades with)
  against brute-force integration of the full map over the hemisphere of 64
  normals (pixel solid angle x max(0, n.w)), max and mean error relative to
  the mean irradiance.
"""
from __future__ import annotations

import math
import time

import numpy as np

from .core import sh
from .core.light import envmap


def fibonacci_dirs(n: int) -> np.ndarray:
    """(n, 3) near-uniform unit directions (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = math.pi * (1.0 + 5.0 ** 0.5) * i
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def brute_force_irradiance(img: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(N, 3) irradiance integral L(w) max(0, n.w) dw over every pixel of ``img``."""
    H, W, _ = img.shape
    d = envmap.pixel_directions(H, W).reshape(-1, 3)
    lw = (img * envmap.pixel_solid_angles(H, W)[:, None, None]).reshape(-1, 3)
    out = np.empty((normals.shape[0], 3))
    for s in range(0, normals.shape[0], 16):
        cos = np.clip(normals[s:s + 16] @ d.T, 0.0, None)
        out[s:s + 16] = cos @ lw
    return out


def report(source: str, bands: int, method: str = "area", out=print) -> dict:
    t0 = time.perf_counter()
    img = envmap.as_environment_image(source)
    t1 = time.perf_counter()
    coeffs = envmap.project_equirect(img, bands, method=method)
    t2 = time.perf_counter()
    H, W, _ = img.shape
    out(f"environment: {source}  ({W}x{H}, read in {t1 - t0:.3f} s)")
    out(f"projected to {bands} bands ({bands * bands} RGB coefficients, method={method}) "
        f"in {t2 - t1:.3f} s")
    out(f"{'k':>3} {'l':>2} {'m':>3} {'R':>12} {'G':>12} {'B':>12}")
    for k in range(bands * bands):
        l, m = sh.lm_of(k)
        out(f"{k:3d} {l:2d} {m:3d} " + " ".join(f"{v:12.6f}" for v in coeffs[k]))

    rec = envmap.reconstruct_equirect(coeffs, H, W)
    w = envmap.pixel_solid_angles(H, W)[:, None, None]
    rad_err = math.sqrt(float(np.sum(w * (rec - img) ** 2)) / float(np.sum(w * img ** 2)))

    normals = fibonacci_dirs(64)
    ref = brute_force_irradiance(img, normals)
    irr = sh.eval_basis(normals, bands) @ sh.convolve(coeffs, sh.clamped_cosine_factors(bands))
    # Relative to the mean irradiance: a normal facing away from a sun has
    # tiny irradiance, where a pointwise relative error says little.
    rel = np.abs(irr - ref) / float(ref.mean())
    out(f"radiance reconstruction error (relative RMS): {rad_err:.4f}")
    out(f"irradiance error vs brute force over 64 normals, relative to the mean "
        f"irradiance: max {rel.max():.5f}, mean {rel.mean():.5f}")
    return {"coeffs": coeffs, "radiance_rel_rms": rad_err,
            "irradiance_max_rel": float(rel.max()), "irradiance_mean_rel": float(rel.mean())}
