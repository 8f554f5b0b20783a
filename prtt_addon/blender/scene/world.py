"""The scene's World as a spherical-harmonic light.

Node setups read directly (exactly, and turned live by their Mapping node):

    [Texture Coordinate (Generated/Object)] -> [Mapping] -> [Environment Texture]
        -> [Background] -> [World Output]
    [Background] with an unlinked colour (a constant environment)

Any other World (Sky Texture, gradients, mixes, an HDRI behind other nodes, a
Mapping node of another type) is rendered by Cycles as an equirectangular
panorama and projected like an HDRI (world_panorama.py; the description says
so and why). Refused in one line: no World, no connected output, a World
image without pixels, a Light Path node (what lights the scene is not what a
camera sees), non-finite values.

* The Environment Texture's image is read from its file (EXR/HDR, through
  core.io.image_io) or, for packed/generated images, from Blender's pixels
  (byte sRGB images are linearised).
* Background strength multiplies the light.
* The World's sun (:func:`world_sun`, without a Sun lamp in the scene): a Sky
  Texture's disc (``scene.prtt.sky_sun``, on by default) or, for an image
  World, its brightest compact region (``scene.prtt.hdri_sun``, off by
  default: core.light.sun_extract) becomes the bake's sun, and the World's
  SH is made of the World without it.
* The Mapping node's rotation (Euler XYZ, types Point and Texture) turns the
  light by an SH rotation (core.light.envmap.compose_light states the
  conventions: lookups turn by R, so the image's SH rotates by R^T).
  Location and scale do not change a direction lookup's result for
  rotation-only use and are ignored (scale must be uniform).

The numbers (projection, strength, rotation, a constant colour's SH) are
core.light.envmap's, shared with ``python -m prtt_addon bake-job --env``.
"""
from __future__ import annotations

import dataclasses
import math
import os

import numpy as np

from ...core.io.image_io import read_hdr_image
from ...core.light import envmap
from ...core.light.sun import MAX_ANGLE, Sun, SunError
from ...core.light.sun_extract import extract_sun
from . import world_panorama
from .material_nodes import image_array
from .scene_objects import rendered_lamps


class WorldLightError(ValueError):
    """The World's nodes are not a setup PRTT can turn into SH light."""


def _linked(socket):
    return socket.links[0].from_node if socket.is_linked else None


def environment_file(image) -> str:
    """The EXR/HDR file the World image's pixels are read from, or "" when they
    come from Blender (packed, generated, another format, missing)."""
    if image.source != "FILE" or image.packed_file:
        return ""
    import bpy
    path = bpy.path.abspath(image.filepath, library=image.library)
    return path if path and os.path.isfile(path) and path.lower().endswith((".exr", ".hdr")) else ""


def _image_pixels(image) -> np.ndarray:
    """(H, W, 3) float32 in file order (top row first), linear."""
    path = environment_file(image)
    if path:
        return read_hdr_image(path)
    px = image_array(image, linearise=True)          # reloads an image without data
    if px.size == 0:
        raise WorldLightError(f"World image {image.name!r} has no pixels (missing file {image.filepath!r}?)")
    rgb = px[..., :3] if image.channels >= 3 else np.repeat(px[..., :1], 3, axis=-1)
    return np.ascontiguousarray(rgb, dtype=np.float32)


def mapping_rotation(node) -> np.ndarray:
    """The rotation a Mapping node applies to lookup directions."""
    if node.vector_type not in {"POINT", "TEXTURE"}:
        raise WorldLightError(f"Mapping node {node.name!r}: type {node.vector_type} is not supported "
                              f"(use Point or Texture)")
    for name in ("Rotation", "Scale"):
        if node.inputs[name].is_linked:
            raise WorldLightError(f"Mapping node {node.name!r}: a linked {name} is not supported")
    try:
        return envmap.mapping_rotation(node.inputs["Rotation"].default_value, node.vector_type)
    except ValueError as exc:
        raise WorldLightError(f"Mapping node {node.name!r}: {exc}") from None


