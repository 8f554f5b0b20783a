"""Equirectangular environment maps <-> RGB SH, in Blender's world orientation.

Orientation (that of the World's Environment Texture node, verified against a
Cycles render in tests/test_envmap_blender.py): for a unit direction
d = (x, y, z), Z up,
    u = 0.5 - atan2(y, x) / (2 pi)        (0 at the left edge of the image)
    v = 1 - acos(z) / pi                  (1 at the top row, i.e. +Z)
so the image centre looks along +X, u = 0.25 along +Y, u = 0.75 along -Y.
Arrays here are (H, W, C) in file order (row 0 = top = +Z). Pixel (i, j) covers
theta in [pi i / H, pi (i+1) / H] and phi = atan2(y, x) in
[pi - 2 pi (j+1) / W, pi - 2 pi j / W].

Projection methods (``method=``):

* ``"area"`` (default): each pixel is a patch of constant radiance and the
  basis is integrated *exactly* over the patch (solid angle
  dphi (cos theta0 - cos theta1) and its higher moments), so
  c_k = sum_p L_p integral_p y_k dw. A constant map gives exactly
  (sqrt(4 pi) L, 0, 0, ...). Right for real HDRIs with small bright suns.
* ``"samples"``: each pixel is a point sample at its centre, weighted by
  Fejer's first rule in cos(theta) times uniform phi. Exact (to rounding) for
  band-limited maps: project(reconstruct(c)) == c when H, W > 2 (bands - 1).

Negative pixels (lossy-compression artefacts, e.g. -0.002 in Blender's
forest.exr) are clamped to 0; NaN/Inf pixels are an error.

The light a bake and the preview shade with (:func:`compose_light`,
:func:`environment_light`, used by both command lines and the World export):
the projection times a strength, turned as a World's Mapping node turns it.
"""
from __future__ import annotations

import functools
import glob
import importlib.util
import math
import os
import sys

import numpy as np

from ..io.image_io import ImageReadError, read_hdr_image
from ..sh.basis import bands_of, check_bands, eval_basis, lm_of
from ..sh.rotation import rotate

#: Environment variable naming a folder of equirect EXRs to use as built-ins.
STUDIOLIGHTS_ENV = "PRTT_STUDIOLIGHTS_DIR"


# --- orientation ------------------------------------------------------------

def direction_to_uv(dirs) -> np.ndarray:
    """(N, 3) unit directions -> (N, 2) equirect (u, v), v = 1 at the top (+Z)."""
    d = np.asarray(dirs, dtype=np.float64)
    u = 0.5 - np.arctan2(d[:, 1], d[:, 0]) / (2.0 * math.pi)
    v = 1.0 - np.arccos(np.clip(d[:, 2], -1.0, 1.0)) / math.pi
    return np.stack([u % 1.0, v], axis=-1)


def uv_to_direction(uv) -> np.ndarray:
    """(N, 2) equirect (u, v) -> (N, 3) unit directions (inverse of direction_to_uv)."""
    uv = np.asarray(uv, dtype=np.float64)
    phi = math.pi * (1.0 - 2.0 * uv[:, 0])
    theta = math.pi * (1.0 - uv[:, 1])
    s = np.sin(theta)
    return np.stack([s * np.cos(phi), s * np.sin(phi), np.cos(theta)], axis=-1)


def pixel_directions(height: int, width: int) -> np.ndarray:
    """(H, W, 3) directions of pixel centres, file order (row 0 = top)."""
    theta = math.pi * (np.arange(height) + 0.5) / height
    phi = math.pi - 2.0 * math.pi * (np.arange(width) + 0.5) / width
    st = np.sin(theta)[:, None]
    return np.stack(
        [st * np.cos(phi)[None, :], st * np.sin(phi)[None, :],
         np.broadcast_to(np.cos(theta)[:, None], (height, width))], axis=-1)


def pixel_solid_angles(height: int, width: int) -> np.ndarray:
    """(H,) exact solid angle of one pixel in each row: dphi (cos t0 - cos t1)."""
    edges = np.cos(math.pi * np.arange(height + 1) / height)
    return (2.0 * math.pi / width) * (edges[:-1] - edges[1:])


# --- separable basis tables ----------------------------------------------------
# y_lm(theta, phi) = Theta_lm(theta) * Phi_m(phi) with Phi_0 = 1,
# Phi_m = cos(m phi) (m > 0), sin(|m| phi) (m < 0). Phi columns are indexed
# by m + (bands - 1), i.e. 2 bands - 1 columns.

