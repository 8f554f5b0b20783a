"""``prtt export``: a baked .blend as a .glb for any glTF viewer, with PRTT's
transfer textures in the ``PRTT_radiance_transfer`` extension (docs/gltf.md).

Meshes, materials, cameras and lights are written by Blender's glTF exporter
(io_scene_gltf2, shipped with Blender). It calls the hooks of every enabled
add-on module that has ``glTF2ExportUserExtension`` (the package's
``__init__`` has one); they act only while :func:`export_glb` runs (the
user's own glTF exports stay untouched), and add:

* on the root: the SH convention and frame, the World's light, and per
  texture set its transfer planes as a KTX2 2D array in a buffer view;
* on each baked object's node: its texture set;
* on each of its mesh's primitives: the TEXCOORD set that holds the PRTT UVs.

The exporter logs and swallows a hook's exception, so afterwards the file is
read back and refused unless every baked object carries its set. What is not
exported yet is refused with a message, not skipped: instances and objects
with UVs generated at bake time (their UVs are not in a mesh the exporter
writes). A relightable bounce goes in as its DC rows (the diffuse bounce under
any light); its glossy rows and baked bounces are left out with a note. The
.blend is never saved.
"""
from __future__ import annotations

import argparse
import json
import os
import struct
import sys

import bpy
import numpy as np

from ...core.io.atomic import atomic_write
from ...core.io.exr_io import read_relight_exr, read_sh_exr
from ...core.io.gltf_prtt import NAME, relight_dc_payload, root_extension, transfer_payload
from ..blendfile import open_scene
from ..preview.drawlist import bake_folder, collect, last_bake
from ..shared import UV_MAP


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


class _Export:
    """The hooks of one export: what they add, and what they saw."""

    def __init__(self, root: dict, blobs: list, set_index: dict):
        self.root, self.blobs, self.set_index = root, blobs, set_index
        self.nodes_tagged: set = set()
        self.primitives_tagged = 0

    def gather_gltf_extensions_hook(self, gltf, export_settings):
        from io_scene_gltf2.io.exp.binary_data import BinaryData  # Blender's bundled exporter
        root = json.loads(json.dumps(self.root))
        for s, blobs in zip(root["sets"], self.blobs):
            for key, blob in blobs.items():
                s[key]["bufferView"] = BinaryData(blob)          # the writer turns it into a buffer view index
        if gltf.extensions is None:
            gltf.extensions = {}
        gltf.extensions[NAME] = _extension(root)

    def gather_node_hook(self, gltf_node, blender_object, export_settings):
        if blender_object is None or blender_object.name not in self.set_index:
            return
        if gltf_node.extensions is None:
            gltf_node.extensions = {}
        gltf_node.extensions[NAME] = _extension({"set": self.set_index[blender_object.name]})
        self.nodes_tagged.add(blender_object.name)

    def gather_mesh_hook(self, gltf_mesh, blender_mesh, blender_object, vertex_groups, modifiers, materials,
                         export_settings):
        # The exporter passes no object for a mesh it shares between nodes: the
        # texcoord is the mesh's (its PRTT map); the set is each node's.
        names = [u.name for u in blender_mesh.uv_layers]
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


def _check_exportable(context, info: dict):
    """Refuse (GltfExportError) a bake that is missing, stale, partial, or
    holds what the export cannot carry yet. Returns the preview's
    (PreviewScene, PreviewStatus) of the bake (its light, its description)."""
    if info is None:
        raise GltfExportError("nothing baked in this scene: bake it first (python -m prtt_addon bake FILE.blend)")
    ps, status = collect(context, use_bounces=False, with_meshes=True)
    problems = [t for level, t in status.messages if level in ("ERROR", "WARNING")]
    if ps is None or problems:
        raise GltfExportError("the bake cannot be exported as it is: " + "; ".join(problems or ["not drawable"])
                              + " (bake again, then export)")
    unsupported = sorted(name for name, rec in info.get("objects", {}).items()
                         if rec.get("kind", "object") != "object" or rec.get("uv") == "generated"
                         or rec.get("tile"))
    if unsupported:
        raise GltfExportError(f"the glTF export does not carry instances or UVs generated at bake time yet: "
                              f"{', '.join(unsupported[:8])}; give them a PRTT UV map (Unwrap) and no instancing, "
                              f"or leave them out of the bake")
    return ps, status


def _read_glb_json(path: str) -> dict:
    with open(path, "rb") as f:
        head = f.read(20)
        magic, _, _, n, kind = struct.unpack("<4sIIII", head)
        if magic != b"glTF" or kind != 0x4E4F534A:
            raise GltfExportError(f"{path}: the exporter did not write a .glb")
        return json.loads(f.read(n))


