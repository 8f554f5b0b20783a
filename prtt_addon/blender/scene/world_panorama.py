"""Any World as an environment image: Blender's own Cycles renders the World
alone through an equirectangular panoramic camera, and the image is projected
to SH like an HDRI (world.world_setup uses it for every node tree it does not
read directly: Sky Texture, gradients, mixes, an HDRI behind other nodes).

* Orientation: the camera sits at the origin turned so that pixel (row, col)
  of the render looks where the same pixel of an Environment Texture image
  would be looked up (row 0 = +Z; core.light.envmap's equirect convention),
  so the projection is project_equirect's (tests/test_world_panorama.py: the
  forest HDRI behind an identity node gives the exact path's SH).
* Resolution PANORAMA_SIZE (512 x 256: 0.7 degrees a pixel, beyond what band
  16 resolves) and PANORAMA_SAMPLES samples a pixel with a 0.01-pixel filter:
  each pixel is the World averaged over the pixel, as the area projection
  integrates it.
* Cached in this Blender session by a digest of the node tree (every node's
  settings and unlinked inputs, the links, images' files): the viewport draws
  with it at every redraw, the render runs once per change.
* Inside Blender's drawing no scene may be made nor a render run: the
  viewport's draw (``with drawing():``) gets :class:`Pending`, the panorama is
  rendered from a timer and the viewport drawn again.
* A Sky Texture's sun disc (0.5 degrees in 0.7-degree pixels) is measured
  apart: found where a quick panorama with the disc is brighter than one
  without, its energy summed over a 4-degree perspective view (disc on less
  disc off) and put back into the pixel holding its direction (against
  Cycles' own light on a plane: -1.9 %, where sampled with the sky it was
  10 % short). Or, where the scene bakes it as its sun (:func:`sky_sun`,
  lamps.scene_sun), left out: ``panorama(disc=False)`` is the sky alone and
  the disc's direction, size and energy become a core Sun with a mask.
* What a camera sees is not always what lights the scene: a Light Path node
  (e.g. a backdrop colour for camera rays only) makes the two differ, and is
  refused in one line (WorldLightError), as is a World that renders to
  non-finite pixels.
"""
from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import tempfile

import numpy as np

from ...core.io.image_io import read_hdr_image
from ...core.light.envmap import direction_to_uv, pixel_directions, pixel_solid_angles
from ...core.light.sun import MAX_ANGLE

#: The panorama's pixels (width, height) and Cycles samples a pixel.
PANORAMA_SIZE = (512, 256)
PANORAMA_SAMPLES = 16

#: digest -> (the panorama without a measured sun disc, the disc (SkySun) or None).
_cache: dict[str, tuple] = {}
#: Renders made in this session (tests count them: a cached World renders once).
renders = 0


def _value(v) -> str:
    if hasattr(v, "__len__") and not isinstance(v, str):
        try:
            return repr(tuple(round(float(x), 7) for x in v))
        except (TypeError, ValueError):
            return repr(tuple(str(x) for x in v))
    if isinstance(v, float):
        return repr(round(v, 7))
    if hasattr(v, "filepath"):                     # an image (or another ID with a file)
        cs = getattr(getattr(v, "colorspace_settings", None), "name", "")
        path = ""
        try:
            import bpy  # Blender's module: only inside Blender
            path = bpy.path.abspath(v.filepath, library=v.library)
            stamp = os.path.getmtime(path) if path and os.path.isfile(path) else 0.0
        except (ImportError, OSError, AttributeError):
            stamp = 0.0
        return (f"{v.name}|{v.filepath}|{tuple(getattr(v, 'size', ()))}|{bool(getattr(v, 'packed_file', None))}"
                f"|{cs}|{getattr(v, 'alpha_mode', '')}|{stamp}")
    if hasattr(v, "matrix_world"):                 # an object (Texture Coordinate's): its placement
        return f"ID:{v.name}|{_value([x for row in v.matrix_world for x in row])}"
    if hasattr(v, "name"):
        return f"ID:{v.name}"
    return repr(v)


