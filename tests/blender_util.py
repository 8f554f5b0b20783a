"""Helpers for tests that drive real Blender through the bpy module."""
import numpy as np
import pytest


def fresh_bpy():
    """Import bpy and reset to an empty factory scene (skips if bpy is missing)."""
    bpy = pytest.importorskip("bpy")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy


def new_float_image(bpy, name, pixels_file_order):
    """A float Blender image from (H, W, 3|4) pixels in file order (row 0 = top)."""
    h, w = pixels_file_order.shape[:2]
    rgba = np.ones((h, w, 4), dtype=np.float32)
    rgba[..., :pixels_file_order.shape[2]] = pixels_file_order[..., :4]
    img = bpy.data.images.new(name, w, h, float_buffer=True, alpha=True)
    # Non-Color: no colour transform on save/render. Set it before the pixels:
    # changing it later regenerates the image and drops them.
    img.colorspace_settings.name = "Non-Color"
    img.pixels.foreach_set(rgba[::-1].ravel())        # Blender stores bottom row first
    return img


_REGISTERED = False


def addon_bpy():
    """bpy with PRTT registered (once per process) and an empty factory scene."""
    global _REGISTERED
    bpy = fresh_bpy()
    # A benchmark run in this process (bench/cycles_compare, sun_cycles) may have registered it.
    if not _REGISTERED and not hasattr(bpy.types.Scene, "prtt"):
        import prtt_addon
        prtt_addon.register()
        _REGISTERED = True
    return bpy


def select_only(bpy, objects):
    for o in bpy.context.view_layer.objects:
        o.select_set(o in objects)
    bpy.context.view_layer.objects.active = objects[0] if objects else None


def uv_snapshot(bpy):
    """Every UV map's data, names and active/render flags, and selection flags."""
    snap = {}
    for o in bpy.data.objects:
        if o.type != "MESH":
            continue
        me = o.data
        maps = {}
        for u in me.uv_layers:
            a = np.empty(len(me.loops) * 2, np.float32)
            u.uv.foreach_get("vector", a)
            maps[u.name] = (a, u.active_render, me.uv_layers.active.name == u.name)
        sel = np.empty(len(me.polygons), bool)
        me.polygons.foreach_get("select", sel)
        snap[o.name] = (maps, sel)
    return snap


def cycles_looker(bpy, tmp_path):
    """A 0.01-rad, 4 x 4 px Cycles camera (1 sample, no denoising) on the current
    scene. Returns look(direction) -> (4, 4, C) float pixels of what it sees
    along that world direction (file order: row 0 at the top)."""
    import OpenEXR
    from mathutils import Vector
    sc = bpy.context.scene
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    sc.collection.objects.link(cam)
    sc.camera = cam
    cam.data.angle = 0.01
    cam.rotation_mode = "QUATERNION"
    sc.render.engine = "CYCLES"
    sc.cycles.samples = 1
    sc.cycles.use_denoising = False
    sc.render.resolution_x = sc.render.resolution_y = 4
    sc.render.image_settings.file_format = "OPEN_EXR"
    path = str(tmp_path / "r.exr")
    sc.render.filepath = path

    def look(direction):
        cam.rotation_quaternion = Vector(direction).to_track_quat("-Z", "Y")
        bpy.ops.render.render(write_still=True)
        with OpenEXR.File(path) as f:
            return np.array(list(f.channels().values())[0].pixels)
    return look
