"""An environment image's sun taken out of it (issue 48, item 3): the
brightest compact region of an equirect image becomes a sun (direction,
disc, energy) and the image without it is left to the SH.

Band 5 cannot hold an HDRI's sun: projected with the sky, a 0.5 degree
sun of a fifth of the image's energy becomes a soft blob with ringing, and
its shadows vanish. Taken out, it is baked as a sun with a mask (crisp
shadows, its light per pixel: core/light/sun.py) and the rest, smooth, stays
in the SH.

Conventions: the image is (H, W, 3) linear RGB in file order (row 0 = +Z),
core.light.envmap's equirect mapping, directions in the image's own frame
(a World's Mapping rotation is applied by the caller). Energies are W/m² on
a surface facing the sun at image strength 1 (sum of radiance times pixel
solid angle).

The region: the pixels 8-connected to the brightest pixel (wrapping around
in longitude) whose luminance is at least REGION_FRACTION of it and
SKY_FACTOR times the image's median; its
background is the median colour of a ring of RING pixels around it; each
region pixel gives its excess over the background. The sun's direction is
the energy-weighted mean direction, its disc the uniform disc with the same
energy-weighted mean of 1 - cos (for a disc of half-angle a that mean is
(1 - cos a) / 2), and the residual image has the region's pixels set to the
background. It is a sun only if it holds at least MIN_SHARE of the image's
energy (luminance) and its disc is at most core.light.sun.MAX_ANGLE wide;
otherwise :func:`extract_sun` says why and returns None.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from .envmap import pixel_directions, pixel_solid_angles
from .sun import MAX_ANGLE

#: Rec. 709 luminance weights.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
#: A pixel belongs to the sun's region if its luminance is at least this
#: fraction of the brightest pixel's and SKY_FACTOR times the image's median
#: (the sky: a faint sun's region must not spread over it), and it touches
#: the region.
REGION_FRACTION = 0.02
SKY_FACTOR = 2.0
#: The largest region taken (pixels): a sun is compact; a bright sky is not.
MAX_REGION_PIXELS = 4096
#: Pixels around the region whose median colour is the sky behind the sun.
RING = 3
#: The least share of the image's energy a sun holds (a brightest pixel of
#: less is not a dominant light: the SH carries it as well).
MIN_SHARE = 0.05


@dataclasses.dataclass(frozen=True)
class ExtractedSun:
    """What :func:`extract_sun` takes out: ``direction`` (3,) unit towards it
    (the image's frame), ``angle`` the equivalent disc's full angle
    (radians), ``energy`` (3,) W/m² facing it at strength 1, ``share`` its
    part of the image's luminous energy, ``pixels`` the region's size."""

    direction: tuple
    angle: float
    energy: tuple
    share: float
    pixels: int


def extract_sun(image: np.ndarray) -> tuple[ExtractedSun | None, np.ndarray, str]:
    """(the sun or None, the image without it (a copy; the image itself when
    no sun is taken), why none was taken ("" when one was)) of an equirect
    ``image`` (H, W, 3). Deterministic; float64 sums."""
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] < 3 or img.shape[0] < 4 or img.shape[1] < 8:
        raise ValueError(f"an equirect image is (H, W, 3) of at least 8 x 4 pixels, got {img.shape}")
    rgb = img[..., :3]
    if not np.isfinite(rgb).all():
        raise ValueError("the image has non-finite pixels")
    H, W = rgb.shape[:2]
    Y = np.maximum(rgb.astype(np.float64) @ LUMINANCE, 0.0)
    omega = pixel_solid_angles(H, W)
    total = float((Y * omega[:, None]).sum())
    r0, c0 = np.unravel_index(int(np.argmax(Y)), Y.shape)
    peak = float(Y[r0, c0])
    if not (peak > 0.0 and total > 0.0):
        return None, img, "the image is black"
    region = _region(Y >= max(REGION_FRACTION * peak, SKY_FACTOR * float(np.median(Y))), r0, c0)
    if region is None:
        return None, img, (f"its brightest region is not compact (over {MAX_REGION_PIXELS} pixels at "
                           f"{REGION_FRACTION:g} of the peak): no dominant light")
    ring = _ring(region, RING) & ~region
    bg = np.median(rgb[ring].astype(np.float64), axis=0) if ring.any() else np.zeros(3)
    bg = np.maximum(bg, 0.0)
    rows, cols = np.nonzero(region)
    excess = np.maximum(rgb[rows, cols].astype(np.float64) - bg, 0.0)           # (n, 3)
    w = omega[rows]
    energy = (excess * w[:, None]).sum(axis=0)
    lum = float((excess @ LUMINANCE * w).sum())
    share = lum / total
    if share < MIN_SHARE:
        return None, img, (f"its brightest region holds {share:.1%} of the image's light, under "
                           f"{MIN_SHARE:.0%}: no dominant light")
    dirs = pixel_directions(H, W)[rows, cols]
    weight = excess @ LUMINANCE * w
    d = (dirs * weight[:, None]).sum(axis=0)
    d /= np.linalg.norm(d)
    spread = float((weight * (1.0 - dirs @ d)).sum() / weight.sum())
    half = math.acos(max(-1.0, 1.0 - 2.0 * spread))
    angle = 2.0 * half
    if angle > MAX_ANGLE:
        return None, img, (f"its brightest region is {math.degrees(angle):.0f} degrees wide, over the "
                           f"{math.degrees(MAX_ANGLE):.0f} a sun may be: left to the SH")
    out = np.array(img, copy=True)
    out[rows, cols, :3] = np.minimum(rgb[rows, cols], bg.astype(out.dtype))
    return ExtractedSun(tuple(float(v) for v in d), float(angle), tuple(float(v) for v in energy), share,
                        int(rows.size)), out, ""


def _region(mask: np.ndarray, r0: int, c0: int) -> np.ndarray | None:
    """The 8-connected component of ``mask`` holding (r0, c0), columns
    wrapping around; None once it grows past MAX_REGION_PIXELS."""
    H, W = mask.shape
    seen = np.zeros_like(mask)
    seen[r0, c0] = True
    todo = [(r0, c0)]
    n = 1
    while todo:
        r, c = todo.pop()
        for dr in (-1, 0, 1):
            rr = r + dr
            if not 0 <= rr < H:
                continue
            for dc in (-1, 0, 1):
                cc = (c + dc) % W
                if mask[rr, cc] and not seen[rr, cc]:
                    seen[rr, cc] = True
                    n += 1
                    if n > MAX_REGION_PIXELS:
                        return None
                    todo.append((rr, cc))
    return seen


def _ring(region: np.ndarray, width: int) -> np.ndarray:
    """``region`` grown by ``width`` pixels (8-neighbourhood, columns wrapping)."""
    out = region.copy()
    for _ in range(width):
        grown = out.copy()
        grown[1:] |= out[:-1]
        grown[:-1] |= out[1:]
        grown |= np.roll(out, 1, axis=1) | np.roll(out, -1, axis=1)
        out = grown
    return out