def export_glb(context, out: str) -> dict:
    """Export ``context.scene`` to the .glb ``out`` (atomically). Returns a
    summary: sets, objects, bytes. GltfExportError when it cannot."""
    global _ACTIVE
    scene = context.scene
    info = last_bake(scene)
    ps, status = _check_exportable(context, info)
    folder = bake_folder(scene, info)
    bands = int(info["settings"]["bands"])
    bounce = info.get("bounce") or {}
    relightable = any(f.endswith(".relight.exr") for f in bounce.get("files", []))
    sets, blobs, set_index = [], [], {}
    for i, (set_name, objects) in enumerate(sorted(info["set_objects"].items())):
        data, _ = read_sh_exr(os.path.join(folder, f"{set_name}.transfer.exr"))      # (H, W, K), row 0 at the bottom
        planes = np.ascontiguousarray(data[::-1].transpose(2, 0, 1))               # (K, H, W), top row first
        blob, meta = transfer_payload(planes)
        entry, payload = {"name": set_name, "resolution": [meta["width"], meta["height"]], "transfer": meta}, {}
        payload["transfer"] = blob
        relight = os.path.join(folder, f"{set_name}.relight.exr")
        if relightable and os.path.isfile(relight):
            dc, _, _ = read_relight_exr(relight)                   # (H, W, 3, K), row 0 at the bottom
            payload["relightDC"], entry["relightDC"] = relight_dc_payload(
                np.ascontiguousarray(dc[::-1].transpose(2, 3, 0, 1)))
        sets.append(entry)
        blobs.append(payload)
        for name in objects:
            set_index[name] = i
    root = root_extension(bands=bands, light=ps.light, light_description=status.light_description, sets=sets)
    prefs = context.preferences
    package = __name__.split(".blender.")[0]
    added = None
    if package not in prefs.addons:
        added = prefs.addons.new()               # the exporter finds hooks on enabled add-ons only
        added.module = package
    _ACTIVE = job = _Export(root, blobs, set_index)
    try:
        with atomic_write(out) as tmp:
            target = tmp if tmp.endswith(".glb") else tmp + ".glb"
            r = bpy.ops.export_scene.gltf(filepath=target, export_format="GLB", use_selection=False,
                                          export_texcoords=True, export_normals=True, export_cameras=True,
                                          export_lights=True, export_apply=True)
            if r != {"FINISHED"}:
                raise GltfExportError(f"Blender's glTF exporter did not finish ({r})")
            if target != tmp:
                os.replace(target, tmp)
            doc = _read_glb_json(tmp)
            missing = sorted(set(set_index) - job.nodes_tagged)
            if NAME not in (doc.get("extensions") or {}) or missing or not job.primitives_tagged:
                raise GltfExportError(f"PRTT's data did not reach the file (objects without it: "
                                      f"{', '.join(missing[:8]) or 'none'}; primitives tagged: "
                                      f"{job.primitives_tagged}); see Blender's log above")
    finally:
        _ACTIVE = None
        if added is not None:
            prefs.addons.remove(added)
    notes = []
    if bounce and not relightable:
        notes.append("baked bounce textures are not in the glTF (relightable ones are: --bounce-mode relightable)")
    elif relightable:
        notes.append("relightable bounces exported as their diffuse (DC) rows; their glossy rows are not in "
                     "the glTF yet")
    return {"sets": len(sets), "objects": len(set_index), "bytes": os.path.getsize(out), "notes": notes}


def export_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog, description="Export a baked .blend as a .glb: Blender's glTF with PRTT's transfer textures "
                               "(extension PRTT_radiance_transfer, docs/gltf.md). The .blend is not modified.",
        epilog="Exit status: 0 written; 1 not written (the message says why and what to do); 2 bad options.")
    p.add_argument("blend", help="a baked .blend file")
    p.add_argument("--out", required=True, help="the .glb to write (relative to where you run the command)")
    p.add_argument("--scene", help="scene name (default: the file's active scene)")
    return p


def export_file(argv, prog="prtt export") -> int:
    args = export_parser(prog).parse_args(argv)
    if not args.out.lower().endswith(".glb"):
        print(f"prtt: error: --out {args.out}: the export writes .glb files", file=sys.stderr)
        return 2
    scene = open_scene(args.blend, args.scene)
    if scene is None:
        return 1
    out = os.path.abspath(args.out)
    try:
        with bpy.context.temp_override(scene=scene):
            summary = export_glb(bpy.context, out)
    except (GltfExportError, ValueError, OSError) as exc:
        print(f"prtt: error: {exc}", file=sys.stderr)
        return 1
    for note in summary["notes"]:
        print(f"prtt: note: {note}")
    print(f"prtt: exported {summary['objects']} object(s) in {summary['sets']} texture set(s), "
          f"{summary['bytes']:,} bytes -> {out}")
    return 0
