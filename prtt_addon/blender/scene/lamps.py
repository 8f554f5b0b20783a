"""The scene's lamps as PRTT takes them (issue 48): a Sun lamp becomes the
bake's sun (core.light.sun.Sun: its mask baked, its light drawn live); every
lamp PRTT does not take is named in one line.

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

import numpy as np

from ...core.light.sun import MAX_ANGLE, Sun, SunError
from . import world_panorama


def rendered_lamps(scene, view_layer=None) -> list:
    """Light objects that light the render: in the view layer, not disabled in
    renders, with power."""
    layer = view_layer if view_layer is not None else scene.view_layers[0]
    return [ob for ob in layer.objects
            if ob.type == "LIGHT" and not ob.hide_render and getattr(ob.data, "energy", 0.0) > 0]


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
               strength=strength, name=ob.name)


def sky_sun_world(scene, view_layer=None):
    """The World whose Sky Texture's disc is the scene's sun, or None: the
    ``sky_sun`` option on, the World the light, no rendering Sun lamp, and one
    measurable disc (world_panorama.sky_sun_nodes) in a local World's nodes.
    Cheap: reads nodes, renders nothing."""
    st = getattr(scene, "prtt", None)
    if st is not None and (not getattr(st, "sky_sun", True) or getattr(st, "light_source", "WORLD") != "WORLD"):
        return None
    world = scene.world
    if world is None or world.node_tree is None or world.library is not None:
        return None
    if any(ob.data.type == "SUN" for ob in rendered_lamps(scene, view_layer)):
        return None
    return world if len(world_panorama.sky_sun_nodes(world.node_tree, wide=True)) == 1 else None


def sky_sun_of(world, error=ValueError, on_ready=None) -> Sun | None:
    """The Sky Texture's sun of ``world`` as a core Sun (named "<World>: <node>"),
    from its measurement (world_panorama.sky_sun: a render, cached with the
    World's panorama), or None when the disc is too faint to measure.
    Strength: the largest of its RGB energy (W/m²); colour: energy / strength."""
    m = world_panorama.sky_sun(world, error, on_ready)
    if m is None:
        return None
    strength = float(np.max(m.energy))
    return Sun(direction=tuple(m.direction), angle=min(m.angle, MAX_ANGLE),
               color=tuple(float(v) / strength for v in m.energy), strength=strength,
               name=f"{world.name}: {m.node}")


def scene_sun(scene, view_layer=None) -> tuple:
    """(Sun or None, the lamp object it is (None for a sky's sun), notes (list
    of one-line strings)): the brightest rendering Sun lamp as the bake's sun,
    or without one the World's Sky Texture sun (:func:`sky_sun_world`; a
    render the first time, cached: Pending inside Blender's drawing)."""
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
        world = sky_sun_world(scene, view_layer)
        if world is not None:
            try:
                sun = sky_sun_of(world)
            except SunError as exc:
                notes.append(f"the World's Sky Texture sun: {exc}; not baked")
                sun = None
            except ValueError as exc:         # the World's own render failed: the light says why
                notes.append(f"the World's Sky Texture sun could not be measured ({exc})")
                sun = None
            if sun is not None:
                return sun, None, notes
        return None, None, notes
    taken.sort(key=lambda so: -so[0].strength * sum(so[0].color) / 3.0)
    sun, ob = taken[0]
    if len(taken) > 1:
        others = ", ".join(repr(o.name) for _, o in taken[1:4])
        notes.append(f"PRTT bakes one sun, {ob.name!r} (the brightest); not {others}"
                     + (f" and {len(taken) - 4} more" if len(taken) > 4 else ""))
    if not getattr(ob.data, "use_shadow", True):
        notes.append(f"Sun {ob.name!r} casts no shadow in Blender; PRTT bakes its shadows")
    st = getattr(scene, "prtt", None)
    if world_has_sky_sun(scene) and getattr(st, "sky_sun", True) and getattr(st, "light_source", "WORLD") == "WORLD":
        notes.append(f"the World's Sky Texture sun stays in the World's soft light, without shadows: PRTT bakes "
                     f"one sun, the lamp {ob.name!r}")
    return sun, ob, notes


def world_has_sky_sun(scene) -> bool:
    """The scene's World has one Sky Texture with a measurable sun disc (the Sky Sun option applies)."""
    w = scene.world
    return w is not None and w.node_tree is not None and len(world_panorama.sky_sun_nodes(w.node_tree, wide=True)) == 1


def unbaked_lamps(scene, view_layer=None) -> str:
    """A one-line note naming the scene's lamps that light Cycles' render but
    not PRTT's ("" when there are none): every rendering lamp but the sun PRTT
    takes (scene_sun); with scene_sun's own notes."""
    _, _, notes = scene_sun(scene, view_layer)
    # Suns PRTT does not take are in the notes already.
    lamps = [ob for ob in rendered_lamps(scene, view_layer) if ob.data.type != "SUN"]
    parts = list(notes)
    if lamps:
        named = ", ".join(f"{ob.data.type.title()} {ob.name!r}" for ob in lamps[:4]) + (
            f" and {len(lamps) - 4} more" if len(lamps) > 4 else "")
        parts.append(f"{len(lamps)} lamp(s) light Cycles' render but not PRTT's (point, spot and area lamps are "
                     f"not baked yet): {named}")
    return "; ".join(parts)