#: Node properties that do not change what a node computes (drawing, naming, layout).
_LAYOUT = {"rna_type", "location", "location_absolute", "width", "height", "warning_propagation", "select",
           "dimensions", "name", "label", "color", "use_custom_color", "hide", "show_options", "show_preview",
           "show_texture", "parent", "width_hidden", "bl_idname", "bl_label", "bl_description", "bl_icon",
           "bl_width_default", "bl_width_min", "bl_width_max", "bl_height_default", "bl_height_min",
           "bl_height_max", "bl_static_type", "type", "inputs", "outputs", "internal_links", "interface"}


def _struct_lines(obj, prefix: str, depth: int, seen: set, skip=frozenset()) -> list[str]:
    """Lines of every setting of RNA struct ``obj``: values, the structs it
    holds (a Color Ramp's elements, a curve's points, texture mapping) and
    their collections, a few levels deep; an ID by its name (an image also by
    its file, size and colour space; a node group walked once). ``skip``: the
    names left out at this level."""
    lines = []
    for p in obj.bl_rna.properties:
        ident = p.identifier
        if ident in skip or ident == "rna_type":
            continue
        try:
            v = getattr(obj, ident)
        except (AttributeError, TypeError, RuntimeError):
            continue
        if p.type == "POINTER":
            if v is None:
                continue
            if isinstance(v, _id_type()):
                if hasattr(v, "nodes") and v.name not in seen:          # a node group
                    seen.add(v.name)
                    lines += _node_lines(v, seen)
                lines.append(f"{prefix}{ident}={_value(v)}")
            elif depth > 0:
                lines += _struct_lines(v, f"{prefix}{ident}.", depth - 1, seen)
        elif p.type == "COLLECTION":
            if depth > 0:
                for k, item in enumerate(v):
                    lines += _struct_lines(item, f"{prefix}{ident}[{k}].", depth - 1, seen)
        elif not p.is_readonly or ident in ("position",):
            lines.append(f"{prefix}{ident}={_value(v)}")
    return lines


def _id_type():
    import bpy  # Blender's module: only inside Blender
    return bpy.types.ID


def _node_lines(tree, seen: set) -> list[str]:
    """Lines that change whenever what ``tree`` computes can (groups followed once)."""
    lines = []
    for n in sorted(tree.nodes, key=lambda x: x.name):
        lines.append(f"node {n.name} {n.bl_idname}")
        lines += _struct_lines(n, "  ", 4, seen, _LAYOUT)      # the node's own layout only: a ramp
                                                               # stop's colour, a curve point's location count
        for s in n.inputs:
            if not s.is_linked and hasattr(s, "default_value"):
                lines.append(f"  in {s.identifier}={_value(s.default_value)}")
    for link in tree.links:
        lines.append(f"link {link.from_node.name}.{link.from_socket.identifier} -> "
                     f"{link.to_node.name}.{link.to_socket.identifier} {link.is_muted}")
    return lines


def world_digest(world) -> str:
    """A digest of everything the World's panorama depends on."""
    import bpy
    vis = getattr(world, "cycles_visibility", None)
    lines = [f"blender {bpy.app.version}", f"size {PANORAMA_SIZE} samples {PANORAMA_SAMPLES}",
             f"world {world.name} {world.library} colour {_value(world.color)} "
             f"camera-visible {getattr(vis, 'camera', True)}"]
    if world.node_tree is not None:
        lines += _node_lines(world.node_tree, set())
    return hashlib.sha256("\n".join(lines).encode("utf-8", "replace")).hexdigest()


def _feeding(tree) -> list:
    """The nodes of ``tree`` that feed its active output (or, in a group, its Group Output)."""
    outs = [n for n in tree.nodes if n.bl_idname in ("ShaderNodeOutputWorld", "NodeGroupOutput")
            and getattr(n, "is_active_output", True)]
    found, todo = {}, list(outs)
    while todo:
        n = todo.pop()
        if n.name in found:
            continue
        found[n.name] = n
        todo += [link.from_node for link in tree.links if link.to_node == n and not link.is_muted]
    return list(found.values())


