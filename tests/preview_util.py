"""A baked Blender scene for the preview tests: every feature the shaders have.

* "Floor": a 2-triangle plane (minimal tessellation), glossy Principled with a
  roughness *texture* (stripes 0.15 .. 0.8), an sRGB base-colour texture
  (checker) and a tangent-space normal map (bumps);
* "Ball": a smooth UV sphere, metallic-ish glossy, constant colours;
* "Block": a flat-shaded cube, diffuse (Diffuse BSDF), mirrored (scale -1 in x)
  so the normal matrix and bitangent sign paths run;
* World: the studio HDRI forest.exr through a Mapping node (Z rotation) with
  Background strength 1.5;
* a camera; bake at 64 texels with 64 rays, one bounce, per-vertex transfer.
"""
import math
import os

import numpy as np

from tests.blender_util import addon_bpy, new_float_image, select_only


def _image(bpy, name, pixels_file_order, srgb=False):
    if not srgb:
        return new_float_image(bpy, name, pixels_file_order)
    h, w = pixels_file_order.shape[:2]
    img = bpy.data.images.new(name, w, h, alpha=True)            # 8-bit, sRGB
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :3] = pixels_file_order[..., :3]
    img.pixels.foreach_set(rgba[::-1].ravel())
    return img


def _tex_node(nt, img, non_color):
    n = nt.nodes.new("ShaderNodeTexImage")
    n.image = img
    n.interpolation = "Linear"
    if non_color:
        img.colorspace_settings.name = "Non-Color"
    return n


def floor_material(bpy):
    mat = bpy.data.materials.new("FloorMat")
    mat.use_nodes = True
    nt = mat.node_tree
    bsdf = nt.nodes["Principled BSDF"]
    n = 32
    y, x = np.mgrid[0:n, 0:n] / n
    rough = 0.15 + 0.65 * (0.5 + 0.5 * np.sin(2 * np.pi * 3 * x))
    r_img = _image(bpy, "floor_rough", np.repeat(rough[..., None], 3, axis=2))
    checker = ((np.floor(x * 4) + np.floor(y * 4)) % 2)[..., None]
    base = np.concatenate([0.25 + 0.5 * checker, 0.4 + 0.0 * checker, 0.7 - 0.4 * checker], axis=2)
    b_img = _image(bpy, "floor_base", base, srgb=True)
    # Normal map: cosine bumps, encoded 0..1.
    gx = 0.35 * np.cos(2 * np.pi * 4 * x)
    gy = 0.35 * np.cos(2 * np.pi * 4 * y)
    nrm = np.stack([gx, gy, np.ones_like(gx)], axis=2)
    nrm /= np.linalg.norm(nrm, axis=2, keepdims=True)
    n_img = _image(bpy, "floor_normal", 0.5 * nrm + 0.5)
    rt = _tex_node(nt, r_img, True)
    bt = _tex_node(nt, b_img, False)
    nt_ = _tex_node(nt, n_img, True)
    nm = nt.nodes.new("ShaderNodeNormalMap")
    nm.inputs["Strength"].default_value = 0.8
    nt.links.new(rt.outputs["Color"], bsdf.inputs["Roughness"])
    nt.links.new(bt.outputs["Color"], bsdf.inputs["Base Color"])
    nt.links.new(nt_.outputs["Color"], nm.inputs["Color"])
    nt.links.new(nm.outputs["Normal"], bsdf.inputs["Normal"])
    return mat


def world_forest(bpy, strength=1.5, rot_z=0.6):
    from prtt_addon.core.light.envmap import builtin_environment_path
    from prtt_addon.dev.bench.scene_build import environment_world
    w = environment_world("Forest", builtin_environment_path("forest"), strength=strength, rotation_z=rot_z)
    bpy.context.scene.world = w
    return w


