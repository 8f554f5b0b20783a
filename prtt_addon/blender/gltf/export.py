"""``prtt export``: a baked .blend as a .glb for any glTF viewer, with PRTT's
transfer textures in the ``PRTT_radiance_transfer`` extension (docs/gltf.md).

Meshes, materials, cameras and lights are written by Blender's glTF exporter
(io_scene_gltf2, shipped with Blender). It calls the hooks of every enabled
add-on module that has ``glTF2ExportUserExtension`` (the package's
``__init__`` has one); they act only while :func:`export_glb` runs (the
user's own glTF exports stay untouched), and add:

* on the root: the SH convention and frame, the World's light, the display
  (exposure, view transform), the World's environment (its image file as it
  is, in a buffer view), and per texture set its transfer planes and bounce
  textures (relightable DC and glossy rows, or the baked bounce light) as
  KTX2 2D arrays in buffer views;
* on each baked object's or instance's node: its texture set, and an
  instance's tile of it (found in the exporter's tree by object and world
  matrix, :func:`_match`, in ``gather_gltf_hook`` once every node is made);
* on each of its mesh's primitives: the TEXCOORD set that holds the PRTT UVs;
  where the bake generated the UVs (curves, text, geometry-nodes faces,
  instances of a mesh without a PRTT map), the node gets a mesh made by the
  exporter from a temporary copy of the evaluated mesh that carries them
  (:func:`_triangle_mesh`, removed after the export);
* on each material of a baked object: the parameters the preview shades it
  with (the very PreviewMaterial the preview draws it with);
* the images of those materials' base colour and normal map are written as
  8-bit PNGs of the pixels the preview reads where Blender's exporter would
  not (float images: it writes their linear values truncated to 8 bits, where
  glTF's base colour is sRGB-encoded).

Nodes of the exporter's that Blender's render leaves out (a collection
excluded from the view layer, the usual source of collection instances; a
curve's own mesh listed again as a geometry-nodes instance) are taken out.
The exporter logs and swallows a hook's exception, so afterwards the file is
read back and refused unless every baked object and instance carries its set.
The .blend is never saved.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys

import bpy
import numpy as np

from ...core.base.atomic import atomic_write
from ...core.base.memory import MemoryLimitError, check_fits
from ...core.io.exr_io import read_edge_exr, read_lamp_exr, read_mask_exr
from ...core.io.gltf_prtt import (
    ENCODINGS,
    NAME,
    bounce_files_payload,
    display_extension,
    environment_extension,
    file_payloads,
    lamp_payload,
    lamps_extension,
    material_extension,
    read_glb_json,
    root_extension,
    set_payload_bytes,
    sun_extension,
    sun_payload,
)
from ...core.io.image_write import png_bytes, srgb8
from ...core.preview import pack as pp
from ...core.shading.shade import light_hash
from .. import versions
from ..blendfile import native_output_captured, open_scene
from ..preview import colour_management as colour
from ..preview.drawlist import collect
from ..preview.offscreen import RenderError, check_out
from ..record import bake_folder, generated_uvs, last_bake, materials_signature
from ..rna_arrays import RnaArrayError, read, write
from ..scene.job import GENERATED_UVS
from ..scene.lamps import scene_sun
from ..scene.scene_objects import GEOMETRY_TYPES, render_enabled
from ..scene.world import world_setup
from ..shared import UV_MAP

#: The largest World image carried in the .glb; a larger one is left out with a note.
ENVIRONMENT_MAX_BYTES = 64 << 20
#: The studio HDRI that lights an export whose World cannot be read (its image
#: missing, say): transfer and relightable bounces do not hold the light, so
#: the bake is still good; the note names the stand-in.
FALLBACK_LIGHT = "forest"
_ENVIRONMENT_MIME = {".exr": "image/x-exr", ".hdr": "image/vnd.radiance"}
#: glTF material texture of each material flag, as the viewer reads it.
_MATERIAL_TEXTURES = (("baseColorTexture", "pbrMetallicRoughness", "baseColorTexture", "base colour"),
                      ("roughnessTexture", "pbrMetallicRoughness", "metallicRoughnessTexture", "roughness"),
                      ("normalTexture", None, "normalTexture", "normal map"))


class GltfExportError(ValueError):
    """The scene cannot be exported as it is; the message says what to do."""


#: The export in progress (None: the hooks do nothing).
_ACTIVE = None


def hook(name: str):
    """The method ``name`` of the export in progress, for the package's
    ``glTF2ExportUserExtension`` (AttributeError when none runs: the
    exporter then skips the hook)."""
    if _ACTIVE is None or not name.endswith("_hook") or not hasattr(_ACTIVE, name):
        raise AttributeError(name)
    return getattr(_ACTIVE, name)


def _extension(data: dict):
    from io_scene_gltf2.io.com.gltf2_io_extensions import Extension  # Blender's bundled exporter
    return Extension(NAME, data, required=False)


@dataclasses.dataclass
class _Part:
    """A baked object or instance as the bake recorded it (the bake record's "parts": scene/job.py)."""

    name: str
    key: str
    set: int
    matrix: np.ndarray | None = None         # (4, 4) world, Blender frame (None: a bake before records)
    tile: tuple | None = None                # (columns, rows, column, row, inset)
    uv: str = "map"                          # "map" | "generated"
    uv_group: str = ""

    @property
    def geometry_nodes_instance(self) -> bool:
        """An instance made by geometry nodes (its source is its instancer)."""
        owner = self.key.split(":", 2)[1] if self.key.startswith("instance:") else ""
        return bool(owner) and self.key.endswith(f":{owner}")


def _parts(info: dict, set_numbers: dict) -> list:
    """The bake's parts, in its record's order."""
    out, recorded = [], info.get("objects", {})
    for name, rec in recorded.items():
        if rec.get("set") not in set_numbers:
            continue
        m = rec.get("matrix")
        out.append(_Part(name, rec.get("key") or f"object:{name}", set_numbers[rec["set"]],
                         None if m is None else np.asarray(m, np.float64),
                         tuple(rec["tile"]) if rec.get("tile") else None, rec.get("uv") or "map",
                         rec.get("uv_group") or ""))
    for set_name, names in info.get("set_objects", {}).items():      # objects without a record
        out += [_Part(n, f"object:{n}", set_numbers[set_name]) for n in names if n not in recorded]
    return out


def _match(vnode, parts: list):
    """The part the exporter's tree node ``vnode`` draws, or None: the same
    object (a real object, an instance's source, or a geometry-nodes
    instance's instancer) at the same world matrix."""
    ob = vnode.blender_object
    if ob is not None:
        keys = (f"object:{ob.name}",)
        suffix, prefix = f":{ob.name}", "instance:"
    elif getattr(vnode, "original_object", None) is not None:
        keys, suffix, prefix = (), f":{vnode.original_object.name}", f"instance:{vnode.original_object.name}:"
    else:
        return None
    M = np.array(vnode.matrix_world, np.float64)
    for p in parts:
        if not (p.key in keys or (p.key.startswith(prefix) and p.key.endswith(suffix))):
            continue
        if p.matrix is None or np.allclose(M, p.matrix, rtol=1e-6, atol=1e-5):
            return p
    return None


def _drop(vtree, vnode, scenes) -> None:
    """Take ``vnode``'s glTF node out of its parent's children (or the scenes' roots)."""
    parent = vtree.nodes.get(vnode.parent_uuid) if vnode.parent_uuid is not None else None
    holders = [parent.node.children] if parent is not None and getattr(parent, "node", None) is not None \
        else [sc.nodes for sc in scenes]
    for nodes in holders:
        for i in [i for i, n in enumerate(nodes) if n is vnode.node][::-1]:
            del nodes[i]


def _triangle_mesh(src, uv: np.ndarray, name: str):
    """A new Blender mesh of ``src``'s loop triangles, three corners each:
    its vertices, split normals (as custom normals), material indices and
    UV maps per corner, and "PRTT" = ``uv`` (T, 3, 2)."""
    src.calc_loop_triangles()
    T = len(src.loop_triangles)
    if uv.shape != (T, 3, 2):
        raise GltfExportError(f"its generated UVs ({uv.shape[0]} triangles) no longer match its mesh "
                              f"({T} triangles): bake again")
    nl = len(src.loops)
    loops = read(src.loop_triangles, "loops", 3, np.int32)
    verts = read(src.loop_triangles, "vertices", 3, np.int32)
    slots = read(src.loop_triangles, "material_index", 1, np.int32)
    normals = read(src.corner_normals, "vector", 3, expect=nl, what=f"{name}: corner normals")
    layers = [(u.name, read(u.uv, "vector", 2, expect=nl, what=f"{name}: UV map {u.name!r}")[loops],
               u.active_render, u.active) for u in src.uv_layers]
    tmp = bpy.data.meshes.new(name)
    try:
        tmp.vertices.add(len(src.vertices))
        write(tmp.vertices, "co", read(src.vertices, "co", 3), 3)
        tmp.loops.add(3 * T)
        write(tmp.loops, "vertex_index", verts.ravel(), 1, np.int32)
        tmp.polygons.add(T)
        write(tmp.polygons, "loop_start", np.arange(0, 3 * T, 3), 1, np.int32)
        write(tmp.polygons, "material_index", slots, 1, np.int32)
        tmp.update(calc_edges=True)
        if len(tmp.polygons) != T or len(tmp.loops) != 3 * T:
            raise GltfExportError(f"its triangles did not make a valid mesh ({len(tmp.polygons)} of {T})")
        if UV_MAP not in [n for n, *_ in layers]:
            layers.append((UV_MAP, None, False, False))
        for lname, values, render, active in layers:
            layer = tmp.uv_layers.new(name=lname)
            write(layer.uv, "vector", np.asarray(uv if lname == UV_MAP else values), 2)
            layer.active_render = bool(render)
            if active:
                tmp.uv_layers.active = layer
        tmp.normals_split_custom_set(normals[loops].reshape(-1, 3).tolist())
        return tmp
    except BaseException:
        bpy.data.meshes.remove(tmp)
        raise


class _Export:
    """The hooks of one export: what they add, and what they saw.

    blobs: [(path into the root extension's JSON, bytes)]: each becomes that
    object's ``bufferView``. materials: {Blender material name: its
    extension}; images: {Blender image name: (kind, pixels (H, W, 4) file
    order)} for the material images the export encodes itself."""

    def __init__(self, root: dict, blobs: list, parts: list, generated: dict, materials: dict, images: dict):
        self.root, self.blobs, self.parts, self.generated = root, blobs, parts, generated
        self.materials, self.images = materials, images
        self.nodes_tagged: set = set()
        self.generated_meshes: dict = {}       # uv group -> glTF mesh
        self.temporary_meshes: list = []       # Blender meshes made for the export (removed after it)
        self.errors: list = []
        self.rendered: set = set()             # the objects Blender renders (scene_objects.render_enabled)
        self.dropped: list = []                # nodes of the exporter's left out (_not_rendered)
        self.primitives_tagged = 0
        self.materials_tagged: set = set()
        self.images_encoded: dict = {}          # Blender image name -> kind
        self.notes: list = []
        self.log = ""                           # what Blender's exporter printed (export --verbose shows it)

    def gather_gltf_extensions_hook(self, gltf, export_settings):
        BinaryData = versions.gltf_binary_data()
        root = json.loads(json.dumps(self.root))
        for path, blob in self.blobs:
            target = root
            for key in path:
                target = target[key]
            target["bufferView"] = BinaryData(blob)          # the writer turns it into a buffer view index
        if gltf.extensions is None:
            gltf.extensions = {}
        gltf.extensions[NAME] = _extension(root)

    def gather_gltf_hook(self, active_scene_idx, scenes, animations, export_settings):
        """Every node gathered: each baked object's or instance's node found in
        the exporter's tree (by its object and world matrix, as the bake
        recorded them) gets its set and tile; one whose UVs the bake generated
        gets a mesh that carries them."""
        vtree = export_settings["vtree"]
        free = list(self.parts)
        for vnode in list(vtree.nodes.values()):
            node = getattr(vnode, "node", None)
            if node is None or node.mesh is None:
                continue
            part = _match(vnode, free)
            if part is None:
                if self._not_rendered(vnode):
                    _drop(vtree, vnode, scenes)
                    if vnode.blender_object is not None:
                        self.dropped.append(vnode.blender_object.name)
                continue
            free.remove(part)
            try:
                if part.uv == "generated":
                    node.mesh = self._generated_mesh(vnode, part, export_settings)
            except (GltfExportError, RnaArrayError, RuntimeError, ValueError) as exc:
                self.errors.append(f"{part.name}: {exc}")
                continue
            if node.extensions is None:
                node.extensions = {}
            ext = {"set": part.set}
            if part.tile is not None:
                ext["tile"] = [int(v) for v in part.tile[:4]] + [float(part.tile[4])]
            node.extensions[NAME] = _extension(ext)
            self.nodes_tagged.add(part.name)

    def _not_rendered(self, vnode) -> bool:
        """A node of the exporter's that Blender's render (and the preview) does
        not show: a top-level object of a collection excluded from the view
        layer or disabled in renders (the source of collection instances), or,
        with geometry-nodes instances exported, a curve's or text's own mesh
        a second time (the depsgraph lists it as an instance of itself)."""
        ob = vnode.blender_object
        if ob is not None:
            return vnode.parent_uuid is None and ob.type in GEOMETRY_TYPES and ob.name not in self.rendered
        orig = getattr(vnode, "original_object", None)
        return (orig is not None and orig.type != "MESH"
                and np.allclose(np.array(vnode.matrix_world), np.array(orig.matrix_world), atol=1e-6))

    def _generated_mesh(self, vnode, part: _Part, export_settings):
        """The glTF mesh of ``part`` with the UVs the bake generated as its
        PRTT TEXCOORD: Blender's exporter run on a temporary mesh (one per UV
        group: instances share it) made of the evaluated mesh's triangles,
        each with its own corners (the generated UVs are per triangle corner),
        its split normals, UV maps and material slots, and a "PRTT" UV map.
        The temporary mesh is removed after the export."""
        got = self.generated_meshes.get(part.uv_group)
        if got is not None:
            return got
        uv = self.generated.get(part.uv_group)
        if uv is None:
            raise GltfExportError(f"its generated UVs are not in the bake's {GENERATED_UVS}: bake again")
        ob = vnode.blender_object
        owner = ob if ob is not None else vnode.original_object
        if ob is not None:
            ob_eval = ob.evaluated_get(bpy.context.evaluated_depsgraph_get())
            src = ob_eval.to_mesh()
        else:                                          # a geometry-nodes instance: its mesh as the exporter has it
            ob_eval, src = None, vnode.data
        try:
            tmp = _triangle_mesh(src, uv, f"{owner.name} (PRTT)")
        finally:
            if ob_eval is not None:
                ob_eval.to_mesh_clear()
        self.temporary_meshes.append(tmp)
        materials = tuple(slot.material for slot in owner.material_slots)
        for m in materials:
            tmp.materials.append(m)
        got = versions.gltf_gather_mesh()(tmp, None, None, None, materials, None, export_settings)
        if got is None:
            raise GltfExportError("Blender's glTF exporter made no mesh of it")
        self.generated_meshes[part.uv_group] = got
        return got

    def gather_mesh_hook(self, gltf_mesh, blender_mesh, blender_object, vertex_groups, modifiers, materials,
                         export_settings):
        # The exporter passes no object for a mesh it shares between nodes: the
        # texcoord is the mesh's (its PRTT map); the set is each node's.
        # From 5.1 the exporter gathers point clouds through this hook too.
        names = [u.name for u in getattr(blender_mesh, "uv_layers", ())]
        if UV_MAP not in names:
            return
        texcoord = names.index(UV_MAP)            # the exporter writes UV maps in order, TEXCOORD_0 first
        for prim in gltf_mesh.primitives:
            if f"TEXCOORD_{texcoord}" not in prim.attributes:
                continue
            if prim.extensions is None:
                prim.extensions = {}
            prim.extensions[NAME] = _extension({"texCoord": texcoord})
            self.primitives_tagged += 1

    def gather_material_hook(self, gltf_material, blender_material, export_settings):
        name = getattr(blender_material, "name", None)
        if name not in self.materials:
            return
        if gltf_material.extensions is None:
            gltf_material.extensions = {}
        gltf_material.extensions[NAME] = _extension(dict(self.materials[name]))
        self.materials_tagged.add(name)

    def gather_image_hook(self, gltf_image, *args):
        """Base colour and normal map images of a PRTT material: the exporter's
        own bytes where they are the preview's pixels to 8 bits (an sRGB byte
        image's file, a byte normal map's file), else an 8-bit PNG made from
        the pixels the preview reads (sRGB-encoded for the base colour).
        ``args``: (export_image, sockets, export_settings), or (sockets,
        export_settings) in Blender 4.2 (versions.image_hook_args)."""
        export_image, blender_shader_sockets, export_settings = versions.image_hook_args(args)
        Channel, FillImage = versions.gltf_image_fills()
        BinaryData = versions.gltf_binary_data()
        sockets = {s.socket.name for s in blender_shader_sockets}
        kind = "base" if "Base Color" in sockets else "normal" if sockets == {"Normal"} else None
        fills = [export_image.fills.get(c) for c in (Channel.R, Channel.G, Channel.B)]
        if kind is None or not all(isinstance(f, FillImage) and f.src_chan == c
                                   for f, c in zip(fills, (Channel.R, Channel.G, Channel.B))):
            return
        img = fills[0].image
        if len({f.image.name for f in fills}) != 1 or self.images.get(img.name, (None,))[0] != kind:
            return
        srgb_byte = not img.is_float and img.colorspace_settings.name.lower().startswith("srgb")
        if (kind == "base" and srgb_byte) or (kind == "normal" and not img.is_float):
            return                                  # the exporter writes these bytes unchanged: the preview's pixels
        alpha = export_image.fills.get(Channel.A)
        if alpha is not None and not (isinstance(alpha, FillImage) and alpha.image.name == img.name
                                      and alpha.src_chan == Channel.A):
            self.notes.append(f"image {img.name!r}: its alpha comes from elsewhere; the glTF has Blender's "
                              f"exporter's PNG of it, not the preview's pixels")
            return
        rgba = pp.image_rgba(self.images[img.name][1])[::-1]    # (H, W, 4) file order, alpha 1 if none
        if alpha is None:
            rgba[..., 3] = 1.0
        if kind == "base":
            data = srgb8(rgba)
        else:
            data = np.round(np.clip(np.nan_to_num(rgba), 0.0, 1.0) * 255.0).astype(np.uint8)
        gltf_image.buffer_view = BinaryData(png_bytes(data))
        gltf_image.mime_type = "image/png"
        self.images_encoded[img.name] = kind


def _check_exportable(context, info: dict):
    """Refuse (GltfExportError) a bake that is missing, stale or partial.
    Returns the preview's
    (PreviewScene, PreviewStatus) of the bake (its light, its description)."""
    if info is None:
        raise GltfExportError("nothing baked in this scene: bake it first (python -m prtt_addon bake FILE.blend)")
    ps, status = collect(context, use_bounces=False, with_meshes=True, light_fallback=FALLBACK_LIGHT)
    problems = [t for level, t in status.messages if level in ("ERROR", "WARNING")]
    if ps is None or problems:
        raise GltfExportError("the bake cannot be exported as it is: " + "; ".join(problems or ["not drawable"])
                              + " (bake again, then export)")
    return ps, status


def _set_files(ps: pp.PreviewScene, folder: str, info: dict) -> list:
    """Per texture set, in export order: (set name, its objects, transfer
    file, relightable file or None, baked bounce level files, (sun mask
    file, its edges' file or None) or None: only where the preview draws the
    sun), the lamp mask file or None (where the preview draws lamps)."""
    out = []
    for set_name, objects in sorted(info["set_objects"].items()):
        pset = ps.sets.get(set_name)
        relight = pset.relight if pset is not None and pset.relight else None
        bounces = list(pset.bounces) if pset is not None and not relight and pset.bounces else []
        sun = (pset.sun, pset.sun_edge) if pset is not None and pset.sun and ps.sun is not None else None
        lamps = pset.lamps if pset is not None and pset.lamps and ps.lamps else None
        out.append((set_name, objects, os.path.join(folder, f"{set_name}.transfer.exr"), relight, bounces, sun,
                    lamps))
    return out


#: Copies of the payloads' bytes Blender's glTF exporter makes beyond PRTT's
#: own: its buffer (a bytearray they are appended to) and that buffer's
#: growth (a reallocation copies it).
EXPORTER_COPIES = 2


def _fits(needed: int, what: str) -> None:
    try:
        check_fits(needed, what, advice="free memory, export with --encoding u8, or bake at a lower resolution")
    except MemoryLimitError as exc:
        raise GltfExportError(str(exc)) from None


def _set_payloads(ps: pp.PreviewScene, folder: str, info: dict, notes: list,
                  encoding: str = "half") -> tuple[list, list, dict]:
    """The root's ``sets`` (transfer and bounce textures as KTX2), the blobs
    that go into buffer views, and {object: set index}. Each payload is
    made from its file a band of rows at a time (gltf_prtt.file_payloads),
    each set after a check that it fits (gltf_prtt.set_payload_bytes) beside the
    payloads made before it."""
    K = ps.bands * ps.bands
    sets, blobs, set_index = [], [], {}
    held = 0
    for i, (set_name, objects, transfer, relight, bounces, sun, lamps) in enumerate(_set_files(ps, folder, info)):
        _fits(set_payload_bytes(transfer, relight, bounces, K, encoding, sun, lamps),
              f"exporting texture set {set_name!r} (beside the {held / 2 ** 20:.0f} MiB of sets made before it)")
        made = file_payloads(transfer, encoding)
        meta = made["transfer"][1]
        entry = {"name": set_name, "resolution": [meta["width"], meta["height"]]}
        if relight:
            made.update(file_payloads(relight, encoding))
        elif bounces:
            b = bounce_files_payload(bounces, K, encoding)
            if isinstance(b, int):
                notes.append(f"texture set {set_name!r}: its bounce textures hold {b} coefficients, "
                             f"the bake {K}: left out of the glTF (bake again)")
            else:
                made["bounce"] = b
        if sun:
            mask_file, edge_file = sun
            mask = read_mask_exr(mask_file)[0]
            edges = read_edge_exr(edge_file)[0] if edge_file else None
            if edges is not None and edges.shape[:2] != mask.shape:
                raise GltfExportError(f"{edge_file}: {edges.shape[1]}x{edges.shape[0]} edges for a "
                                      f"{mask.shape[1]}x{mask.shape[0]} sun mask; bake again")
            # rows top first, as every payload
            made["sun"] = sun_payload(mask[::-1], None if edges is None else edges[::-1])
        if lamps:
            masks = read_lamp_exr(lamps, len(ps.lamps))[0]
            made["lamps"] = lamp_payload(masks[::-1])          # rows top first
        for key, (blob, meta) in made.items():
            entry[key] = meta
            blobs.append((("sets", i, key), blob))
            held += len(blob)
        sets.append(entry)
        for name in objects:
            set_index[name] = i
    return sets, blobs, set_index


def _environment(scene, notes: list, fallback: str = "") -> tuple[dict, bytes | None]:
    """The root's ``environment`` (the World the light was projected from, or
    the studio HDRI FALLBACK_LIGHT when ``fallback`` says why the World's
    cannot be read) and its image file's bytes (None: not carried, a note says why)."""
    st = scene.prtt
    if fallback:
        setup = world_setup(scene, source="BUILTIN", builtin=FALLBACK_LIGHT)
        notes.append(f"the World's light cannot be read ({fallback}): the glTF is lit by the studio HDRI "
                     f"{FALLBACK_LIGHT!r} instead; the transfer and relightable bounce textures do not hold the "
                     f"light, so a viewer's own environment relights them (baked bounce textures keep the "
                     f"light they were baked with); fix the World and export again to carry it")
    else:
        setup = world_setup(scene, source=st.light_source, builtin=st.builtin_environment or "forest")
    rotation, vector_type = setup.mapping or ((0.0, 0.0, 0.0), "POINT")
    common = dict(description=setup.description, strength=setup.strength, rotation=rotation,
                  vector_type=vector_type, lookup_rotation=setup.rotation)
    if isinstance(setup.source, np.ndarray):
        notes.append("the World is a constant colour: the glTF's environment has no image")
        return environment_extension(color=setup.source, **common), None
    path = setup.file or (setup.source() if setup.key[0] == "builtin" else "")
    if setup.key[0] == "panorama":
        notes.append(f"{setup.description}: the glTF carries its SH light, not an image")
        return environment_extension(**common), None
    if not path:
        notes.append(f"the World image {setup.image_name!r} is not an EXR/HDR file on disk (packed, generated "
                     f"or another format): the glTF's environment has no image")
        return environment_extension(**common), None
    size = os.path.getsize(path)
    if size > ENVIRONMENT_MAX_BYTES:
        notes.append(f"the World image {path} is {size / 2**20:.0f} MiB, over the "
                     f"{ENVIRONMENT_MAX_BYTES / 2**20:.0f} MiB the glTF carries: left out (the light's SH are in)")
        return environment_extension(**common), None
    with open(path, "rb") as f:
        blob = f.read()
    image = {"name": setup.image_name or os.path.basename(path),
             "mimeType": _ENVIRONMENT_MIME[os.path.splitext(path)[1].lower()], "bytes": len(blob)}
    return environment_extension(image=image, **common), blob


def _sun(context, ps: pp.PreviewScene, sets: list) -> dict | None:
    """The root's ``sun``: the sun the preview draws (the baked direction and
    disc, the lamp's colour and strength now), or None when no set carries a mask."""
    if ps.sun is None or not any("sun" in s for s in sets):
        return None
    live = scene_sun(context.scene, getattr(context, "view_layer", None))[0]
    return sun_extension(name=live.name, direction=ps.sun.direction, angle=ps.sun.angle, color=live.color,
                         strength=live.strength)


def _material_block(m: pp.PreviewMaterial, normal: int) -> dict:
    return material_extension(
        base_color=m.base_color, metallic=m.metallic, roughness=m.roughness, f0=m.f0,
        normal_strength=m.normal_strength, base_texture=m.base_texture >= 0,
        roughness_texture=m.roughness_texture >= 0, normal_texture=normal >= 0)


def _material_params(ps: pp.PreviewScene) -> tuple[dict, dict]:
    """{material name: extension} from the PreviewMaterials the preview draws,
    and {image name: (kind, pixels)} of their base colour and normal map images."""
    materials, images = {}, {}
    for name, m in zip(ps.material_names, ps.materials):
        if name is None:
            continue
        normal = m.normal_texture if ps.normal_maps else -1
        materials[name] = _material_block(m, normal)
        for kind, index in (("base", m.base_texture), ("normal", normal)):
            if index >= 0:
                images.setdefault(ps.image_names[index], (kind, ps.images[index]))
    return materials, images


def _check_materials(doc: dict, job: _Export, notes: list) -> None:
    """A note for each material flag whose texture Blender's exporter did not write."""
    for mat in doc.get("materials", []):
        ext = (mat.get("extensions") or {}).get(NAME)
        if not ext:
            continue
        for flag, group, key, what in _MATERIAL_TEXTURES:
            where = mat.get(group) or {} if group else mat
            if ext.get(flag) and key not in where:
                notes.append(f"material {mat.get('name')!r}: the preview reads its {what} from an image, but "
                             f"Blender's glTF exporter wrote no {key}; a viewer shows its factor instead")
    missing = sorted(set(job.materials) - job.materials_tagged)
    if missing:
        notes.append(f"materials without PRTT parameters in the glTF: {', '.join(missing[:8])}")


def export_glb(context, out: str, *, encoding: str = "half") -> dict:
    """Export ``context.scene`` to the .glb ``out`` (atomically). Returns a
    summary: sets, objects, bytes, notes. GltfExportError when it cannot."""
    scene = context.scene
    info = last_bake(scene)
    ps, status = _check_exportable(context, info)
    folder = bake_folder(scene, info)
    bands = int(info["settings"]["bands"])
    notes = []
    sets, blobs, set_index = _set_payloads(ps, folder, info, notes, encoding)
    payload = sum(len(b) for _, b in blobs)
    _fits(EXPORTER_COPIES * payload, f"Blender's glTF exporter's copy of the {payload / 2 ** 20:.0f} MiB of "
          f"baked textures")
    environment, env_blob = _environment(scene, notes, status.light_fallback)
    if env_blob is not None:
        blobs.append((("environment", "image"), env_blob))
    vs = scene.view_settings
    table = colour.display_of(scene)
    if table is not None:
        blobs.append((("display", "table"), table.payload()))
    if colour.unsupported(scene):
        notes.append(f"the viewer does not draw the colour management's {colour.unsupported(scene)}")
    display = display_extension(vs.exposure, vs.view_transform, look=vs.look, gamma=vs.gamma,
                                device=scene.display_settings.display_device, table=table)
    root = root_extension(bands=bands, light=ps.light, light_description=status.light_description, sets=sets,
                          display=display, environment=environment,
                          default_material=_material_block(pp.PreviewMaterial(), normal=-1),
                          sun=_sun(context, ps, sets),
                          lamps=lamps_extension(ps.lamps) if any("lamps" in s for s in sets) else None)
    materials, images = _material_params(ps)
    parts = _parts(info, {s["name"]: i for i, s in enumerate(sets)})
    generated = generated_uvs(folder) if any(p.uv == "generated" for p in parts) else {}
    prefs = context.preferences
    package = __name__.split(".blender.")[0]
    added = None
    if package not in prefs.addons:
        added = prefs.addons.new()               # the exporter finds hooks on enabled add-ons only
        added.module = package
    try:
        try:
            job, doc = _write(out, scene, context, (root, blobs, parts, generated, materials, images), lights=True)
        except _ExporterFailed as exc:
            if not exc.in_lights:
                raise _with_log(GltfExportError(exc.message), exc.log) from None
            # Blender's exporter fails on some lamps (bpy 5.0.1: a point lamp with Normalize off):
            # PRTT does not use them, so they are left out rather than the whole export.
            job, doc = _write(out, scene, context, (root, blobs, parts, generated, materials, images),
                              lights=False)
            notes.append(f"lamps left out of the glTF: Blender's glTF exporter failed on them ({exc.last}); "
                         f"PRTT's light is the World")
    finally:
        if added is not None:
            prefs.addons.remove(added)
    _check_materials(doc, job, notes)
    notes += job.notes
    if job.dropped:
        notes.append(f"left out of the glTF, as Blender's render leaves them out: {', '.join(job.dropped[:8])}")
    if job.images_encoded:
        notes.append("material images written from the pixels the preview reads, as 8-bit PNGs (base colour "
                     "sRGB-encoded): " + ", ".join(sorted(job.images_encoded)))
    b = info.get("bounce")
    if b:
        stale = []
        if b.get("light_hash") and light_hash(ps.light) != b["light_hash"]:
            stale.append("the World light changed")
        sig = info.get("materials_signature")
        if sig and materials_signature(scene) != sig:
            stale.append("materials changed")
        if stale:
            notes.append("the bounce textures are stale (" + ", ".join(stale) + "): exported as baked; bake "
                         "again to update them")
    return {"sets": len(sets), "objects": len(set_index), "bytes": os.path.getsize(out), "notes": notes,
            "images_encoded": dict(job.images_encoded), "exporter_log": job.log}


class _ExporterFailed(Exception):
    """Blender's glTF exporter raised: ``message`` says what failed and what to
    do, ``last`` is its error's last line, ``in_lights`` whether it failed
    gathering a lamp."""

    def __init__(self, text: str, log: str = ""):
        self.log = log
        lines = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.startswith("Location:")]
        self.last = lines[-1] if lines else "no message"
        self.in_lights = any("exp/light" in ln or "light_spots" in ln or "Light." in ln for ln in lines)
        # the cause is in what it printed before failing, not in its exception: an image
        # it could not read, or its own ERROR line ("UDIM packed images are not supported ...")
        printed = (log + "\n" + text).splitlines()
        cannot = next((ln for ln in printed if "Cannot read" in ln), None)
        said = next((ln.split("ERROR:", 1)[1].strip() for ln in printed if "| ERROR:" in ln), None)
        if said and not cannot:
            what = f"{said} (it then stopped: {self.last})"
        elif cannot:
            image = cannot.split("Cannot read", 1)[1].strip(" :'\"").split("'")[0]
            what = (f"it cannot read an image ({image}): "
                    f"an image file or UDIM tile is missing; find it (File > External Data > Report Missing "
                    f"Files) or remove it from the material, then export again")
        else:
            what = f"{self.last}; see docs/gltf.md (Limitations) or report it with the .blend"
        self.message = f"Blender's glTF exporter failed: {what}"
        super().__init__(self.message)


