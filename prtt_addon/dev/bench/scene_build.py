"""Build Blender scenes from PRTT's procedural meshes (demo, benchmarks, Cycles comparisons).

Everything is created in the current ``bpy.data``; nothing else is touched.
"""
from __future__ import annotations

import math

import bpy
import numpy as np

from ...core.light.envmap import builtin_environment_path
from .scene_library import ROOM_MATERIALS, room_objects


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


def floor_textures(n: int = 512, planks: int = 8, seed: int = 3):
    """Wood-plank base colour (linear) and roughness (0.15..0.6), file order."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:n, 0:n] / n
    plank = np.floor(x * planks).astype(int)
    per_plank_rough = rng.uniform(0.15, 0.45, planks)[plank]
    grain = 0.5 + 0.5 * np.sin(2 * np.pi * (y * 6 + 0.3 * np.sin(2 * np.pi * x * 3) + plank * 0.37))
    gap = (np.abs(x * planks - np.round(x * planks)) < 0.02)
    rough = np.clip(per_plank_rough + 0.15 * grain + 0.35 * gap, 0.0, 1.0)
    tone = rng.uniform(0.7, 1.1, planks)[plank] * (0.85 + 0.15 * grain)
    base = np.stack([0.42 * tone, 0.26 * tone, 0.14 * tone], axis=-1) * np.where(gap, 0.4, 1.0)[..., None]
    return base.astype(np.float32), np.repeat(rough[..., None], 3, axis=2).astype(np.float32)


def demo_scene() -> dict:
    """The demo's scene (``./prtt.sh demo``) in the current (empty) Blender
    file: the room's objects and materials, the floor's plank textures, the
    forest World, the camera; returns its objects."""
    base, rough = floor_textures()
    mats = {}
    for name, spec in ROOM_MATERIALS.items():
        kw = dict(base_color=tuple(spec["base_color"]), roughness=spec.get("roughness", 0.5),
                  metallic=spec.get("metallic", 0.0), specular=spec.get("specular", 0.5))
        if name == "floor":
            kw.update(base_image=float_image("floor_color", base, non_color=False),
                      roughness_image=float_image("floor_roughness", rough, non_color=True))
        mats[name] = principled(name, **kw)
    objects = {}
    for name, mesh in room_objects():
        objects[name] = mesh_object(name, mesh, material=mats.get(name),
                                       uv_scale=0.5 if name == "floor" else None)
    scene = bpy.context.scene
    scene.world = environment_world("Forest", builtin_environment_path("forest"), strength=1.0)
    scene.camera = camera_object("Camera", (0.0, -5.6, 2.3), (0.0, 0.6, 0.7), fov_y_deg=62.0)
    # Standard: the demo's figures set PRTT beside Cycles, and Standard shows their
    # radiance unbent (the preview draws any view transform: docs/preview.md)
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.exposure = -0.7                  # the forest HDRI lights white walls to ~2
    bpy.context.view_layer.update()         # new objects get their view-layer bases (selection)
    return objects