def build_scene(bpy, out_dir, *, resolution=64, rays=64, bounces=1, bounce_mode="BAKED", sun=False,
                lamps=False):
    """Create, unwrap and bake the scene (module doc); ``sun``: with a warm
    3-degree Sun lamp whose highlight falls on the floor and the ball;
    ``lamps``: with a point lamp of 10 cm over the ball and a bluish spot
    on the block and the floor. Returns the objects."""
    bpy.ops.mesh.primitive_plane_add(size=4)
    floor = bpy.context.active_object
    floor.name = "Floor"
    floor.data.materials.append(floor_material(bpy))
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.6, location=(-0.5, 0.2, 0.65), segments=24, ring_count=12)
    ball = bpy.context.active_object
    ball.name = "Ball"
    bpy.ops.object.shade_smooth()
    m = bpy.data.materials.new("BallMat")
    m.use_nodes = True
    p = m.node_tree.nodes["Principled BSDF"]
    p.inputs["Base Color"].default_value = (0.9, 0.6, 0.2, 1.0)
    p.inputs["Metallic"].default_value = 0.4
    p.inputs["Roughness"].default_value = 0.35
    ball.data.materials.append(m)
    bpy.ops.mesh.primitive_cube_add(size=0.7, location=(0.8, -0.4, 0.35), rotation=(0, 0, 0.5))
    block = bpy.context.active_object
    block.name = "Block"
    block.scale = (-1.0, 1.0, 1.0)
    d = bpy.data.materials.new("BlockMat")
    d.use_nodes = True
    nt = d.node_tree
    nt.nodes.remove(nt.nodes["Principled BSDF"])
    diff = nt.nodes.new("ShaderNodeBsdfDiffuse")
    diff.inputs["Color"].default_value = (0.2, 0.7, 0.3, 1.0)
    nt.links.new(diff.outputs["BSDF"], nt.nodes["Material Output"].inputs["Surface"])
    block.data.materials.append(d)
    world_forest(bpy)
    bpy.ops.object.camera_add(location=(3.2, -3.4, 2.6))
    cam = bpy.context.active_object
    cam.name = "Cam"
    direction = np.array([0.0, 0.0, 0.3]) - np.array(cam.location)
    import mathutils
    cam.rotation_euler = mathutils.Vector(direction).to_track_quat("-Z", "Y").to_euler()
    bpy.context.scene.camera = cam
    if sun:
        lamp = bpy.data.objects.new("Key", bpy.data.lights.new("Key", "SUN"))
        lamp.data.energy, lamp.data.angle, lamp.data.color = 3.0, math.radians(3.0), (1.0, 0.9, 0.75)
        # towards the camera's mirror side of the floor: its highlight is in view
        lamp.rotation_euler = mathutils.Vector((-0.45, 0.5, 0.74)).to_track_quat("Z", "Y").to_euler()
        bpy.context.scene.collection.objects.link(lamp)
    if lamps:
        bulb = bpy.data.objects.new("Bulb", bpy.data.lights.new("Bulb", "POINT"))
        bulb.data.energy, bulb.data.shadow_soft_size, bulb.data.color = 150.0, 0.1, (1.0, 0.85, 0.7)
        bulb.location = (-0.2, -0.6, 1.9)
        spot = bpy.data.objects.new("Spot", bpy.data.lights.new("Spot", "SPOT"))
        spot.data.energy, spot.data.shadow_soft_size, spot.data.color = 300.0, 0.05, (0.6, 0.8, 1.0)
        spot.data.spot_size, spot.data.spot_blend = math.radians(50.0), 0.3
        spot.location = (2.2, -1.2, 2.0)
        spot.rotation_euler = mathutils.Vector((0.8, -0.4, 0.35)) \
            .__sub__(mathutils.Vector(spot.location)).to_track_quat("-Z", "Y").to_euler()
        for ob in (bulb, spot):
            bpy.context.scene.collection.objects.link(ob)
    st = bpy.context.scene.prtt
    st.resolution, st.rays, st.bounces, st.bounce_rays = resolution, rays, bounces, 16
    st.vertex_transfer = True
    st.bounce_mode = bounce_mode
    st.output_dir = str(out_dir)
    select_only(bpy, [floor, ball, block])
    assert bpy.ops.prtt.unwrap() == {"FINISHED"}
    assert bpy.ops.prtt.bake_transfer() == {"FINISHED"}, st.status
    return floor, ball, block


def baked_blend(tmp_dir, **kw):
    """Build and bake once (``kw`` to build_scene); returns the saved .blend
    path (reopen it per test)."""
    blend = os.path.join(tmp_dir, "preview.blend")
    if not os.path.exists(blend):
        bpy = addon_bpy()
        build_scene(bpy, os.path.join(tmp_dir, "out"), **kw)
        bpy.ops.wm.save_as_mainfile(filepath=blend)
    return blend


def open_blend(blend):
    bpy = addon_bpy()
    bpy.ops.wm.open_mainfile(filepath=blend)
    return bpy
