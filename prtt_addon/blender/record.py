"""What the last bake recorded, and whether it still holds: the bake record
(``scene.prtt.last_bake``, JSON written by bake/run.py), its folder, the
generated UVs it wrote, and the materials' signature it was baked with.
The bake, the preview and the glTF export all read the record here.

Caches (module level): the materials' signature per scene until a material,
image or geometry changes (``materials_changed``, from the preview's
depsgraph handler), the generated UVs by file time. ``clear_caches`` on file
load and undo.
"""
from __future__ import annotations

import hashlib
import json
import os

import bpy
import numpy as np

from ..core.io.sidecars import read_generated_uvs
from .rna_arrays import read
from .scene.job import GENERATED_UVS, output_folder
from .scene.material_nodes import parse_material
from .scene.scene_objects import scene_geometry

_MATERIALS_GEN = [0]        # bumped on material/image/object updates
_SIGNATURES: dict = {}      # scene name -> (generation, signature)
_GENERATED: dict = {}       # generated_uvs.npz path -> ((path, mtime), {uv group: UVs})


def clear_caches() -> None:
    for c in (_SIGNATURES, _GENERATED):
        c.clear()
    _MATERIALS_GEN[0] += 1


def materials_changed() -> None:
    """A material, image, node tree or an object's geometry changed: the
    cached signatures are stale."""
    _MATERIALS_GEN[0] += 1


def last_bake(scene) -> dict | None:
    raw = scene.prtt.last_bake
    if not raw:
        return None
    try:
        return json.loads(raw)
    except ValueError:
        return None


def bake_folder(scene, info: dict) -> str:
    """The folder of the last bake: its //-relative form resolved against the
    .blend where it holds the bake (the project folder may have moved), else
    the absolute folder the bake wrote (the .blend saved elsewhere), else the
    scene's Output Folder."""
    for d in (info.get("out_dir_relative") or "", info.get("out_dir") or ""):
        if d.startswith("//"):
            d = bpy.path.abspath(d) if bpy.data.filepath else ""
        if d and os.path.isfile(os.path.join(d, "manifest.json")):
            return os.path.abspath(d)
    return output_folder(scene)


def materials_signature(scene) -> str:
    """A hash of what the bounce bake took from materials: every render-visible
    object's and instance source's slots (Principled values, image names and
    sizes, normal maps) and which faces use them. Cached until a material,
    image or geometry changes."""
    gen = _MATERIALS_GEN[0]
    got = _SIGNATURES.get(scene.name)
    if got is not None and got[0] == gen:
        return got[1]
    h = hashlib.sha256()
    done = set()
    view_layer = bpy.context.view_layer if bpy.context.scene == scene else scene.view_layers[0]
    depsgraph = bpy.context.evaluated_depsgraph_get() if bpy.context.scene == scene else None
    owners = ([f.source or f.owner for f in scene_geometry(depsgraph, scene, view_layer)]
              if depsgraph is not None else [o for o in scene.objects if o.visible_get()])
    for ob in sorted(owners, key=lambda o: o.name_full):
        if ob.name_full in done:
            continue
        done.add(ob.name_full)
        h.update(ob.name_full.encode())
        for slot in ob.material_slots:
            ex = parse_material(slot.material, lambda _msg: None)
            imgs = [(i.name, tuple(i.size)) if i is not None else None
                    for i in (ex.base_image, ex.rough_image, ex.normal_image)]
            h.update(json.dumps([ex.spec, imgs, ex.normal_strength, ex.texture_uv, ex.normal_uv],
                                sort_keys=True, default=str).encode())
        me = ob.data if ob.type == "MESH" else None
        if me is not None and len(me.polygons):
            h.update(read(me.polygons, "material_index", 1, np.int32).tobytes())
    sig = h.hexdigest()
    _SIGNATURES[scene.name] = (gen, sig)
    return sig


def generated_uvs(out_dir: str) -> dict:
    """{uv group: (T, 3, 2) float32} from the bake's generated_uvs.npz (cached by mtime)."""
    path = os.path.join(out_dir, GENERATED_UVS)
    try:
        key = (path, os.stat(path).st_mtime_ns)
    except OSError:
        return {}
    got = _GENERATED.get(path)
    if got is None or got[0] != key:
        got = _GENERATED[path] = (key, read_generated_uvs(path))
    return got[1]
