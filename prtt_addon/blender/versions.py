"""What differs between the Blender versions the manifest claims (4.2 LTS
to the newest): the one place the preview, the glTF export and the UI ask.

Each difference is named after what PRTT needs, not after a version, and
says which versions behave how. ``./prtt.sh compat`` (tools/compat.py) runs
the installed extension through every one of them.
"""
from __future__ import annotations

import importlib

import bpy

#: Blender 4.5+ warns when a path property without this option is given a
#: "//"-relative path (PRTT stores its Output Folder relative to the .blend);
#: 4.2 does not know the option.
RELATIVE_PATH_OPTIONS = {"options": {"PATH_SUPPORTS_BLEND_RELATIVE"}} if bpy.app.version >= (4, 5, 0) else {}


def uses_nodes(idblock) -> bool:
    """Does a Material or World shade with its node tree? Blender 5.0 made
    node trees unconditional (``use_nodes`` deprecated); before, the flag
    decides."""
    if bpy.app.version >= (5, 0, 0):
        return idblock.node_tree is not None
    return bool(idblock.use_nodes) and idblock.node_tree is not None


# --- gpu: drawing into one layer of an array texture -------------------------------

_SWAPPED_SLOT_KEYS = None


def _slot_keys_swapped() -> bool:
    """Does this Blender's GPUFrameBuffer read a colour slot's dictionary with
    its keys swapped? Blender 4.2 and 4.5 compare each key with
    ``PyUnicode_CompareWithASCIIString(...)`` without ``== 0`` (fixed in
    5.0): the value of "texture" is read as the layer ("'GPUTexture' object
    cannot be interpreted as an integer"), and the first key that is not
    "texture" as the texture. Asked of the running Blender once, on a
    1x1x2 texture, rather than assumed from its version."""
    global _SWAPPED_SLOT_KEYS
    if _SWAPPED_SLOT_KEYS is None:
        import gpu
        probe = gpu.types.GPUTexture((1, 1), layers=2, format="RGBA8")
        try:
            gpu.types.GPUFrameBuffer(color_slots=({"texture": probe, "layer": 1},))
            _SWAPPED_SLOT_KEYS = False
        except TypeError:
            gpu.types.GPUFrameBuffer(color_slots=({"layer": probe, "texture": 1},))   # must work here
            _SWAPPED_SLOT_KEYS = True
    return _SWAPPED_SLOT_KEYS


def layer_slot(texture, layer: int) -> dict:
    """The ``color_slots`` entry of a GPUFrameBuffer that draws into layer
    ``layer`` of 2D array texture ``texture``, in the form this Blender reads."""
    if _slot_keys_swapped():
        # Read in order: the first key ("layer" != "texture") as the texture,
        # then "texture" (!= "layer") as the layer. Order matters.
        return {"layer": texture, "texture": int(layer)}
    return {"texture": texture, "layer": int(layer)}


# --- io_scene_gltf2: the bundled glTF exporter's modules and hook arguments ----------

def _first_module(*names):
    for name in names:
        try:
            return importlib.import_module(name)
        except ModuleNotFoundError:
            continue
    raise ModuleNotFoundError(f"none of {', '.join(names)} in this Blender's glTF exporter")


def gltf_binary_data():
    """The exporter's BinaryData class (a blob that becomes a buffer view):
    ``io.exp.binary_data`` from 4.5, ``io.exp.gltf2_io_binary_data`` in 4.2."""
    return _first_module("io_scene_gltf2.io.exp.binary_data",
                         "io_scene_gltf2.io.exp.gltf2_io_binary_data").BinaryData


def gltf_gather_mesh():
    """The exporter's ``gather_mesh(mesh, uuid_for_skined_data, vertex_groups,
    modifiers, materials, original_mesh, export_settings)``: in
    ``blender.exp.obj_data`` from 5.1 (which also gathers point clouds),
    ``blender.exp.mesh`` in 4.5 and 5.0, ``gltf2_blender_gather_mesh`` in 4.2."""
    return _first_module("io_scene_gltf2.blender.exp.obj_data", "io_scene_gltf2.blender.exp.mesh",
                         "io_scene_gltf2.blender.exp.gltf2_blender_gather_mesh").gather_mesh


def gltf_image_fills():
    """(Channel, FillImage) of the exporter's image encoder:
    ``blender.exp.material.encode_image`` from 4.5,
    ``material.extensions.gltf2_blender_image`` in 4.2."""
    m = _first_module("io_scene_gltf2.blender.exp.material.encode_image",
                      "io_scene_gltf2.blender.exp.material.extensions.gltf2_blender_image")
    return m.Channel, m.FillImage


def image_hook_args(args: tuple):
    """(export_image, blender_shader_sockets, export_settings) of the
    arguments ``gather_image_hook`` got after the glTF image. From 4.5 the
    exporter passes the ExportImage it encodes; 4.2 passes only the sockets,
    so the ExportImage is made from them by 4.2's own function (the one its
    gather_image called just before, with no UDIM tile)."""
    if len(args) == 3:
        return args
    sockets, export_settings = args
    gather = importlib.import_module("io_scene_gltf2.blender.exp.material.gltf2_blender_gather_image")
    get_image_data = vars(gather)["__get_image_data"]        # module-level: not name-mangled
    return get_image_data(sockets, None, export_settings), sockets, export_settings


# --- uv: Lightmap Pack with a margin in texels ---------------------------------------


def lightmap_pack(meshes, *, pack_in_one: bool, divisions: int) -> None:
    """Blender's Lightmap Pack of ``meshes`` (Object Mode, each mesh's active
    UV map, every face) with every packed box inset by 1 / ``divisions`` of
    the UV square on each side. The operator takes that inset as a
    percentage capped at 1 % (``PREF_MARGIN_DIV``, read as int(100 / m)
    divisions); PRTT needs up to padding / resolution (6 texels at 256²:
    2.3 %), so it calls the function behind the operator, whose signature is
    the same in every version claimed (bl_operators/uvcalc_lightmap.py,
    ``lightmap_uvpack``, 4.2 to 5.3). ``PREF_BOX_DIV`` is the operator's default."""
    from bl_operators import uvcalc_lightmap  # Blender's own scripts: loaded only to unwrap
    uvcalc_lightmap.lightmap_uvpack(list(meshes), PREF_SEL_ONLY=False, PREF_NEW_UVLAYER=False,
                                    PREF_PACK_IN_ONE=bool(pack_in_one), PREF_BOX_DIV=12,
                                    PREF_MARGIN_DIV=max(1, int(divisions)))