def tree_nodes(tree, *, feeding: bool = False, seen: set | None = None):
    """Every node of ``tree`` and, after a group node, the nodes of its group
    (each group once); with ``feeding`` only the nodes that feed the active
    output (in a group, its Group Output)."""
    seen = set() if seen is None else seen
    for n in (_feeding(tree) if feeding else tree.nodes):
        yield n
        group = getattr(n, "node_tree", None)
        if group is not None and group.name not in seen:
            seen.add(group.name)
            yield from tree_nodes(group, feeding=feeding, seen=seen)


def light_path_node(tree):
    """The first Light Path node in ``tree`` (or a group it uses), or None."""
    return next((n for n in tree_nodes(tree) if n.bl_idname == "ShaderNodeLightPath"), None)


class Pending(Exception):
    """The World's panorama is being rendered from a timer: inside Blender's
    drawing no scene may be made nor a render run; the caller draws it from
    the next frame."""


_drawing = 0
_pending: set[str] = set()


class drawing:
    """``with drawing():`` marks Blender's draw callback: a panorama not in the
    cache is then rendered from a timer (:class:`Pending`), not here."""

    def __enter__(self):
        global _drawing
        _drawing += 1

    def __exit__(self, *exc):
        global _drawing
        _drawing -= 1


def panorama(world, error=ValueError, on_ready=None, *, disc: bool = True) -> np.ndarray:
    """(H, W, 3) float32 linear, top row first: ``world`` rendered by Cycles
    through an equirectangular camera (cached by :func:`world_digest`), a Sky
    Texture's measured sun disc put back as its energy in the pixel of its
    direction, or (``disc`` False) left out: the sky alone, for a scene that
    bakes the disc as its sun (:func:`sky_sun`). ``error``: the exception
    class a World that cannot be evaluated raises. Inside :class:`drawing`,
    an uncached World raises :class:`Pending` and is rendered from a timer,
    which calls ``on_ready()`` once it is."""
    img, sun = _entry(world, error, on_ready, wide=not disc)
    if not disc or sun is None:
        return img
    H, W = img.shape[:2]
    u, v = direction_to_uv(sun.direction[None, :])[0]
    row = min(H - 1, int((1.0 - v) * H))
    col = min(W - 1, int(u * W))
    out = img.copy()
    out[row, col] += (sun.energy / pixel_solid_angles(H, W)[row]).astype(np.float32)
    return out


@dataclasses.dataclass(frozen=True)
class SkySun:
    """A Sky Texture's sun disc as measured from Cycles' render of the World:
    ``direction`` (3,) unit towards it (Z up), ``energy`` (3,) its radiance
    integrated over the disc (W/m² on a surface facing it, RGB), ``angle``
    the node's disc size (full angle, radians), ``node`` the node's name."""

    direction: np.ndarray
    energy: np.ndarray
    angle: float
    node: str


def sky_sun(world, error=ValueError, on_ready=None) -> "SkySun | None":
    """The sun disc of ``world``'s one Sky Texture (:func:`sky_sun_nodes`),
    measured with its panorama (the same render and cache; Pending inside
    :class:`drawing` as :func:`panorama`), or None: no disc, several, a
    linked World, or a disc too faint to measure. Discs up to
    core.light.sun.MAX_ANGLE are measured (the panorama's own, with its disc
    put back, measures up to SUN_DISC_MAX_DEGREES, as it always has)."""
    return _entry(world, error, on_ready, wide=True)[1]