@dataclasses.dataclass(frozen=True)
class WorldSetup:
    """The World's light as parsed from its nodes, before any pixels are read.

    key identifies the unrotated, unscaled projection (it changes when the image
    or the constant colour does, not when strength or rotation do), so the
    viewport can cache the projection and turn the light in real time."""

    key: tuple
    source: object            # image pixels loader (callable), or an rgb constant (np.ndarray)
    strength: float
    rotation: np.ndarray | None   # R of the Mapping node (lookup directions are R w), or None
    description: str
    file: str = ""            # the EXR/HDR file the pixels come from ("": Blender's pixels, a studio HDRI
                              # (source() gives its path), or no image)
    image_name: str = ""      # the Environment Texture's image (or the studio HDRI's name)
    mapping: tuple | None = None  # the Mapping node's ((rx, ry, rz) Euler XYZ radians, vector type), or None


def world_setup(scene, *, source: str = "WORLD", builtin: str = "forest", view_layer=None) -> WorldSetup:
    """Parse the World's nodes (or the studio HDRI choice). Cheap: reads no
    pixels, but for an image World whose sun HDRI Sun takes (its pixels read
    and its sun extracted once, cached: :func:`_extracted`). A World whose Sky
    Texture's disc is the scene's sun (:func:`sky_sun_world`) is the sky
    without its disc."""
    if source == "BUILTIN":
        return WorldSetup(("builtin", builtin), lambda: envmap.builtin_environment_path(builtin), 1.0, None,
                          f"studio HDRI '{builtin}'", image_name=builtin)
    world = scene.world
    if world is None:
        raise WorldLightError("the scene has no World: add one, or choose a studio HDRI as the light")
    if not world.node_tree:
        c = np.array(world.color[:3], dtype=np.float64)
        return WorldSetup(("color", tuple(c)), c, 1.0, None,
                          f"World colour {tuple(round(float(x), 3) for x in c)}")
    out = next((n for n in world.node_tree.nodes if n.bl_idname == "ShaderNodeOutputWorld" and n.is_active_output),
               None) or next((n for n in world.node_tree.nodes if n.bl_idname == "ShaderNodeOutputWorld"), None)
    if out is None or not out.inputs["Surface"].is_linked:
        raise WorldLightError(f"World {world.name!r} has no connected World Output")
    bg = _linked(out.inputs["Surface"])
    if source == "WORLD" and sky_sun_world(scene, view_layer) is world:
        return _panorama_setup(world, "a Sky Texture", disc=False)
    if bg.bl_idname != "ShaderNodeBackground":
        return _panorama_setup(world, f"{bg.name!r} ({bg.bl_label}) feeds the output")
    if bg.inputs["Strength"].is_linked:
        return _panorama_setup(world, "a linked Background strength")
    strength = float(bg.inputs["Strength"].default_value)
    if not math.isfinite(strength):
        raise WorldLightError(f"World {world.name!r}: the Background strength is {strength}, not a finite number")
    col = bg.inputs["Color"]
    if not col.is_linked:
        c = np.array(col.default_value[:3], dtype=np.float64)
        return WorldSetup(("color", tuple(c)), c, strength, None, f"World colour x{strength:g}")
    env = _linked(col)
    if env.bl_idname != "ShaderNodeTexEnvironment":
        return _panorama_setup(world, f"{env.name!r} ({env.bl_label}) feeds the Background")
    img = env.image
    if img is None:
        raise WorldLightError(f"World {world.name!r}: the Environment Texture has no image")
    if env.projection != "EQUIRECTANGULAR":
        return _panorama_setup(world, f"a {env.projection.lower().replace('_', ' ')} Environment Texture")
    desc = f"World image {img.name!r} x{strength:g}"
    extracted = source == "WORLD" and hdri_sun_taken(scene, view_layer)
    R = None
    vec = env.inputs["Vector"]
    if vec.is_linked:
        m = _linked(vec)
        if m.bl_idname != "ShaderNodeMapping":
            return _panorama_setup(world, f"{m.name!r} ({m.bl_label}) feeds the Environment Texture's vector")
        if m.vector_type not in {"POINT", "TEXTURE"} or any(m.inputs[n].is_linked for n in ("Rotation", "Scale")):
            return _panorama_setup(world, f"Mapping node {m.name!r} of type {m.vector_type} or with linked inputs")
        R = mapping_rotation(m)
        mapping = (tuple(float(a) for a in m.inputs["Rotation"].default_value), m.vector_type)
        desc += ", rotated"
    else:
        mapping = None
    key = ("image", img.name, img.filepath, img.source, tuple(img.size), bool(img.packed_file), img.is_dirty)
    if extracted:
        found = _extracted(key, img)
        if found[0] is not None:
            return WorldSetup(key + ("its sun extracted",), lambda: _extracted(key, img)[1], strength, R,
                              desc + ", its sun extracted (the sun)", file=environment_file(img),
                              image_name=img.name, mapping=mapping)
    return WorldSetup(key, lambda: _image_pixels(img), strength, R, desc, file=environment_file(img),
                      image_name=img.name, mapping=mapping)


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


