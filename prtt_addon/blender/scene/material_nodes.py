"""Blender materials -> PRTT's material dicts, textures and normal maps.

Read from the node tree feeding the active Material Output's Surface:

* Principled BSDF: Base Color, Metallic, Roughness, Specular IOR Level
  (Blender 4+; "Specular" before), IOR. Base Color and Roughness may come from
  an Image Texture (sampled at the material's UV map: the Image Texture's
  vector input if it is a UV Map node, else the active render UV map).
* Diffuse BSDF (roughness 1, no specular) and Glossy BSDF (metallic 1).
* Normal: a Normal Map node (tangent space) fed by an Image Texture, with
  its Strength and UV map.

Anything else gives a default grey material and a warning naming it, never a
failed bake. Missing image files give a warning and the constant values.
"""
from __future__ import annotations

import dataclasses
import os

import numpy as np

from ...core.model.material import DEFAULT
from ..rna_arrays import read_pixels
from ..versions import uses_nodes


@dataclasses.dataclass
class MaterialExport:
    """What one Blender material contributes to a job."""

    spec: dict                                   # core material dict
    base_image: object = None                    # bpy.types.Image or None
    rough_image: object = None
    normal_image: object = None
    normal_strength: float = 1.0
    normal_uv: str = ""                          # "" = active render UV map
    texture_uv: str = ""


def _linked(socket):
    return socket.links[0].from_node if socket.is_linked else None


def _image_node(node):
    """The image of an Image Texture node (possibly behind reroutes), or None."""
    while node is not None and node.bl_idname == "NodeReroute":
        node = _linked(node.inputs[0])
    if node is not None and node.bl_idname == "ShaderNodeTexImage":
        return node
    return None


def _uv_of(tex_node) -> str:
    v = tex_node.inputs["Vector"]
    if v.is_linked and _linked(v).bl_idname == "ShaderNodeUVMap":
        return _linked(v).uv_map
    return ""


def image_usable(image) -> bool:
    """Does the image have pixels (an existing file, packed, or generated)?"""
    import bpy
    if image is None:
        return False
    if image.source == "FILE" and not image.packed_file:
        return os.path.isfile(bpy.path.abspath(image.filepath, library=image.library))
    return image.source in {"FILE", "GENERATED"}


def parse_material(mat, warn) -> MaterialExport:
    name = mat.name if mat else "default"
    if mat is None or not uses_nodes(mat):
        c = list(mat.diffuse_color[:3]) if mat is not None else list(DEFAULT.base_color)
        return MaterialExport({"name": name, "base_color": c, "roughness": float(mat.roughness) if mat else 0.5})
    nodes = mat.node_tree.nodes
    out = next((n for n in nodes if n.bl_idname == "ShaderNodeOutputMaterial" and n.is_active_output), None)
    surf = _linked(out.inputs["Surface"]) if out is not None else None
    ex = MaterialExport({"name": name})
    if surf is None:
        warn(f"material {name!r}: nothing feeds its Material Output; using default grey")
        return ex
    kind = surf.bl_idname
    if kind not in {"ShaderNodeBsdfPrincipled", "ShaderNodeBsdfDiffuse", "ShaderNodeBsdfGlossy"}:
        warn(f"material {name!r}: {surf.bl_label} is not supported (Principled, Diffuse or Glossy "
             f"BSDF); using default grey")
        return ex
    spec = ex.spec
    colour = surf.inputs["Base Color"] if kind == "ShaderNodeBsdfPrincipled" else surf.inputs["Color"]
    spec["base_color"] = [float(x) for x in colour.default_value[:3]]
    tex = _image_node(_linked(colour))
    if tex is not None:
        if image_usable(tex.image):
            ex.base_image, ex.texture_uv = tex.image, _uv_of(tex)
        else:
            warn(f"material {name!r}: base colour image {tex.image.name if tex.image else '(none)'!r} "
                 f"has no pixels; using the constant colour")
    elif colour.is_linked:
        warn(f"material {name!r}: its base colour comes from {_linked(colour).bl_label}, which PRTT "
             f"cannot evaluate; using the socket's value")
    rough = surf.inputs["Roughness"]
    spec["roughness"] = float(np.clip(rough.default_value, 0.0, 1.0))
    rtex = _image_node(_linked(rough))
    if rtex is not None and image_usable(rtex.image):
        ex.rough_image = rtex.image
        ex.texture_uv = ex.texture_uv or _uv_of(rtex)
    if kind == "ShaderNodeBsdfPrincipled":
        es = surf.inputs.get("Emission Strength")
        ec = surf.inputs.get("Emission Color") or surf.inputs.get("Emission")
        if (es is not None and ec is not None and (es.is_linked or es.default_value > 0)
                and (ec.is_linked or max(ec.default_value[:3]) > 0)):
            warn(f"material {name!r}: its emission lights Cycles' render but not PRTT's (emission is not "
                 f"modelled yet): its surfaces and their surroundings look darker than in Cycles")
        spec["metallic"] = float(np.clip(surf.inputs["Metallic"].default_value, 0, 1))
        s_in = surf.inputs.get("Specular IOR Level") or surf.inputs.get("Specular")
        if s_in is not None:
            spec["specular"] = float(np.clip(s_in.default_value, 0, 1))
        if "IOR" in surf.inputs:
            spec["ior"] = float(np.clip(surf.inputs["IOR"].default_value, 1.0, 10.0))
    elif kind == "ShaderNodeBsdfDiffuse":
        spec.update(roughness=1.0, specular=0.0)
    else:
        spec["metallic"] = 1.0
    nrm = surf.inputs.get("Normal")
    nm = _linked(nrm) if nrm is not None else None
    if nm is not None and nm.bl_idname == "ShaderNodeNormalMap":
        if nm.space != "TANGENT":
            warn(f"material {name!r}: only tangent-space normal maps are supported")
        else:
            ntex = _image_node(_linked(nm.inputs["Color"]))
            if ntex is None or not image_usable(ntex.image):
                what = ntex.image.name if ntex is not None and ntex.image else "(none)"
                warn(f"material {name!r}: normal map image {what!r} has no pixels (missing file?); "
                     f"baking without it")
            else:
                ex.normal_image = ntex.image
                ex.normal_strength = float(nm.inputs["Strength"].default_value)
                ex.normal_uv = nm.uv_map
    return ex


def image_array(image, *, linearise: bool) -> np.ndarray:
    """(H, W, C) float32 pixels in file order (top row first)."""
    # A packed image loads from its packed bytes when its pixels are read;
    # reload() would look for a file (Blender: 'Image "" not available').
    if not image.has_data and not image.packed_file:
        try:
            image.reload()
        except RuntimeError:
            pass
    px = read_pixels(image)[::-1]
    if linearise and not image.is_float and image.colorspace_settings.name.lower().startswith("srgb"):
        rgb = px[..., :3]
        px = np.concatenate([np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4),
                             px[..., 3:]], axis=-1)
    return np.ascontiguousarray(px, dtype=np.float32)