def _entry(world, error, on_ready, wide: bool = False) -> tuple:
    """The cache entry (panorama without its measured disc, SkySun or None);
    ``wide``: discs up to MAX_ANGLE measured apart (a separate entry only
    where the World's disc is wider than SUN_DISC_MAX_DEGREES)."""
    key = world_digest(world)
    wide = wide and world.node_tree is not None and any(
        n.sun_size > math.radians(SUN_DISC_MAX_DEGREES) for n in sky_sun_nodes(world.node_tree, wide=True))
    if wide:
        key += ":wide"
    if key not in _cache:
        if _drawing:
            if key in _failed:                 # said once per change; a render outside drawing tries again
                raise _failed[key]
            _render_later(world, key, error, on_ready, wide)
            raise Pending(f"World {world.name!r} is being rendered as a panorama (a few seconds)")
        # one World at a time (a panorama is 1.5 MB), or its two entries where its disc is wide
        for k in [k for k in _cache if k.split(":")[0] != key.split(":")[0]]:
            del _cache[k]
        _cache[key] = _render(world, error, wide)
    return _cache[key]


def _render_later(world, key: str, error, on_ready, wide: bool = False) -> None:
    import bpy
    if key in _pending:
        return
    _pending.add(key)
    uid = getattr(world, "session_uid", None)
    name = world.name

    def run():
        if getattr(bpy.app, "is_job_running", lambda _k: False)("RENDER"):
            return 1.0                           # F12 is rendering: one Cycles render at a time
        _pending.discard(key)
        # By its session id: a linked World and a local one may share a name.
        world = next((w for w in bpy.data.worlds if getattr(w, "session_uid", None) == uid), None) \
            if uid is not None else bpy.data.worlds.get(name)
        if world is not None and world_digest(world) == key.split(":")[0] and key not in _cache:
            try:
                _entry(world, error, None, wide)
            except Exception as exc:             # noqa: BLE001 - said when the draw asks again
                _failed[key] = exc
            if on_ready is not None:
                on_ready()
        return None                              # once

    bpy.app.timers.register(run, first_interval=0.0)


#: Worlds whose render from a timer failed: the draw raises their error instead of trying again.
_failed: dict[str, Exception] = {}


#: The sun's measurement: a perspective view this wide (degrees) centred on the brightest
#: pixel of a quick panorama, at this many pixels a side and samples a pixel.
SUN_VIEW_DEGREES = 4.0
#: Sun discs up to this diameter are measured apart (a wider one stays in the panorama).
SUN_DISC_MAX_DEGREES = 2.0
SUN_VIEW_PIXELS = 64
SUN_SAMPLES = 16


def sky_sun_nodes(tree, *, wide: bool = False) -> list:
    """Sky Texture nodes of ``tree`` (and its groups) that draw a sun disc:
    the models that draw one (Nishita, and its successors in Blender 5), and a
    small one: up to SUN_DISC_MAX_DEGREES for the panorama with its disc put
    back (a wider disc is left in the panorama), up to
    core.light.sun.MAX_ANGLE with ``wide`` (a disc baked as the sun)."""
    most = MAX_ANGLE if wide else math.radians(SUN_DISC_MAX_DEGREES)
    return [n for n in tree_nodes(tree)
            if n.bl_idname == "ShaderNodeTexSky" and getattr(n, "sun_disc", False) and not n.mute
            and n.sky_type in ("NISHITA", "SINGLE_SCATTERING", "MULTIPLE_SCATTERING")
            and getattr(n, "sun_size", 1.0) <= most]


