"""The scene's lamps as PRTT takes them (issue 48): a Sun lamp becomes the
bake's sun (core.light.sun.Sun: its mask baked, its light drawn live), up to
four Point and Spot lamps become its lamps (core.light.lamp.Lamp, issue 49:
their masks baked, their light drawn live); every lamp PRTT does not take is
named in one line.

What renders is what counts: Light objects in the view layer, not disabled in
renders, with power. One sun is baked, the brightest (strength times the
colour's mean); other suns, and point, spot and area lamps (not baked yet),
are named. A Sun's light is ``energy`` (W/m²) times ``2^exposure`` (Blender
4.5 on) times its colour (its temperature's colour where ``use_temperature``,
Blender 5 on), as Cycles lights with it.

Without a Sun lamp, the sun disc of the World's Sky Texture is the sun
(``scene.prtt.sky_sun``, on by default): its direction, size and energy as
Cycles renders the World (world_panorama.sky_sun), its mask baked, and the
World's SH made of the sky without it (world.world_setup). With a Sun lamp
the lamp is the sun and the disc stays in the World's SH, as it does with
``sky_sun`` off.
"""
from __future__ import annotations

import math

from ...core.light.lamp import MAX_LAMPS, Lamp, LampError
from ...core.light.sun import MAX_ANGLE, Sun, SunError
from .scene_objects import rendered_lamps
from .world import world_has_sky_sun, world_sun


def lamp_colour(light) -> tuple:
    """The lamp's linear RGB as Cycles lights with it (its temperature's colour when it uses one)."""
    c = tuple(float(v) for v in light.color)
    if getattr(light, "use_temperature", False):
        t = tuple(float(v) for v in light.temperature_color)
        c = tuple(a * b for a, b in zip(c, t))
    return c


def sun_of(ob) -> Sun:
    """A Sun lamp object as a core Sun (SunError when its disc is too wide to be a sun)."""
    light = ob.data
    z = ob.matrix_world.to_3x3().col[2]          # a Sun shines along its local -Z
    strength = float(light.energy) * 2.0 ** float(getattr(light, "exposure", 0.0))
    return Sun(direction=(z.x, z.y, z.z), angle=float(light.angle), color=lamp_colour(light),
               strength=strength, name=ob.name, shadow=bool(getattr(light, "use_shadow", True)))


def scene_sun(scene, view_layer=None) -> tuple:
    """(Sun or None, the lamp object it is (None for the World's sun), notes
    (list of one-line strings)): the brightest rendering Sun lamp as the
    bake's sun, or without one the World's sun (world.world_sun: its Sky
    Texture's disc, a render the first time, cached, Pending inside Blender's
    drawing; or its image's extracted sun)."""
    suns = [ob for ob in rendered_lamps(scene, view_layer) if ob.data.type == "SUN"]
    notes = []
    taken = []
    for ob in suns:
        try:
            taken.append((sun_of(ob), ob))
        except SunError as exc:
            if float(ob.data.angle) > MAX_ANGLE:
                notes.append(f"Sun {ob.name!r}: its angle of {math.degrees(ob.data.angle):.0f} degrees is wider than "
                             f"a sun PRTT bakes ({math.degrees(MAX_ANGLE):.0f} at most): not baked")
            else:
                notes.append(f"Sun {ob.name!r}: {exc}; not baked")
    if not taken:
        sun, note = world_sun(scene, view_layer)
        return sun, None, notes + ([note] if note else [])
    taken.sort(key=lambda so: -so[0].strength * sum(so[0].color) / 3.0)
    sun, ob = taken[0]
    if len(taken) > 1:
        others = ", ".join(repr(o.name) for _, o in taken[1:4])
        notes.append(f"PRTT bakes one sun, {ob.name!r} (the brightest); not {others}"
                     + (f" and {len(taken) - 4} more" if len(taken) > 4 else ""))
    st = getattr(scene, "prtt", None)
    if world_has_sky_sun(scene) and getattr(st, "sky_sun", True) and getattr(st, "light_source", "WORLD") == "WORLD":
        notes.append(f"the World's Sky Texture sun stays in the World's soft light, without shadows: PRTT bakes "
                     f"one sun, the lamp {ob.name!r}")
    elif getattr(st, "hdri_sun", False) and getattr(st, "light_source", "WORLD") == "WORLD":
        notes.append(f"HDRI Sun: the World image's sun stays in the World's soft light: PRTT bakes one sun, the "
                     f"lamp {ob.name!r}")
    return sun, ob, notes