def sky_sun_of(world, error=ValueError, on_ready=None) -> "Sun | None":
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


def world_has_sky_sun(scene) -> bool:
    """The scene's World has one Sky Texture with a measurable sun disc (the Sky Sun option applies)."""
    w = scene.world
    return w is not None and w.node_tree is not None and len(world_panorama.sky_sun_nodes(w.node_tree, wide=True)) == 1


def hdri_sun_taken(scene, view_layer=None) -> bool:
    """The World's image gives the scene's sun: ``hdri_sun`` on (off by
    default), the World the light, no rendering Sun lamp. Cheap: reads no pixels."""
    st = getattr(scene, "prtt", None)
    if st is None or not getattr(st, "hdri_sun", False) or getattr(st, "light_source", "WORLD") != "WORLD":
        return False
    return not any(ob.data.type == "SUN" for ob in rendered_lamps(scene, view_layer))


#: image key -> (ExtractedSun or None, the image without it, why none): one image at a time.
_EXTRACTED: dict = {}


def _extracted(key: tuple, img) -> tuple:
    """core.light.sun_extract.extract_sun of the World image's pixels, cached by its key."""
    if key not in _EXTRACTED:
        _EXTRACTED.clear()
        _EXTRACTED[key] = extract_sun(_image_pixels(img))
    return _EXTRACTED[key]


def world_sun(scene, view_layer=None) -> tuple:
    """(the World's sun as a core Sun, or None; a one-line note ("" when none
    is due)): its Sky Texture's disc (:func:`sky_sun_world`) or its image's
    extracted sun (:func:`hdri_sun_taken`: direction turned by the Mapping
    node, energy times the Background strength; named "<image>: sun")."""
    world = sky_sun_world(scene, view_layer)
    if world is not None:
        try:
            return sky_sun_of(world), ""
        except SunError as exc:
            return None, f"the World's Sky Texture sun: {exc}; not baked"
        except ValueError as exc:             # the World's own render failed: the light says why
            return None, f"the World's Sky Texture sun could not be measured ({exc})"
    if not hdri_sun_taken(scene, view_layer):
        return None, ""
    try:
        # the World as the light reads it: its image's extraction is made (and cached) there
        setup = world_setup(scene, view_layer=view_layer)
    except (WorldLightError, OSError, ValueError) as exc:
        return None, f"HDRI Sun: {exc}"
    if setup.key[0] != "image":
        return None, "HDRI Sun: the World is not an Environment Texture image read directly; no sun extracted"
    sun, _, why = _EXTRACTED[setup.key[:7]]
    R, strength = setup.rotation, setup.strength
    if sun is None:
        return None, f"HDRI Sun: World image {setup.image_name!r}: {why}"
    d = np.asarray(sun.direction)
    if R is not None:
        d = np.asarray(R).T @ d               # the image is read at R w: its sun lies at w = R^T d
    energy = np.asarray(sun.energy) * max(strength, 0.0)
    top = float(energy.max())
    if not top > 0.0:
        return None, ""
    try:
        return Sun(direction=tuple(d), angle=sun.angle, color=tuple(energy / top), strength=top,
                   name=f"{setup.image_name}: sun"), ""
    except SunError as exc:
        return None, f"HDRI Sun: {exc}"