def _with_log(exc: Exception, log: str) -> Exception:
    """``exc`` carrying what Blender's exporter printed (``export --verbose`` shows it)."""
    exc.exporter_log = log
    return exc


def _write(out: str, scene, context, job_args, *, lights: bool):
    """Run Blender's glTF exporter with PRTT's hooks into ``out`` (atomically):
    (the hooks' _Export, the written glTF's JSON). _ExporterFailed when the
    exporter raises, GltfExportError when PRTT's data did not reach the file."""
    global _ACTIVE
    root, blobs, parts, generated, materials, images = job_args
    _ACTIVE = job = _Export(root, blobs, parts, generated, materials, images)
    job.rendered = render_enabled(scene, context.view_layer)
    try:
        with atomic_write(out) as tmp:
            target = tmp if tmp.endswith(".glb") else tmp + ".glb"
            try:
                # its ~30 INFO lines, and a failure's traceback, kept for --verbose (job.log)
                with native_output_captured() as log:
                    r = bpy.ops.export_scene.gltf(
                        filepath=target, export_format="GLB", use_selection=False, export_texcoords=True,
                        export_normals=True, export_cameras=True, export_lights=lights, export_apply=True,
                        # the pose the bake saw: armatures as posed, skinned meshes as deformed
                        export_rest_position_armature=False, export_skins=False,
                        export_tangents=any(m["normalTexture"] for m in materials.values()),
                        export_gn_mesh=any(p.geometry_nodes_instance for p in parts))
            except RuntimeError as exc:            # the exporter's own exception, as an operator error
                job.log = "".join(log)
                raise _ExporterFailed(str(exc), "".join(log)) from None
            job.log = "".join(log)
            if r != {"FINISHED"}:
                raise GltfExportError(f"Blender's glTF exporter did not finish ({r})")
            if target != tmp:
                os.replace(target, tmp)
            if job.errors:
                raise GltfExportError("could not export " + "; ".join(job.errors[:4]))
            try:
                doc = read_glb_json(tmp)
            except ValueError as exc:
                raise GltfExportError(f"the exporter did not write a .glb ({exc})") from exc
            missing = sorted({p.name for p in parts} - job.nodes_tagged)
            if NAME not in (doc.get("extensions") or {}) or missing or not job.primitives_tagged:
                raise _with_log(GltfExportError(
                    f"PRTT's data did not reach the file (objects without it: {', '.join(missing[:8]) or 'none'}; "
                    f"primitives tagged: {job.primitives_tagged}); `export --verbose` shows what Blender's "
                    f"exporter printed"), job.log)
    finally:
        _ACTIVE = None
        for m in job.temporary_meshes:
            bpy.data.meshes.remove(m)
    return job, doc


