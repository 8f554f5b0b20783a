"""Materials of the reference shading model: Lambert diffuse + normalised Phong.

A material is what the Principled BSDF gives us; shading uses three derived,
possibly textured, quantities per point (docs/shading.md):

* diffuse albedo   rho_d = base_color * (1 - metallic)
* specular weight  k_s   = (1 - metallic) * F0 + metallic * base_color,
                   F0    = ((ior - 1) / (ior + 1))^2 * 2 * specular
  (Blender 4.x's "Specular IOR Level" 0.5 leaves the IOR's own F0: 0.04 at 1.5)
* Phong exponent   s     = 1 / (2 alpha^2) - 1/2, alpha = roughness^2,
  clamped to [0, MAX_EXPONENT]: the Blinn-Phong exponent equivalent to GGX,
  2 / alpha^2 - 2, divided by 4 for a lobe about the reflection vector.
  Roughness 1 gives s = 0 (the lobe covers the hemisphere), 0.5 gives 7.5,
  0.1 gives 5000.

The glossy lobe is the normalised Phong lobe (s + 1) / (2 pi) cos^s about the
reflection direction (zonal.phong_factors); the cosine factor of the rendering
equation is already in the transfer.

Textures: ``base_color_texture`` (RGB, linear) and ``roughness_texture``
(first channel) index the scene's ``textures`` and are sampled bilinearly at
the triangle's ``mat_uvs``; they replace the constant values (spatially varying
albedo and roughness, as in the paper).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..model.material import DEFAULT, Material
from ..texels.texsample import bilinear_repeat

#: Exponent for roughness 0 (a mirror has no finite Phong exponent).
MAX_EXPONENT = 10000.0




def phong_exponent(roughness) -> np.ndarray:
    """Phong exponent about the reflection vector for Principled roughness."""
    r = np.clip(np.asarray(roughness, dtype=np.float64), 0.0, 1.0)
    alpha2 = r ** 4
    with np.errstate(divide="ignore"):
        s = 0.5 / alpha2 - 0.5
    return np.clip(np.where(alpha2 > 0, s, MAX_EXPONENT), 0.0, MAX_EXPONENT)


def dielectric_f0(ior, specular) -> np.ndarray:
    return ((np.asarray(ior) - 1.0) / (np.asarray(ior) + 1.0)) ** 2 * 2.0 * np.asarray(specular)


@dataclasses.dataclass
class ShadingParams:
    """Per-point parameters: albedo (N, 3), spec (N, 3), exponent (N,); and
    metallic (N,) and the dielectric F0 (N,) where known (the sun's
    microfacet lobe reads them: shade.sun_direct; None: a dielectric of
    F0 = spec)."""

    albedo: np.ndarray
    spec: np.ndarray
    exponent: np.ndarray
    metallic: np.ndarray | None = None
    f0: np.ndarray | None = None

    @classmethod
    def constant(cls, n: int, material: Material = DEFAULT) -> "ShadingParams":
        return derive(np.tile(material.base_color, (n, 1)), np.full(n, material.metallic),
                      np.full(n, material.roughness), np.full(n, material.specular), np.full(n, material.ior))

    def take(self, idx) -> "ShadingParams":
        return ShadingParams(self.albedo[idx], self.spec[idx], self.exponent[idx],
                             None if self.metallic is None else self.metallic[idx],
                             None if self.f0 is None else self.f0[idx])


def derive(base, metallic, roughness, specular, ior) -> ShadingParams:
    """Principled values per point -> ShadingParams (formulas in the module doc)."""
    return derive_from_f0(base, metallic, roughness, dielectric_f0(ior, specular))


def derive_from_f0(base, metallic, roughness, f0) -> ShadingParams:
    """As :func:`derive`, with the dielectric F0 (N,) already folded from ior and specular."""
    base = np.asarray(base, dtype=np.float64)
    m = np.asarray(metallic, dtype=np.float64)[:, None]
    f0 = np.asarray(f0, dtype=np.float64)[:, None]
    return ShadingParams(base * (1.0 - m), (1.0 - m) * f0 + m * base, phong_exponent(roughness),
                         m[:, 0].copy(), np.broadcast_to(f0, m.shape)[:, 0].copy())


def sample_texture(img_top_first: np.ndarray, uv: np.ndarray) -> np.ndarray:
    return bilinear_repeat(img_top_first, uv)


def eval_materials(sc, tri: np.ndarray, bary: np.ndarray) -> ShadingParams:
    """Shading parameters at points on triangles ``tri`` with barycentrics ``bary``.

    Untextured materials (and the default, for triangles without one) are
    derived once each and gathered per point: the same elementwise formulas
    on the same values as per point, ~10x less work on a 1024² G-buffer."""
    n = tri.shape[0]
    mats = [Material.from_dict(m) for m in sc.materials]
    k = len(mats)
    mid = sc.material_id[tri] if sc.material_id is not None else np.full(n, -1)
    table = mats + [DEFAULT]                                # row k: the default
    per_mat = derive(np.array([m.base_color for m in table], np.float64),
                     np.array([m.metallic for m in table], np.float64),
                     np.array([m.roughness for m in table], np.float64),
                     np.array([m.specular for m in table], np.float64),
                     np.array([m.ior for m in table], np.float64))
    row = np.where((mid >= 0) & (mid < k), mid, k)
    albedo, spec, exponent = per_mat.albedo[row], per_mat.spec[row], per_mat.exponent[row]
    metallic, f0 = per_mat.metallic[row], per_mat.f0[row]
    for i, mat in enumerate(mats):
        if not mat.textured:
            continue
        sel = np.flatnonzero(mid == i)
        if sel.size == 0:
            continue
        base = np.tile(np.asarray(mat.base_color, np.float64), (sel.size, 1))
        rough = np.full(sel.size, mat.roughness, np.float64)
        uv = np.einsum("nk,nkc->nc", bary[sel], sc.mat_uvs[tri[sel]])
        if mat.base_color_texture >= 0:
            rgb = sample_texture(sc.textures[mat.base_color_texture], uv)
            base = np.maximum(rgb[:, :3] if rgb.shape[1] >= 3 else np.repeat(rgb[:, :1], 3, 1), 0.0)
        if mat.roughness_texture >= 0:
            rough = np.clip(sample_texture(sc.textures[mat.roughness_texture], uv)[:, 0], 0.0, 1.0)
        p = derive(base, np.full(sel.size, mat.metallic), rough, np.full(sel.size, mat.specular),
                   np.full(sel.size, mat.ior))
        albedo[sel], spec[sel], exponent[sel] = p.albedo, p.spec, p.exponent
    return ShadingParams(albedo, spec, exponent, metallic, f0)


def materials_hash(sc) -> str:
    """sha256 of everything materials contribute (for stale bounce textures)."""
    import hashlib
    import json
    h = hashlib.sha256(json.dumps(sc.materials, sort_keys=True).encode())
    for a in (sc.material_id, sc.mat_uvs):
        if a is not None:
            h.update(np.ascontiguousarray(a).tobytes())
    for t in sc.textures:
        h.update(t.tobytes())
    return h.hexdigest()