def _m_columns(n: int) -> np.ndarray:
    return np.array([lm_of(k)[1] for k in range(n * n)]) + (n - 1)


def _theta_profile(theta: np.ndarray, n: int) -> np.ndarray:
    """(T, K) Theta_lm(theta): y_lm at phi = 0 for m >= 0, mirrored to m < 0."""
    dirs = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=-1)
    y = eval_basis(dirs, n)
    for k in range(n * n):
        l, m = lm_of(k)
        if m < 0:
            y[:, k] = y[:, l * l + l - m]
    return y


def _phi_profile(phi: np.ndarray, n: int) -> np.ndarray:
    """(P, 2n-1) Phi_m(phi) for m = -(n-1) .. n-1."""
    out = np.empty((phi.shape[0], 2 * n - 1))
    for m in range(-(n - 1), n):
        out[:, m + n - 1] = np.cos(m * phi) if m >= 0 else np.sin(-m * phi)
    return out


@functools.lru_cache(maxsize=16)
def _area_tables(height: int, width: int, n: int):
    """Exact per-pixel integrals: rows (H, K) of Theta sin, columns (W, 2n-1) of Phi."""
    # Theta_lm(theta) sin(theta) is a trigonometric polynomial of degree <= l+1;
    # Gauss-Legendre with n + 8 nodes per row integrates it to rounding.
    q = n + 8
    x, wq = np.polynomial.legendre.leggauss(q)
    t0 = math.pi * np.arange(height) / height
    half = 0.5 * math.pi / height
    theta = (t0[:, None] + half * (x[None, :] + 1.0)).ravel()
    prof = _theta_profile(theta, n) * np.sin(theta)[:, None]
    rows = (prof.reshape(height, q, n * n) * (wq * half)[None, :, None]).sum(axis=1)
    # Phi integrals in closed form over [phi_hi(j+1), phi_hi(j)].
    p_hi = math.pi - 2.0 * math.pi * np.arange(width) / width
    p_lo = p_hi - 2.0 * math.pi / width
    cols = np.empty((width, 2 * n - 1))
    for m in range(-(n - 1), n):
        if m == 0:
            cols[:, n - 1] = p_hi - p_lo
        elif m > 0:
            cols[:, m + n - 1] = (np.sin(m * p_hi) - np.sin(m * p_lo)) / m
        else:
            a = -m
            cols[:, m + n - 1] = (np.cos(a * p_lo) - np.cos(a * p_hi)) / a
    return rows, cols


