"""Point and spot lamps (Blender's Point and Spot lights; issue 49).

A lamp is near: its light falls off with distance and its direction changes
across a surface, so like the sun it is kept apart from the environment's SH
(Unity's shadowmask model): the bake stores, per texel, the visible fraction
of the lamp's sphere (the lamp's *mask*, core/bake/estimators/lamp_mask.py),
and the preview adds its direct light per pixel with the mask as its shadow,
so its colour, power and a spot's cone change live.

Conventions (Z-up world, as the scene; Cycles' lights, measured against
Cycles in tests/test_lamps.py):

* ``position`` (3,) world metres; ``radius`` the sphere's radius (Blender's
  *Radius*, ``shadow_soft_size``), 0 a point.
* ``power`` (W) and linear ``color``: the radiant intensity is
  ``power * color / (4 pi)`` W/sr in every direction, a spot's as its point's
  (Blender: a spot's power is that of the point lamp it is cut from), so the
  irradiance facing the lamp at distance r is ``I / r^2``.
* A spot shines along unit ``axis`` (its object's local -Z), full cone angle
  ``spot_size`` (radians) and ``spot_blend`` in [0, 1]: with
  c = cos(half the cone) and t = (cos(angle to the axis) - c) / ((1 - c) blend),
  the attenuation is smoothstep(clamp(t, 0, 1)) (Cycles' spot_light_attenuation;
  a blend of 0 is a hard cone). Cycles evaluates it along each ray to a point
  of the lamp's sphere, so seen from a point at distance r the cone's edge is
  averaged over the sphere's disc of angular radius a = asin(R / r): over the
  angle from the axis, whose offset across a uniform disc has the semicircle
  density; five Gauss-Chebyshev nodes (a cos(k pi / 6), k = 1..5, weights
  sin^2(k pi / 6) / 3) integrate a smoothstep over it to within 2e-3 for a
  blend at least twice the disc (tests/test_lamps.py).
  Non-uniform spot scales are not modelled.
* ``shadow``: False for a lamp whose *Shadow* is off: nothing blocks it,
  its mask is 1 (traced nowhere).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math

import numpy as np

#: Gauss-Chebyshev (second kind) nodes and weights of the semicircle density on [-1, 1]:
#: the angle's offset across a uniform disc (Lamp.spot; prtt_shade.glsl lamp_light).
SPREAD_NODES = tuple((math.cos(k * math.pi / 6.0), math.sin(k * math.pi / 6.0) ** 2 / 3.0) for k in range(1, 6))
#: Lamps a texture set's masks hold: one RGBA texture, one channel a lamp (Unity's shadowmask: four).
MAX_LAMPS = 4
#: Rays a texel traces to a lamp's sphere (as the sun's disc: core.light.sun.SUN_RAYS).
LAMP_RAYS = 256
KINDS = ("POINT", "SPOT")


class LampError(ValueError):
    """A lamp that cannot be baked (said in one line)."""


def _vector(v, what: str, name: str) -> tuple:
    a = np.asarray(v, np.float64).reshape(-1)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise LampError(f"lamp {name!r}: {what} must be 3 finite numbers, got {v!r}")
    return tuple(float(x) for x in a)


@dataclasses.dataclass(frozen=True)
class Lamp:
    kind: str                  # "POINT" or "SPOT"
    position: tuple            # (3,) world metres
    radius: float = 0.0        # metres
    power: float = 1000.0      # W
    color: tuple = (1.0, 1.0, 1.0)
    axis: tuple = (0.0, 0.0, -1.0)   # a spot's unit direction of shining
    spot_size: float = math.radians(45.0)   # full cone angle, radians
    spot_blend: float = 0.15
    name: str = "Lamp"
    shadow: bool = True

    def __post_init__(self):
        name = str(self.name)[:200]
        object.__setattr__(self, "name", name)
        if self.kind not in KINDS:
            raise LampError(f"lamp {name!r}: kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        object.__setattr__(self, "position", _vector(self.position, "position", name))
        ax = np.asarray(_vector(self.axis, "axis", name))
        n = float(np.linalg.norm(ax))
        if not n > 1e-12:
            raise LampError(f"lamp {name!r}: axis has no length")
        if abs(n - 1.0) > 4.0 * np.finfo(np.float64).eps:
            ax = ax / n
        object.__setattr__(self, "axis", tuple(float(x) for x in ax))
        c = np.asarray(self.color, np.float64).reshape(-1)
        if c.shape != (3,) or not np.isfinite(c).all() or (c < 0).any():
            raise LampError(f"lamp {name!r}: colour must be 3 non-negative numbers, got {self.color!r}")
        object.__setattr__(self, "color", tuple(float(x) for x in c))
        for field, lo, hi in (("radius", 0.0, 1e4), ("power", 0.0, 1e12), ("spot_size", 0.0, math.pi),
                              ("spot_blend", 0.0, 1.0)):
            v = getattr(self, field)
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise LampError(f"lamp {name!r}: {field} must be a number, got {v!r}") from None
            if not (math.isfinite(v) and lo <= v <= hi):
                raise LampError(f"lamp {name!r}: {field} {v!r} is outside [{lo:g}, {hi:g}]")
            object.__setattr__(self, field, v)
        if not isinstance(self.shadow, bool):
            raise LampError(f"lamp {name!r}: shadow must be true or false, got {self.shadow!r}")

    @property
    def intensity(self) -> np.ndarray:
        """(3,) W/sr: power * colour / (4 pi)."""
        return self.power * np.asarray(self.color, np.float64) / (4.0 * math.pi)

    @property
    def cos_half_cone(self) -> float:
        """cos(half the spot's cone); -1 for a point lamp (no cone)."""
        return math.cos(0.5 * self.spot_size) if self.kind == "SPOT" else -1.0

    @property
    def spot_smooth(self) -> float:
        """1 / ((1 - cos half cone) blend): the spot's smoothstep scale (inf for a hard cone or a point)."""
        width = (1.0 - self.cos_half_cone) * self.spot_blend
        return 1.0 / width if self.kind == "SPOT" and width > 0.0 else math.inf

    def spot(self, towards_point: np.ndarray, spread=0.0) -> np.ndarray:
        """(N,) the spot's attenuation along unit directions (N, 3) from the
        lamp towards points (1 for a point), averaged over the sphere's disc
        of angular radius ``spread`` ((N,) or scalar radians) as seen there
        (module docstring)."""
        d = np.asarray(towards_point, np.float64)
        if self.kind != "SPOT":
            return np.ones(d.shape[0])
        theta = np.arccos(np.clip(d @ np.asarray(self.axis), -1.0, 1.0))
        a = np.asarray(spread, np.float64)

        def at(th):
            t = (np.cos(th) - self.cos_half_cone) * self.spot_smooth
            t = np.clip(np.nan_to_num(t, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
            return t * t * (3.0 - 2.0 * t)
        return sum(w * at(theta + x * a) for x, w in SPREAD_NODES)

    def irradiance(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((N, 3) unit directions from ``points`` (N, 3) towards the lamp,
        (N, 3) W/m² facing it there, the spot's cone and the distance's 1/r² in)."""
        p = np.asarray(points, np.float64)
        to = np.asarray(self.position) - p
        r2 = np.maximum(np.einsum("nc,nc->n", to, to), 1e-12)
        l = to / np.sqrt(r2)[:, None]
        spread = np.arcsin(np.minimum(self.radius / np.sqrt(r2), 1.0))
        return l, (self.spot(-l, spread) / r2)[:, None] * self.intensity[None, :]

    def mask_key(self) -> dict:
        """What the mask depends on: where the lamp is, its size, whether it
        shadows (not colour, power or a spot's cone: those are drawn live)."""
        key = {"position": [round(v, 9) for v in self.position], "radius": round(self.radius, 9)}
        if not self.shadow:
            key["shadow"] = False
        return key

    def mask_hash(self) -> str:
        return hashlib.sha256(json.dumps(self.mask_key(), sort_keys=True).encode()).hexdigest()

    def as_dict(self) -> dict:
        return {"kind": self.kind, "name": self.name, "position": list(self.position), "radius": self.radius,
                "power": self.power, "color": list(self.color), "axis": list(self.axis),
                "spot_size": self.spot_size, "spot_blend": self.spot_blend,
                **({} if self.shadow else {"shadow": False})}

    @classmethod
    def from_dict(cls, d) -> "Lamp":
        """A lamp from a job file's or manifest's JSON (untrusted: LampError on anything else)."""
        if not isinstance(d, dict):
            raise LampError(f"lamp: expected a JSON object, got {type(d).__name__}")
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - fields
        if unknown:
            raise LampError(f"lamp: unknown field(s) {', '.join(sorted(map(str, unknown)))}")
        if "kind" not in d or "position" not in d:
            raise LampError("lamp: missing field 'kind' or 'position'")
        try:
            return cls(**d)
        except LampError:
            raise
        except (TypeError, ValueError) as exc:
            raise LampError(f"lamp: {exc}") from None

    def moved_from(self, baked: "Lamp", tolerance: float = 1e-4) -> str | None:
        """Why a mask baked for ``baked`` does not hold for this lamp (moved, resized, Shadow toggled), or None."""
        moved = float(np.linalg.norm(np.subtract(self.position, baked.position)))
        if moved > tolerance:
            return f"the lamp {self.name!r} moved {moved:.3g} m since the bake"
        if abs(self.radius - baked.radius) > tolerance:
            return f"the lamp {self.name!r}'s radius is {self.radius:.3g} m, baked at {baked.radius:.3g}"
        if self.shadow != baked.shadow:
            return f"the lamp {self.name!r}'s Shadow is {'on' if self.shadow else 'off'}, baked {'on' if baked.shadow else 'off'}"
        return None


def lamps_from_list(specs) -> tuple:
    """Lamps from a JSON list (untrusted): at most MAX_LAMPS, LampError otherwise."""
    if not isinstance(specs, list):
        raise LampError(f"lamps: expected a JSON list, got {type(specs).__name__}")
    if len(specs) > MAX_LAMPS:
        raise LampError(f"lamps: {len(specs)} lamps, a set's masks hold {MAX_LAMPS}")
    return tuple(Lamp.from_dict(s) for s in specs)


def lamps_hash(lamps) -> str:
    """The masks' key part of ``lamps`` (in order: channel i is lamp i)."""
    return hashlib.sha256("|".join(lp.mask_hash() for lp in lamps).encode()).hexdigest()
