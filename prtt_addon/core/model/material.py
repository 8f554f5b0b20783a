"""A surface's material as a job describes it: the Principled BSDF's
parameters PRTT shades with (core/shading/materials.py turns them into
shading parameters), validated on construction from a job's JSON."""
from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Material:
    name: str = "default"
    base_color: tuple = (0.8, 0.8, 0.8)     # linear RGB
    metallic: float = 0.0
    roughness: float = 0.5
    specular: float = 0.5                   # Principled "Specular IOR Level"
    ior: float = 1.5
    base_color_texture: int = -1            # index into Scene.textures, -1 = none
    roughness_texture: int = -1

    @classmethod
    def from_dict(cls, d: dict) -> "Material":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown material fields {sorted(unknown)}")
        m = cls(**{k: (tuple(v) if k == "base_color" else v) for k, v in d.items()})
        m.validate()
        return m

    def validate(self) -> None:
        bc = np.asarray(self.base_color, dtype=float)
        if bc.shape != (3,) or not np.all(np.isfinite(bc)) or bc.min() < 0:
            raise ValueError(f"base_color must be 3 finite values >= 0, got {self.base_color}")
        for name in ("metallic", "roughness", "specular"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0.0 <= v <= 1.0):
                raise ValueError(f"{name} must be in [0, 1], got {v!r}")
        if not (isinstance(self.ior, (int, float)) and 1.0 <= self.ior <= 10.0):
            raise ValueError(f"ior must be in [1, 10], got {self.ior!r}")
        for name in ("base_color_texture", "roughness_texture"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < -1:
                raise ValueError(f"{name} must be an integer >= -1, got {v!r}")

    @property
    def textured(self) -> bool:
        return self.base_color_texture >= 0 or self.roughness_texture >= 0

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["base_color"] = list(self.base_color)
        return d


DEFAULT = Material()