def _render(world, error, wide: bool = False) -> tuple:
    """(the panorama without a measured sun disc, SkySun or None): a Sky
    Texture's sun disc measured apart (:func:`panorama` puts it back as its
    energy in the pixel that holds its direction). Sampled with the rest, a
    disc of 0.5 degrees in 0.7-degree pixels came out 10 % / 6 % / 3 % short
    of Cycles' own light at 16 / 64 / 256 samples (the sky alone: 1.6 %)."""
    global renders
    if world.node_tree is not None:
        lp = light_path_node(world.node_tree)
        if lp is not None:
            raise error(f"World {world.name!r}: its Light Path node {lp.name!r} makes what lights the scene "
                        f"differ from what a camera sees, and PRTT reads the World as a camera sees it; "
                        f"remove it, or choose a studio HDRI as the light")
    W, H = PANORAMA_SIZE
    # A linked World cannot be edited (its disc turned off and on): its disc stays in the panorama,
    # as do several discs.
    suns = sky_sun_nodes(world.node_tree, wide=wide) if world.node_tree is not None and world.library is None else []
    sun = None
    if len(suns) == 1:
        disc_deg = math.degrees(suns[0].sun_size)
        # the narrow view as it always was; a wider disc (baked as the sun) in a view 2.5 times as wide
        view = SUN_VIEW_DEGREES if disc_deg <= SUN_DISC_MAX_DEGREES else 2.5 * disc_deg
        direction, energy = _measure_sun(world, suns[0], error, view)
        sun = SkySun(direction, energy, float(suns[0].sun_size), suns[0].name)
        suns[0].sun_disc = False
    try:
        img = _camera_render(world, error, pano=True, size=(W, H), samples=PANORAMA_SAMPLES)
    finally:
        if sun is not None:
            suns[0].sun_disc = True
    renders += 1
    if img.shape != (H, W, 3) or not np.isfinite(img).all():
        raise error(f"World {world.name!r}: Cycles rendered it to {img.shape} pixels "
                    f"{'with non-finite values' if img.size else ''}; choose a studio HDRI as the light")
    if sun is not None and not (np.isfinite(sun.energy).all() and sun.energy.max() > 0):
        sun = None                     # too faint to measure (the sun under the horizon): nothing to add
    return np.ascontiguousarray(img, dtype=np.float32), sun


def _measure_sun(world, node, error, view_degrees: float = SUN_VIEW_DEGREES) -> tuple[np.ndarray, np.ndarray]:
    """(unit direction, RGB energy: the disc's radiance integrated over its
    solid angle, W m^-2 sr^0 in Blender's units) of Sky Texture ``node``'s sun:
    found where a quick panorama with the disc is brighter than one without
    (0.35-degree pixels; the sky's horizon glow can outshine a low sample of
    the disc), then refined and its energy summed over a narrow perspective
    view, disc on less disc off."""
    quick = (1024, 512)
    on = _camera_render(world, error, pano=True, size=quick, samples=4)
    node.sun_disc = False
    try:
        off = _camera_render(world, error, pano=True, size=quick, samples=4)
        lum = (on - off).sum(axis=2)
        row, col = np.unravel_index(int(np.argmax(lum)), lum.shape)
        aim = pixel_directions(*lum.shape)[row, col]
        off = _camera_render(world, error, pano=False, size=(SUN_VIEW_PIXELS,) * 2, samples=SUN_SAMPLES, aim=aim,
                             view_degrees=view_degrees)
    finally:
        node.sun_disc = True
    on = _camera_render(world, error, pano=False, size=(SUN_VIEW_PIXELS,) * 2, samples=SUN_SAMPLES, aim=aim,
                        view_degrees=view_degrees)
    # Each pixel's direction and solid angle on the view's image plane at distance 1.
    n = SUN_VIEW_PIXELS
    half = math.tan(math.radians(view_degrees) / 2)
    c = ((np.arange(n) + 0.5) / n * 2 - 1) * half
    x, y = np.meshgrid(c, -c)                                  # row 0 = top of the view
    pix = (2 * half / n) ** 2
    omega = pix / (1 + x * x + y * y) ** 1.5
    disc = np.clip(on - off, 0.0, None)                        # (n, n, 3)
    energy = (disc * omega[..., None]).sum(axis=(0, 1))
    R = _aim_matrix(aim)
    local = np.stack([x, y, -np.ones_like(x)], axis=-1)
    local /= np.linalg.norm(local, axis=-1, keepdims=True)
    w = (disc.sum(axis=2) * omega).ravel()
    if not np.isfinite(energy).all() or w.sum() <= 0:
        return aim, np.zeros(3)
    d = (local.reshape(-1, 3) * w[:, None]).sum(axis=0) @ R.T
    return d / np.linalg.norm(d), energy