def export_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog, description="Export a baked .blend as a .glb: Blender's glTF with PRTT's transfer textures "
                               "(extension PRTT_radiance_transfer, docs/gltf.md). The .blend is not modified.",
        epilog="Exit status: 0 written; 1 not written (the message says why and what to do); 2 bad options.")
    p.add_argument("blend", help="a baked .blend file")
    p.add_argument("--out", required=True, help="the .glb to write (relative to where you run the command)")
    p.add_argument("--scene", help="scene name (default: the file's active scene)")
    p.add_argument("--verbose", action="store_true",
                   help="also print what Blender's glTF exporter printed (its INFO lines; quiet by default)")
    p.add_argument("--encoding", choices=ENCODINGS, default="half",
                   help="the textures' encoding: half (RGBA16F, the EXRs' values; default) or u8 (RGBA8 with a "
                        "scale and offset per plane: about half the bytes, error written per payload as maxError)")
    return p


def export_file(argv, prog="prtt export") -> int:
    args = export_parser(prog).parse_args(argv)
    if not args.out.lower().endswith(".glb"):
        print(f"prtt: error: --out {args.out}: the export writes .glb files", file=sys.stderr)
        return 2
    try:
        check_out(args.out, (".glb",))          # before the .blend is opened: seconds, not a temporary's name
    except RenderError as exc:
        print(f"prtt: error: {exc}", file=sys.stderr)
        return 1
    scene = open_scene(args.blend, args.scene)
    if scene is None:
        return 1
    out = os.path.abspath(args.out)
    try:
        with bpy.context.temp_override(scene=scene):
            summary = export_glb(bpy.context, out, encoding=args.encoding)
    except (GltfExportError, ValueError, OSError) as exc:
        if args.verbose and getattr(exc, "exporter_log", ""):
            print(exc.exporter_log.rstrip(), file=sys.stderr)
        print(f"prtt: error: {exc}", file=sys.stderr)
        return 1
    if args.verbose and summary["exporter_log"]:
        print(summary["exporter_log"].rstrip())
    for note in summary["notes"]:
        print(f"prtt: note: {note}")
    print(f"prtt: exported {summary['objects']} object(s) in {summary['sets']} texture set(s), "
          f"{summary['bytes']:,} bytes -> {out}")
    return 0