def lamp_of(ob) -> Lamp:
    """A Point or Spot lamp object as a core Lamp (LampError for one it cannot take)."""
    light = ob.data
    m = ob.matrix_world
    z = m.to_3x3().col[2]                        # a spot shines along its local -Z
    power = float(light.energy) * 2.0 ** float(getattr(light, "exposure", 0.0))
    spot = light.type == "SPOT"
    return Lamp(kind=light.type, position=tuple(m.translation), radius=float(light.shadow_soft_size),
                power=power, color=lamp_colour(light), axis=(-z.x, -z.y, -z.z),
                spot_size=float(light.spot_size) if spot else math.radians(45.0),
                spot_blend=float(light.spot_blend) if spot else 0.15, name=ob.name,
                shadow=bool(getattr(light, "use_shadow", True)))


def scene_lamps(scene, view_layer=None) -> tuple:
    """(Lamps (core.light.lamp.Lamp, at most MAX_LAMPS, brightest first), notes):
    the rendering Point and Spot lamps PRTT bakes (their masks, their light
    drawn live), and one-line notes for those it does not (beyond MAX_LAMPS,
    or a spot scaled unevenly: its ellipse is drawn round)."""
    obs = [ob for ob in rendered_lamps(scene, view_layer) if ob.data.type in ("POINT", "SPOT")]
    taken, notes = [], []
    for ob in obs:
        try:
            taken.append(lamp_of(ob))
        except LampError as exc:
            notes.append(f"{ob.data.type.title()} {ob.name!r}: {exc}; not baked")
            continue
        sx, sy, _ = ob.matrix_world.to_scale()
        if ob.data.type == "SPOT" and abs(sx - sy) > 1e-4 * max(abs(sx), abs(sy), 1e-12):
            notes.append(f"Spot {ob.name!r} is scaled unevenly: PRTT draws its cone round")
    taken.sort(key=lambda lp: (-lp.power * sum(lp.color) / 3.0, lp.name))
    if len(taken) > MAX_LAMPS:
        rest = taken[MAX_LAMPS:]
        notes.append(f"PRTT bakes {MAX_LAMPS} point and spot lamps, the brightest; not "
                     + ", ".join(repr(lp.name) for lp in rest[:4]) + (f" and {len(rest) - 4} more" if len(rest) > 4 else ""))
    return tuple(taken[:MAX_LAMPS]), notes


def unbaked_lamps(scene, view_layer=None) -> str:
    """A one-line note naming the scene's lamps that light Cycles' render but
    not PRTT's ("" when there are none): area lamps, suns and lamps beyond
    what PRTT takes (scene_sun, scene_lamps); with their own notes."""
    _, _, notes = scene_sun(scene, view_layer)
    # Suns PRTT does not take are in the notes already, points and spots in scene_lamps'.
    parts = list(notes) + scene_lamps(scene, view_layer)[1]
    lamps = [ob for ob in rendered_lamps(scene, view_layer) if ob.data.type not in ("SUN", "POINT", "SPOT")]
    if lamps:
        named = ", ".join(f"{ob.data.type.title()} {ob.name!r}" for ob in lamps[:4]) + (
            f" and {len(lamps) - 4} more" if len(lamps) > 4 else "")
        parts.append(f"{len(lamps)} lamp(s) light Cycles' render but not PRTT's (area lamps are "
                     f"not baked yet): {named}")
    return "; ".join(parts)
