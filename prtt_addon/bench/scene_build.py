"""Build Blender scenes from PRTT's procedural meshes (demo, benchmarks, Cycles comparisons).

Everything is created in the current ``bpy.data``; nothing else is touched.
"""
from __future__ import annotations

import math

import bpy
import numpy as np


def mesh_object(name: str, mesh, *, material=None, uv_scale: float | None = None, collection=None):
    """A mesh object from a core ``meshgen.Mesh`` (smooth shaded when it has
    vertex normals). uv_scale: also a planar "UVMap" from x, y (for material textures)."""
    me = bpy.data.meshes.new(name)
    faces = np.asarray(mesh.faces, np.int64)
    # Explicit edges: without them Blender 5.0.1's from_pydata types .select_edge wrongly.
    edges = np.unique(np.sort(np.stack([faces, np.roll(faces, -1, axis=1)], -1).reshape(-1, 2), axis=1), axis=0)
    me.from_pydata(np.asarray(mesh.vertices, float).tolist(), edges.tolist(), faces.tolist())
    me.update()
    if mesh.normals is not None:
        me.shade_smooth()
    if uv_scale is not None:
        uv = me.uv_layers.new(name="UVMap")
        loops_v = np.empty(len(me.loops), np.int32)
        me.loops.foreach_get("vertex_index", loops_v)
        xy = np.asarray(mesh.vertices, float)[loops_v, :2] * uv_scale
        uv.uv.foreach_set("vector", xy.astype(np.float32).ravel())
    if material is not None:
        me.materials.append(material)
    ob = bpy.data.objects.new(name, me)
    (collection or bpy.context.scene.collection).objects.link(ob)
    return ob


def float_image(name: str, pixels_file_order: np.ndarray, *, non_color: bool):
    """A float image packed into the .blend; pixels (H, W, C) in file order (row 0 = top)."""
    h, w = pixels_file_order.shape[:2]
    rgba = np.ones((h, w, 4), np.float32)
    c = pixels_file_order.shape[2]
    rgba[..., :3] = pixels_file_order[..., :3] if c >= 3 else pixels_file_order[..., :1]
    img = bpy.data.images.new(name, w, h, float_buffer=True, alpha=False)
    img.colorspace_settings.name = "Non-Color" if non_color else "Linear Rec.709"
    img.pixels.foreach_set(rgba[::-1].ravel())
    img.pack()
    return img


def principled(name: str, *, base_color=(0.8, 0.8, 0.8), roughness=0.5, metallic=0.0, specular=0.5,
               base_image=None, roughness_image=None, diffuse: bool = False):
    """A material: Principled BSDF (optionally with base-colour / roughness images
    on the active UV map), or a Diffuse BSDF with ``diffuse=True``."""
    mat = bpy.data.materials.new(name)
    if hasattr(mat, "use_nodes") and bpy.app.version < (5, 0, 0):
        mat.use_nodes = True
    nt = mat.node_tree
    out = next(n for n in nt.nodes if n.bl_idname == "ShaderNodeOutputMaterial")
    for n in [n for n in nt.nodes if n.name != out.name]:   # (bpy wrappers: compare names, not identity)
        nt.nodes.remove(n)
    if diffuse:
        bsdf = nt.nodes.new("ShaderNodeBsdfDiffuse")
        bsdf.inputs["Color"].default_value = (*base_color, 1.0)
        nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
        return mat
    bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.inputs["Base Color"].default_value = (*base_color, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Metallic"].default_value = metallic
    bsdf.inputs["Specular IOR Level"].default_value = specular
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    for img, socket in ((base_image, "Base Color"), (roughness_image, "Roughness")):
        if img is not None:
            tex = nt.nodes.new("ShaderNodeTexImage")
            tex.image = img
            nt.links.new(tex.outputs["Color"], bsdf.inputs[socket])
    return mat


def environment_world(name: str, image_path: str, *, strength: float = 1.0, rotation_z: float = 0.0):
    """A World: Environment Texture (equirect) -> Background, through a Mapping node."""
    w = bpy.data.worlds.new(name)
    if hasattr(w, "use_nodes") and bpy.app.version < (5, 0, 0):
        w.use_nodes = True
    nt = w.node_tree
    bg = next(n for n in nt.nodes if n.bl_idname == "ShaderNodeBackground")
    bg.inputs["Strength"].default_value = strength
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.image = bpy.data.images.load(image_path, check_existing=True)
    mapping = nt.nodes.new("ShaderNodeMapping")
    mapping.inputs["Rotation"].default_value[2] = rotation_z
    coord = nt.nodes.new("ShaderNodeTexCoord")
    nt.links.new(coord.outputs["Generated"], mapping.inputs["Vector"])
    nt.links.new(mapping.outputs["Vector"], env.inputs["Vector"])
    nt.links.new(env.outputs["Color"], bg.inputs["Color"])
    return w


def camera_object(name: str, eye, target, *, fov_y_deg: float, collection=None):
    """A perspective camera at ``eye`` looking at ``target`` with a vertical field of view."""
    import mathutils
    cam = bpy.data.cameras.new(name)
    cam.sensor_fit = "VERTICAL"
    cam.angle_y = math.radians(fov_y_deg)
    cam.clip_start, cam.clip_end = 0.05, 200.0
    ob = bpy.data.objects.new(name, cam)
    ob.location = tuple(eye)
    direction = mathutils.Vector(tuple(np.asarray(target, float) - np.asarray(eye, float)))
    ob.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()
    (collection or bpy.context.scene.collection).objects.link(ob)
    return ob
