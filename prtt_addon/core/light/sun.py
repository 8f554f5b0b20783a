"""A sun: a distant light of a small angular disc (Blender's Sun lamp; issue 48).

Band 5 cannot hold a sun: an environment's SH blurs a 0.5 degree disc into a
blob with ringing, and its shadows into nothing. So a sun is kept apart from
the environment's SH, as Unity's shadowmask keeps a light: the bake stores, per
texel, the visible fraction of the sun's disc (the *mask*:
core/bake/estimators/sun_mask.py) and the preview adds the sun's direct light
per pixel (core/shading/shade.sun_direct) with the mask as its shadow.

Conventions (Z-up world, as the scene):

* ``direction``: unit vector from the scene *towards* the sun (Blender's Sun
  shines along its object's local -Z; this is its +Z in world space).
* ``angle``: the disc's full angular diameter in radians (Blender's Sun
  ``angle``, 0.526 degrees by default); 0 is a point at infinity.
* ``color`` (linear RGB) and ``strength`` (W/m²): the irradiance on a surface
  facing the sun is ``strength * color`` (Cycles' convention: a white diffuse
  plane facing a Sun of strength 1 renders at 1 / pi). Neither changes the
  mask: they are applied at shading time and change live.
* ``shadow``: False for a Sun whose *Shadow* is off in Blender: nothing
  blocks it, its mask is 1 everywhere (traced nowhere).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math

import numpy as np

#: The largest disc a sun may have (Blender allows 180 degrees): beyond this
#: a "sun" is an area of sky, which the environment's SH carries better.
MAX_ANGLE = math.radians(30.0)
#: Rays a texel traces to its sun's disc: the mask's steps are 1 / SUN_RAYS
#: (stratified, so a penumbra is smooth at this count; bench sun). 64 left a
#: 5 degree sun's shadowed floor 2.2 % from Cycles, most of it the mask's own
#: noise; 256 bring it to 1.6 %. Refined (sun_mask), only penumbra texels
#: trace them all, so the cost grows with the penumbrae.
SUN_RAYS = 256


class SunError(ValueError):
    """A sun that cannot be baked (said in one line)."""


@dataclasses.dataclass(frozen=True)
class Sun:
    direction: tuple          # (3,) unit, towards the sun
    angle: float              # radians, full angular diameter
    color: tuple = (1.0, 1.0, 1.0)
    strength: float = 1.0     # W/m²
    name: str = "Sun"
    shadow: bool = True       # False: casts no shadow (Blender's Shadow off): the mask is 1

    def __post_init__(self):
        d = np.asarray(self.direction, np.float64).reshape(-1)
        if d.shape != (3,) or not np.isfinite(d).all():
            raise SunError(f"sun {self.name!r}: direction must be 3 finite numbers, got {self.direction!r}")
        n = float(np.linalg.norm(d))
        if not n > 1e-12:
            raise SunError(f"sun {self.name!r}: direction has no length")
        # A unit vector is kept as it is: normalising it again can move it by an
        # ulp, so a sun read back from its own JSON would differ from itself.
        if abs(n - 1.0) > 4.0 * np.finfo(np.float64).eps:
            d = d / n
        object.__setattr__(self, "direction", tuple(float(v) for v in d))
        a = float(self.angle)
        if not (math.isfinite(a) and 0.0 <= a <= MAX_ANGLE):
            raise SunError(f"sun {self.name!r}: angle {math.degrees(a) if math.isfinite(a) else a:.4g} degrees "
                           f"is outside [0, {math.degrees(MAX_ANGLE):g}]")
        object.__setattr__(self, "angle", a)
        c = np.asarray(self.color, np.float64).reshape(-1)
        if c.shape != (3,) or not np.isfinite(c).all() or (c < 0).any():
            raise SunError(f"sun {self.name!r}: colour must be 3 non-negative numbers, got {self.color!r}")
        object.__setattr__(self, "color", tuple(float(v) for v in c))
        s = float(self.strength)
        if not (math.isfinite(s) and s >= 0.0):
            raise SunError(f"sun {self.name!r}: strength must be a non-negative number, got {self.strength!r}")
        object.__setattr__(self, "strength", s)
        object.__setattr__(self, "name", str(self.name)[:200])
        if not isinstance(self.shadow, bool):
            raise SunError(f"sun {self.name!r}: shadow must be true or false, got {self.shadow!r}")

    @property
    def irradiance(self) -> np.ndarray:
        """(3,) W/m² on a surface facing the sun: strength * colour."""
        return self.strength * np.asarray(self.color, np.float64)

    @property
    def cos_half_angle(self) -> float:
        return math.cos(0.5 * self.angle)

    def mask_key(self) -> dict:
        """What the mask depends on: direction and disc, and whether it casts a
        shadow (not colour, strength or name). A shadowing sun's key is the
        one it had before ``shadow`` existed."""
        key = {"direction": [round(v, 12) for v in self.direction], "angle": round(self.angle, 12)}
        if not self.shadow:
            key["shadow"] = False
        return key

    def mask_hash(self) -> str:
        return hashlib.sha256(json.dumps(self.mask_key(), sort_keys=True).encode()).hexdigest()

    def as_dict(self) -> dict:
        return {"name": self.name, "direction": list(self.direction), "angle": self.angle,
                "color": list(self.color), "strength": self.strength, **({} if self.shadow else {"shadow": False})}

    @classmethod
    def from_dict(cls, d) -> "Sun":
        """A sun from a job file's or manifest's JSON (untrusted: SunError on anything else)."""
        if not isinstance(d, dict):
            raise SunError(f"sun: expected a JSON object, got {type(d).__name__}")
        unknown = set(d) - {"name", "direction", "angle", "color", "strength", "shadow"}
        if unknown:
            raise SunError(f"sun: unknown field(s) {', '.join(sorted(map(str, unknown)))}")
        try:
            return cls(direction=d["direction"], angle=d["angle"], color=d.get("color", (1.0, 1.0, 1.0)),
                       strength=d.get("strength", 1.0), name=d.get("name", "Sun"), shadow=d.get("shadow", True))
        except KeyError as exc:
            raise SunError(f"sun: missing field {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            if isinstance(exc, SunError):
                raise
            raise SunError(f"sun: {exc}") from None

    def moved_from(self, baked: "Sun", tolerance_deg: float = 0.01) -> str | None:
        """Why a mask baked for ``baked`` does not hold for this sun (its direction
        or disc changed by more than ``tolerance_deg``), or None."""
        cos = float(np.clip(np.dot(self.direction, baked.direction), -1.0, 1.0))
        turned = math.degrees(math.acos(cos))
        if turned > tolerance_deg:
            return f"the sun {self.name!r} turned {turned:.2f} degrees since the bake"
        if self.shadow != baked.shadow:
            return f"the sun {self.name!r}'s Shadow is {'on' if self.shadow else 'off'}, baked {'on' if baked.shadow else 'off'}"
        if abs(math.degrees(self.angle - baked.angle)) > tolerance_deg:
            return (f"the sun {self.name!r}'s angle is {math.degrees(self.angle):.3g} degrees, baked at "
                    f"{math.degrees(baked.angle):.3g}")
        return None
