"""The scene's colour management (Render Properties > Color Management) as a
core.shading.display.DisplayTransform, sampled from Blender itself.

Blender's colour management runs inside Blender (OpenColorIO), with no Python
API that maps pixels. So the table is made by Blender: a float image holding
the lattice's scene-linear colours is saved with Image.save_render through a
temporary scene that has the user's display device, view transform, look and
white balance (exposure 0, gamma 1, no dither) as a 16-bit PNG, which is read
back (0.13 s for 65^3 colours). Exposure and gamma are applied around the
table (exposure before, gamma after: Blender's order), so dragging them never
samples again. Tables are cached per setting and per Blender session, and
per gamma the instance the draw handler gets every frame (its checks and its
digest are made once).

Blender refuses new data-blocks while it draws, so the viewport's draw handler
asks for a table with ``display_of(scene, sample=False)`` and samples it from
a timer (``schedule``); until then it draws Standard for a frame.

Not drawn: the view's RGB Curves (Use Curves): ``unsupported`` names them.
"""
from __future__ import annotations

import os
import tempfile

import bpy
import numpy as np

from ...core.shading.display import LUT_SIZE, DisplayTransform, lattice
from ..rna_arrays import read_pixels, write_pixels

#: Width of the lattice image (rows follow).
_IMAGE_WIDTH = 1024
_TABLES: dict = {}          # settings_key -> DisplayTransform (gamma 1)
_SHOWN: dict = {}           # (settings_key, gamma) -> that table with the gamma
_PENDING: set = set()


def settings_key(scene) -> tuple:
    """What the table depends on: display device, view transform, look, and
    the white balance where this Blender has it."""
    ds, vs = scene.display_settings, scene.view_settings
    wb = ()
    if getattr(vs, "use_white_balance", False):
        wb = (float(vs.white_balance_temperature), float(vs.white_balance_tint))
    return (ds.display_device, vs.view_transform, vs.look, wb)


def is_standard(scene) -> bool:
    """Standard on an sRGB display, no look, gamma 1, no white balance: the
    exact sRGB encode draws it (no table)."""
    device, view, look, wb = settings_key(scene)
    return (device == "sRGB" and view == "Standard" and look in ("None", "", "NONE") and not wb
            and scene.view_settings.gamma == 1.0)


def describe(scene) -> str:
    device, view, look, wb = settings_key(scene)
    text = f"{view}, look {look}, display {device}"
    if scene.view_settings.gamma != 1.0:
        text += f", gamma {scene.view_settings.gamma:g}"
    if wb:
        text += f", white balance {wb[0]:g} K tint {wb[1]:g}"
    return text


def unsupported(scene) -> str:
    """What of the scene's colour management PRTT does not draw ('' if none)."""
    return "its RGB Curves (Color Management > Use Curves)" if scene.view_settings.use_curve_mapping else ""


def display_of(scene, *, sample: bool = True) -> DisplayTransform | None:
    """The scene's view transform as a table, or None for plain Standard.
    With ``sample`` False a table not yet made is not made (returns None:
    call ``schedule``)."""
    if is_standard(scene):
        return None
    key = settings_key(scene)
    table = _TABLES.get(key)
    if table is None:
        if not sample:
            return None
        table = _TABLES[key] = sample_table(key, describe(scene))
    gamma = float(scene.view_settings.gamma)
    shown = _SHOWN.get((key, gamma))
    if shown is None:
        if len(_SHOWN) > 16:            # a gamma slider dragged through many values
            _SHOWN.clear()
        shown = _SHOWN[(key, gamma)] = table.with_gamma(gamma)
    return shown


def missing(scene) -> bool:
    """True when the scene needs a table that is not made yet."""
    return not is_standard(scene) and settings_key(scene) not in _TABLES


def schedule(scene, on_ready) -> None:
    """Sample the scene's table from a timer (outside drawing), then call
    ``on_ready()``. Does nothing while one is pending."""
    key = settings_key(scene)
    if key in _PENDING:
        return
    _PENDING.add(key)
    name = scene.name

    def run():
        _PENDING.discard(key)
        sc = bpy.data.scenes.get(name)
        if sc is not None and settings_key(sc) == key and key not in _TABLES:
            _TABLES[key] = sample_table(key, describe(sc))
            on_ready()
        return None                      # once

    bpy.app.timers.register(run, first_interval=0.0)


def sample_table(key: tuple, name: str, size: int = LUT_SIZE) -> DisplayTransform:
    """Blender's own colour management of the lattice's colours, as a table."""
    device, view, look, wb = key
    colours = lattice(size)
    n = colours.shape[0]
    rows = -(-n // _IMAGE_WIDTH)
    rgba = np.ones((rows * _IMAGE_WIDTH, 4), np.float32)
    rgba[:n, :3] = colours
    rgba[n:, :3] = 0.0
    image = bpy.data.images.new("PRTT display lattice", _IMAGE_WIDTH, rows, alpha=True, float_buffer=True)
    scene = bpy.data.scenes.new("PRTT display lattice")
    read = None
    try:
        image.colorspace_settings.name = _linear_name()
        write_pixels(image, rgba.reshape(rows, _IMAGE_WIDTH, 4))
        scene.display_settings.display_device = device
        scene.view_settings.view_transform = view
        scene.view_settings.look = look
        scene.view_settings.exposure = 0.0
        scene.view_settings.gamma = 1.0
        if wb:
            scene.view_settings.use_white_balance = True
            scene.view_settings.white_balance_temperature, scene.view_settings.white_balance_tint = wb
        scene.render.dither_intensity = 0.0
        settings = scene.render.image_settings
        settings.file_format = "PNG"
        settings.color_mode = "RGB"
        settings.color_depth = "16"
        with tempfile.TemporaryDirectory(prefix="prtt-display-") as tmp:
            path = os.path.join(tmp, "lattice.png")
            image.save_render(path, scene=scene)
            read = bpy.data.images.load(path)
            read.colorspace_settings.name = "Non-Color"
            px = read_pixels(read)
            values = px.reshape(-1, px.shape[2])[:n, :3]
    finally:
        for img in (image, read):
            if img is not None:
                bpy.data.images.remove(img)
        bpy.data.scenes.remove(scene)
    lut = np.clip(values, 0.0, 1.0).astype(np.float32).reshape(size, size, size, 3)
    return DisplayTransform(lut, name=name)


def _linear_name() -> str:
    """Blender's name of scene-linear Rec.709 ('Linear' before 4.0's rename)."""
    names = {item.identifier for item in
             bpy.types.ColorManagedInputColorspaceSettings.bl_rna.properties["name"].enum_items}
    return "Linear Rec.709" if "Linear Rec.709" in names or not names else "Linear"