def _missing_image(tree):
    """The first image that feeds ``tree``'s output (in it or a group it uses)
    whose file is missing, or None (an unconnected node's image does not count)."""
    import bpy
    for n in world_panorama.tree_nodes(tree, feeding=True):
        img = getattr(n, "image", None)
        if img is not None and img.source == "FILE" and not img.packed_file:
            path = bpy.path.abspath(img.filepath, library=img.library)
            if not (path and os.path.isfile(path)):
                return img
    return None


def _redraw() -> None:
    import bpy  # Blender's module: only inside Blender

    from ..shared import redraw_viewports  # shared imports bpy: only when a panorama is ready
    redraw_viewports(bpy.context)


def _panorama_setup(world, why: str, *, disc: bool = True) -> WorldSetup:
    """The World rendered by Cycles (world_panorama), for a node tree read no
    other way; ``disc`` False: without its Sky Texture's sun disc (baked as
    the scene's sun instead)."""
    missing = _missing_image(world.node_tree)
    if missing is not None:
        raise WorldLightError(f"World image {missing.name!r} has no pixels (missing file {missing.filepath!r}?)")
    w, h = world_panorama.PANORAMA_SIZE
    key = ("panorama", world_panorama.world_digest(world)) + (() if disc else ("without its sun disc",))
    return WorldSetup(key, lambda: world_panorama.panorama(world, WorldLightError, _redraw, disc=disc), 1.0, None,
                      f"World {world.name!r} ({why}: rendered by Cycles as a {w}x{h} panorama"
                      + ("" if disc else "; its sun disc is the sun") + ")",
                      image_name=world.name)


def project_setup(setup: WorldSetup, bands: int) -> np.ndarray:
    """(K, 3) SH of the unrotated environment at strength 1 (the expensive part)."""
    if isinstance(setup.source, np.ndarray):
        return envmap.constant_light(setup.source, bands)
    return envmap.project_equirect(setup.source(), bands)


def world_light(scene, bands: int, *, source: str = "WORLD", builtin: str = "forest",
                view_layer=None) -> tuple[np.ndarray, str]:
    """(K, 3) SH light and a one-line description, from the scene's World or a studio HDRI."""
    setup = world_setup(scene, source=source, builtin=builtin, view_layer=view_layer)
    try:
        return envmap.compose_light(project_setup(setup, bands), setup.strength, setup.rotation), setup.description
    except ValueError as exc:        # a colour or strength that makes no finite light (envmap says which)
        raise WorldLightError(f"{setup.description}: {exc}") from None


#: A light whose mean radiance (times the view's exposure) is below this draws a dark preview
#: (Blender's default World is a grey of 0.05).
DIM_LIGHT = 0.1


def dim_light_note(light: np.ndarray, exposure: float = 0.0) -> str:
    """A one-line note when ``light`` (K, 3) SH is so dim that the preview is
    near black ("" otherwise): its mean radiance, L_00 / sqrt(4 pi), averaged
    over RGB and scaled by the view's exposure (2^exposure)."""
    mean = float(np.mean(np.asarray(light, np.float64)[0])) / math.sqrt(4.0 * math.pi)
    if not math.isfinite(mean) or mean * 2.0 ** float(exposure) >= DIM_LIGHT:
        return ""
    return (f"the light is dim (mean radiance {mean:.3g}; Blender's default World is a grey of 0.05): the "
            f"preview is as dark as Cycles' render would be without lamps; give the World an HDRI or a Sky "
            f"Texture, raise its strength, or choose a studio HDRI as the light")