def _fejer_weights(height: int) -> np.ndarray:
    """Fejer's first rule for integral_0^pi g(theta) sin(theta) dtheta at
    theta_i = pi (i + 1/2) / H; exact for polynomials in cos(theta) of degree < H."""
    theta = math.pi * (np.arange(height) + 0.5) / height
    k = np.arange(1, height // 2 + 1)
    s = (np.cos(2.0 * np.outer(theta, k)) / (4.0 * k * k - 1.0)).sum(axis=1)
    return (2.0 / height) * (1.0 - 2.0 * s)


@functools.lru_cache(maxsize=16)
def _sample_tables(height: int, width: int, n: int):
    theta = math.pi * (np.arange(height) + 0.5) / height
    phi = math.pi - 2.0 * math.pi * (np.arange(width) + 0.5) / width
    prof = _theta_profile(theta, n)
    rows = prof * _fejer_weights(height)[:, None]
    cols = _phi_profile(phi, n) * (2.0 * math.pi / width)
    return prof, _phi_profile(phi, n), rows, cols


# --- projection / reconstruction ---------------------------------------------------

def as_environment_image(image_or_path, *, clamp_negative: bool = True) -> np.ndarray:
    """Load/validate an equirect image -> (H, W, 3) float64.

    Negative values are clamped to 0 unless ``clamp_negative`` is false (for
    signed test functions; radiance is never negative).

    Accepts a path, a built-in name ("forest", see :func:`builtin_environments`),
    or an array (H, W), (H, W, 3) or (H, W, 4) (alpha ignored), file order.
    """
    if isinstance(image_or_path, (str, os.PathLike)):
        s = os.fspath(image_or_path)
        if os.sep not in s and "." not in s and not os.path.exists(s):
            s = builtin_environment_path(s)
        img = read_hdr_image(s)
    else:
        img = np.asarray(image_or_path)
    if img.dtype.kind not in "fiu":
        raise ValueError(f"environment image must be numeric, got dtype {img.dtype}")
    if img.ndim == 2:
        img = img[..., None].repeat(3, axis=-1)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise ValueError(f"environment image must be (H, W, 3|4), got shape {img.shape}")
    if img.shape[0] < 1 or img.shape[1] < 1:
        raise ValueError(f"environment image is empty: shape {img.shape}")
    img = np.asarray(img[..., :3], dtype=np.float64)
    bad = ~np.isfinite(img)
    if bad.any():
        raise ValueError(f"environment image has {int(bad.any(axis=-1).sum())} NaN/Inf pixels")
    return np.maximum(img, 0.0) if clamp_negative else img


def project_equirect(image_or_path, bands: int, *, method: str = "area",
                     clamp_negative: bool = True) -> np.ndarray:
    """Project an equirect environment to RGB SH: returns (K, 3) float64.

    image_or_path : see :func:`as_environment_image`.
    method : "area" (exact pixel integrals, default) or "samples" (band-limited
    quadrature at pixel centres); see the module docstring.
    clamp_negative : clamp negative pixels to 0 (default; see module docstring).
    """
    n = check_bands(bands)
    img = as_environment_image(image_or_path, clamp_negative=clamp_negative)
    H, W, _ = img.shape
    if method == "area":
        rows, cols = _area_tables(H, W, n)
    elif method == "samples":
        _, _, rows, cols = _sample_tables(H, W, n)
    else:
        raise ValueError(f"unknown projection method {method!r}; use 'area' or 'samples'")
    per_m = np.einsum("hwc,wm->hmc", img, cols)          # (H, 2n-1, 3)
    mcol = _m_columns(n)
    return np.einsum("hk,hkc->kc", rows, per_m[:, mcol, :])


def reconstruct_equirect(coeffs, height: int, width: int | None = None) -> np.ndarray:
    """Evaluate SH at the pixel centres of an H x W equirect map (file order).

    coeffs : (K,) or (K, C). Returns (H, W) or (H, W, C) float64.
    """
    c = np.asarray(coeffs, dtype=np.float64)
    n = bands_of(c.shape[0])
    width = 2 * height if width is None else width
    prof, phi_prof, _, _ = _sample_tables(int(height), int(width), n)
    mcol = _m_columns(n)
    squeeze = c.ndim == 1
    c2 = c.reshape(c.shape[0], -1)
    per_m = np.zeros((height, 2 * n - 1, c2.shape[1]))
    np.add.at(per_m, (slice(None), mcol), prof[:, :, None] * c2[None, :, :])
    out = np.einsum("hmc,wm->hwc", per_m, phi_prof)
    return out[..., 0] if squeeze else out


# --- the light: an environment scaled and turned as a World does it -------------------

def euler_xyz_matrix(rx: float, ry: float, rz: float) -> np.ndarray:
    """Blender's Euler XYZ rotation (radians): R = Rz @ Ry @ Rx."""
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def mapping_rotation(rotation_xyz, vector_type: str = "POINT") -> np.ndarray:
    """The rotation R a World's Mapping node applies to lookup directions
    (the image is read at R w): its Euler XYZ rotation for type Point, the
    inverse (transpose) for type Texture. ValueError for angles that are not
    three finite numbers (a World's settings are user input)."""
    try:
        angles = [float(a) for a in rotation_xyz]
    except (TypeError, ValueError) as exc:
        raise ValueError(f"World rotation {rotation_xyz!r} is not three numbers") from exc
    if len(angles) != 3 or not all(math.isfinite(a) for a in angles):
        raise ValueError(f"World rotation {angles} is not three finite angles")
    R = euler_xyz_matrix(*angles)
    return R if vector_type == "POINT" else R.T


#: The largest light coefficient a World may give: the bake's bounce and the
#: preview multiply it by transfer in float32 (max 3.4e38), with headroom.
LIGHT_MAX = 1e30


def compose_light(projection: np.ndarray, strength: float = 1.0,
                  lookup_rotation: np.ndarray | None = None) -> np.ndarray:
    """The world-frame (K, 3) SH light from the unrotated, unscaled projection
    of an environment (:func:`project_equirect`, or :func:`constant_light`).

    Conventions: world space is Z up, the image in the orientation of the
    module docstring. ``strength`` multiplies the light (the Background
    node's Strength). ``lookup_rotation`` is R of a Mapping node
    (:func:`mapping_rotation`): lookups turn by R, so the light seen in
    direction w is L(w) = img(R w), and its coefficients are the image's
    rotated by R^T (``sh.rotate(c, Q)`` turns a function by Q: it returns the
    coefficients of w -> f(Q^T w)). The environment therefore appears turned
    the other way from the Mapping's angles. None: no Mapping node.
    """
    if not isinstance(strength, (int, float, np.floating, np.integer)) or not math.isfinite(strength):
        raise ValueError(f"World strength {strength!r} is not a finite number")
    with np.errstate(over="ignore", invalid="ignore"):
        L = np.asarray(projection, np.float64) * float(strength)
    if not np.isfinite(L).all():
        raise ValueError(f"World light is not finite at strength {float(strength):g} (the environment's "
                         f"projection times the strength overflows, or the projection holds NaN/Inf)")
    if L.size and np.abs(L).max() > LIGHT_MAX:
        raise ValueError(f"World light of {np.abs(L).max():.3g} is beyond {LIGHT_MAX:g}: the bake and the "
                         f"preview compute in float32 (lower the strength or the colour)")
    if lookup_rotation is not None:
        L = rotate(L, np.asarray(lookup_rotation).T)
    return L


def constant_light(rgb, bands: int) -> np.ndarray:
    """(K, 3) SH of a constant environment of colour ``rgb`` (the DC term only);
    ValueError for a colour that is not three finite numbers."""
    c = np.asarray(rgb, np.float64).reshape(-1)
    if c.shape != (3,) or not np.isfinite(c).all() or np.abs(c).max() > 1e300:
        raise ValueError(f"World colour {c.tolist()} is not three finite numbers")
    L = np.zeros((bands * bands, 3))
    L[0] = c * math.sqrt(4.0 * math.pi)
    return L


def environment_light(source, bands: int, strength: float = 1.0, rotation_z_deg: float = 0.0) -> np.ndarray:
    """(K, 3) SH light from an environment (an .exr/.hdr path, pixels or a
    built-in name: :func:`as_environment_image`), its strength and the Z
    rotation of a Point-type Mapping node in degrees (0: no rotation)
    (:func:`compose_light` gives the conventions)."""
    L = project_equirect(source, bands)
    R = mapping_rotation((0.0, 0.0, math.radians(rotation_z_deg))) if rotation_z_deg else None
    return compose_light(L, strength, R)


# --- built-in environments ----------------------------------------------------------

def _studiolight_dirs() -> list[str]:
    dirs = []
    env = os.environ.get(STUDIOLIGHTS_ENV)
    if env:
        dirs.append(env)
    bpy_mod = sys.modules.get("bpy")   # inside Blender: ask it, never import it here
    if bpy_mod is not None and hasattr(bpy_mod, "utils"):
        try:
            p = bpy_mod.utils.system_resource("DATAFILES", path="studiolights/world")
            if p:
                dirs.append(p)
        except Exception:
            pass
    spec = importlib.util.find_spec("bpy") if bpy_mod is None else None
    roots = list(spec.submodule_search_locations or []) if spec else []
    if spec and spec.origin:
        roots.append(os.path.dirname(spec.origin))
    for root in roots:
        dirs.extend(sorted(glob.glob(os.path.join(root, "*", "datafiles", "studiolights", "world"))))
    return [d for d in dict.fromkeys(dirs) if os.path.isdir(d)]


def builtin_environments() -> dict[str, str]:
    """{name: path} of Blender's bundled studio HDRIs (forest, sunset, city, ...)."""
    out: dict[str, str] = {}
    for d in _studiolight_dirs():
        for p in sorted(glob.glob(os.path.join(d, "*.exr"))):
            out.setdefault(os.path.splitext(os.path.basename(p))[0], p)
    return out


def builtin_environment_path(name: str) -> str:
    """Path of a built-in environment by name; a clear error lists the choices."""
    envs = builtin_environments()
    if name in envs:
        return envs[name]
    if not envs:
        raise ImageReadError(
            f"built-in environment {name!r} not found: Blender's studio lights are not "
            f"available (install bpy or set {STUDIOLIGHTS_ENV})")
    raise ImageReadError(f"unknown built-in environment {name!r}; choose one of {', '.join(envs)}")