def _aim_matrix(aim: np.ndarray) -> np.ndarray:
    """Rotation taking a camera's -Z to ``aim`` with its +Y as near to world +Z as can be."""
    f = np.asarray(aim, np.float64) / np.linalg.norm(aim)
    up = np.array([0.0, 0.0, 1.0]) if abs(f[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    xr = np.cross(f, up)
    xr /= np.linalg.norm(xr)
    yr = np.cross(xr, f)
    return np.stack([xr, yr, -f], axis=1)                      # columns: camera x, y, z in world


def _camera_render(world, error, *, pano: bool, size, samples: int, aim=None,
                   view_degrees: float = SUN_VIEW_DEGREES) -> np.ndarray:
    """(H, W, 3) float32 of ``world`` alone, linear, top row first: through an
    equirectangular camera at the origin (``pano``) or a perspective one of
    ``view_degrees`` wide looking along ``aim``."""
    import bpy
    import mathutils
    W, H = size
    scene = bpy.data.scenes.new("PRTT World Panorama")
    cam_data = bpy.data.cameras.new("PRTT World Panorama")
    cam = bpy.data.objects.new("PRTT World Panorama", cam_data)
    try:
        scene.world = world
        scene.collection.objects.link(cam)
        scene.camera = cam
        if pano:
            cam_data.type = "PANO"
            if hasattr(cam_data, "panorama_type"):         # Blender 4.0+
                cam_data.panorama_type = "EQUIRECTANGULAR"
            else:                                          # pragma: no cover - Blender 3.x (Cycles' own)
                cam_data.cycles.panorama_type = "EQUIRECTANGULAR"
            # The camera looks down its -Z with +Y up; turned so that the image's centre column
            # looks along -X and row 0 along +Z, as an Environment Texture's image is looked up.
            cam.rotation_euler = (math.pi / 2, 0.0, -math.pi / 2)
        else:
            cam_data.type = "PERSP"
            cam_data.sensor_fit = "HORIZONTAL"
            cam_data.angle = math.radians(view_degrees)
            cam.matrix_world = mathutils.Matrix(_aim_matrix(aim).tolist()).to_4x4()
        r = scene.render
        r.engine = "CYCLES"
        r.resolution_x, r.resolution_y, r.resolution_percentage = W, H, 100
        r.film_transparent = False
        r.filter_size = 0.01
        r.use_compositing = False
        r.use_sequencer = False
        r.image_settings.file_format = "OPEN_EXR"
        r.image_settings.color_depth = "32"
        r.image_settings.exr_codec = "ZIP"
        scene.cycles.device = "CPU"
        scene.cycles.samples = samples
        scene.cycles.use_denoising = False
        if hasattr(scene.cycles, "use_adaptive_sampling"):
            scene.cycles.use_adaptive_sampling = False
        scene.view_settings.view_transform = "Standard"
        # An animated World at the frame the user is on.
        scene.frame_current = bpy.context.scene.frame_current
        from ..blendfile import native_output_captured  # imports bpy: only inside Blender
        with tempfile.TemporaryDirectory(prefix="prtt-world-") as d:
            r.filepath = os.path.join(d, "world.exr")
            # Blender's render prints its progress ("Fra:1 Mem: ...", "Saved: ...") from C:
            # kept out of a command's output, shown when the render fails.
            with native_output_captured() as said, bpy.context.temp_override(scene=scene):
                done = bpy.ops.render.render(write_still=True, scene=scene.name)
            if "FINISHED" not in done or not os.path.isfile(r.filepath):
                tail = " ".join("".join(said).strip().splitlines()[-2:])
                raise error(f"World {world.name!r}: Cycles did not render it ({', '.join(sorted(done))}"
                            f"{': ' + tail if tail else ''}); choose a studio HDRI as the light")
            return read_hdr_image(r.filepath)
    finally:
        bpy.data.objects.remove(cam)
        bpy.data.cameras.remove(cam_data)
        bpy.data.scenes.remove(scene)
