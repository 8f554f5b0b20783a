"""The Blender scene -> a PreviewScene (core/preview/pack.py), cheaply, every frame.

What is drawn: every object of the last bake (``scene.prtt.last_bake``) that
still exists and is visible, with its *current* transform and evaluated mesh,
its set's transfer / bounce / per-vertex textures from the bake's folder, its
materials (Principled values and textures, parsed like the bake's export) and
the World light at the bake's band count.

Caches (module level, so the draw handler stays fast): meshes per object
(rebuilt when the depsgraph reports a geometry change), material images, the
World's unrotated SH projection (turning the environment or changing its
strength only rotates/scales coefficients), the per-vertex corner tables.
``clear_caches`` runs on file load and undo, when object pointers change.

Checks reported with the scene (``PreviewStatus``): objects moved or edited
since the bake, missing files, and stale bounce textures (the World light or
any material changed since they were baked).
"""
from __future__ import annotations

import dataclasses
import math
import os
import zipfile

import bpy
import numpy as np

from ...core.io.sidecars import read_corner_vertex
from ...core.light.envmap import compose_light
from ...core.light.lamp import LampError, lamps_from_list
from ...core.light.sun import Sun, SunError
from ...core.preview import pack as pp
from ...core.preview.shader_source import MAX_PREVIEW_BANDS
from ...core.shading.shade import light_hash
from .. import record
from ..rna_arrays import read
from ..scene import world_panorama
from ..scene.job import GENERATED_UVS, apply_tile
from ..scene.lamps import scene_lamps, scene_sun, unbaked_lamps
from ..scene.material_nodes import image_array, parse_material
from ..scene.scene_objects import scene_geometry
from ..scene.world import WorldLightError, dim_light_note, project_setup, world_setup
from ..shared import UV_MAP

_MESHES: dict = {}          # object name -> (signature, DrawMesh)
_IMAGES: dict = {}          # image key -> array
_PROJECTIONS: dict = {}     # (world key, bands) -> (K, 3)
_VERTEX_TABLES: dict = {}   # (path, mtime) -> corner_vertex
_GEOMETRY_GEN: dict = {}    # object name -> counter bumped on geometry updates


def clear_caches() -> None:
    for c in (_MESHES, _IMAGES, _VERTEX_TABLES):
        c.clear()
    record.clear_caches()


def note_depsgraph_updates(depsgraph) -> None:
    """depsgraph_update_post: remember what changed (no work here)."""
    for u in depsgraph.updates:
        idb = u.id
        if isinstance(idb, bpy.types.Object):
            if u.is_updated_geometry:
                name = idb.original.name if idb.original is not None else idb.name
                _GEOMETRY_GEN[name] = _GEOMETRY_GEN.get(name, 0) + 1
                record.materials_changed()        # slots and assignments live with the geometry
        elif isinstance(idb, (bpy.types.Material, bpy.types.Image, bpy.types.NodeTree)):
            record.materials_changed()
            if isinstance(idb, bpy.types.Image):
                for k in [k for k in _IMAGES if k[0] == idb.name]:
                    del _IMAGES[k]


@dataclasses.dataclass
class PreviewStatus:
    bake: dict | None = None
    messages: list = dataclasses.field(default_factory=list)    # (level, text): level INFO/WARNING/ERROR
    bounce_stale: list = dataclasses.field(default_factory=list)
    light_description: str = ""
    #: Why the World's light could not be read when a fallback light was used instead ("" otherwise).
    light_fallback: str = ""
    #: Why the sun's masks no longer match the scene's Sun lamp ("" when they do or there is none).
    sun_stale: str = ""
    #: The sun the preview draws, in words ("" when none): the panel's "Sun:" line.
    sun_description: str = ""
    #: Why a lamp's masks no longer match the scene ("" when they do or there are none).
    lamps_stale: str = ""
    #: The point and spot lamps the preview draws, in words ("" when none): the panel's "Lamps:" line.
    lamps_description: str = ""

    def add(self, level: str, text: str) -> None:
        self.messages.append((level, text))


# --- light ----------------------------------------------------------------------------

def current_light(scene, bands: int, setup=None, view_layer=None) -> tuple[np.ndarray, str]:
    """The World light at ``bands`` bands (or ``setup``'s), with its projection cached."""
    st = scene.prtt
    if setup is None:
        setup = world_setup(scene, source=st.light_source, builtin=st.builtin_environment or "forest",
                            view_layer=view_layer)
    key = (setup.key, bands)
    proj = _PROJECTIONS.get(key)
    if proj is None:
        if len(_PROJECTIONS) > 8:
            _PROJECTIONS.clear()
        proj = _PROJECTIONS[key] = project_setup(setup, bands)
    return compose_light(proj, setup.strength, setup.rotation), setup.description


# --- materials ------------------------------------------------------------------------

def _image_key(img, linear: bool) -> tuple:
    return (img.name, linear, img.filepath, tuple(img.size), img.colorspace_settings.name)


class _MaterialTable:
    """Materials and images of one frame, each once."""

    def __init__(self, normal_maps: bool):
        self.materials: list = []
        self.images: list = []
        self.image_keys: list = []
        self.names: list = []           # the Blender material of each entry of materials (None: no material)
        self.image_names: list = []     # the Blender image of each entry of images
        self._mat_index: dict = {}
        self._img_index: dict = {}
        self.normal_maps = normal_maps
        self.exports: list = []

    def _image(self, img, linear: bool) -> int:
        key = _image_key(img, linear)
        i = self._img_index.get(key)
        if i is None:
            arr = _IMAGES.get(key)
            if arr is None:
                arr = _IMAGES[key] = image_array(img, linearise=linear)
            i = self._img_index[key] = len(self.images)
            self.images.append(arr)
            self.image_keys.append("|".join(map(str, key)))
            self.image_names.append(img.name)
        return i

    def index(self, mat) -> int:
        key = mat.name if mat is not None else None
        i = self._mat_index.get(key)
        if i is None:
            ex = parse_material(mat, lambda _msg: None)
            spec = dict(ex.spec)
            spec.pop("name", None)
            base = self._image(ex.base_image, True) if ex.base_image is not None else -1
            rough = self._image(ex.rough_image, False) if ex.rough_image is not None else -1
            normal = -1
            if ex.normal_image is not None and self.normal_maps:
                normal = self._image(ex.normal_image, False)
            m = pp.PreviewMaterial.from_spec(spec, normal_texture=normal, normal_strength=ex.normal_strength)
            m = dataclasses.replace(m, base_texture=base, roughness_texture=rough)
            i = self._mat_index[key] = len(self.materials)
            self.materials.append(m)
            self.names.append(key)
            self.exports.append(ex)
        return i


# --- meshes ---------------------------------------------------------------------------

def _vertex_table(path: str) -> np.ndarray | None:
    try:
        key = (path, os.stat(path).st_mtime_ns)
    except OSError:
        return None
    t = _VERTEX_TABLES.get(key)
    if t is None:
        t = _VERTEX_TABLES[key] = read_corner_vertex(path)
    return t


def mesh_corners(ob_eval, table: _MaterialTable) -> tuple[dict, np.ndarray, list]:
    """Per-corner object-space arrays (T, 3, C) of an evaluated object, the
    material slot of each triangle (slots past the last one count as the last)
    and the slots' materials."""
    mesh = ob_eval.to_mesh()
    try:
        mesh.calc_loop_triangles()
        T = len(mesh.loop_triangles)
        if T == 0:
            return {}, np.zeros(0, np.int64), []
        nl = len(mesh.loops)
        loops = read(mesh.loop_triangles, "loops", 3, np.int32)
        verts = read(mesh.loop_triangles, "vertices", 3, np.int32)
        slot_of = read(mesh.loop_triangles, "material_index", 1, np.int32)
        co = read(mesh.vertices, "co", 3)
        normals = read(mesh.corner_normals, "vector", 3, expect=nl, what=f"{ob_eval.name}: corner normals")
        corners = {"positions": co[verts], "normals": normals[loops]}
        uvl = mesh.uv_layers.get(UV_MAP)
        if uvl is not None:
            corners["uv"] = read(uvl.uv, "vector", 2, expect=nl, what=f"{ob_eval.name}: UV map {UV_MAP!r}")[loops]
        slots = [s.material for s in ob_eval.material_slots] or [None]
        slot_of = np.clip(slot_of, 0, len(slots) - 1)
        render_uv = next((u.name for u in mesh.uv_layers if u.active_render), None)
        mat_uv = np.zeros((T, 3, 2), np.float32)
        nm_uv = np.zeros((T, 3, 2), np.float32)
        tangents = np.tile(np.array([1.0, 0.0, 0.0, 1.0], np.float32), (T, 3, 1))
        uv_cache, tan_cache = {}, {}

        def uv_of(name):
            if name not in uv_cache:
                layer = mesh.uv_layers.get(name) if name else None
                uv_cache[name] = None if layer is None else read(layer.uv, "vector", 2, expect=nl,
                                                                  what=f"{ob_eval.name}: UV map {name!r}")
            return uv_cache[name]

        def tangents_of(name):
            if name not in tan_cache:
                try:
                    mesh.calc_tangents(uvmap=name)
                    tan_cache[name] = np.concatenate([read(mesh.loops, "tangent", 3),
                                                      read(mesh.loops, "bitangent_sign")[:, None]], 1)
                except RuntimeError:
                    tan_cache[name] = None
            return tan_cache[name]

        for k in np.unique(slot_of):
            sel = slot_of == k
            mi = table.index(slots[k])
            ex, pm = table.exports[mi], table.materials[mi]
            if pm.base_texture >= 0 or pm.roughness_texture >= 0:
                uv = uv_of(ex.texture_uv or render_uv)
                if uv is not None:
                    mat_uv[sel] = uv[loops[sel]]
            if pm.normal_texture >= 0:
                name = ex.normal_uv or render_uv
                uv, tan = uv_of(name), tangents_of(name)
                if uv is not None and tan is not None:
                    nm_uv[sel] = uv[loops[sel]]
                    tangents[sel] = tan[loops[sel]]
        corners.update(mat_uv=mat_uv, nm_uv=nm_uv, tangents=tangents)
        return corners, slot_of, slots
    finally:
        ob_eval.to_mesh_clear()


def _draw_mesh(found, rec: dict, pset: pp.PreviewSet, table, status, generated: dict) -> pp.DrawMesh | None:
    """The DrawMesh of a baked object or instance (cached per part), its UVs
    the bake's (the PRTT map or generated ones, in its tile), its ranges mapped
    to this frame's materials."""
    ob_eval = found.evaluated
    name = rec["_name"]
    data = getattr(ob_eval, "data", None)
    slot_names = tuple(s.material.name_full if s.material else "" for s in ob_eval.material_slots)
    sig = (data.name_full if data is not None else "", _GEOMETRY_GEN.get(found.owner.name, 0),
           _GEOMETRY_GEN.get(found.source_name, 0), pset.name, pset.key, table.normal_maps, slot_names,
           rec.get("uv", "map"), tuple(rec.get("tile") or ()), id(generated.get(rec.get("uv_group"))))
    got = _MESHES.get(found.key)
    if got is not None and got[0] == sig:
        mesh = got[1]
    else:
        corners, slot_of, _slots = mesh_corners(ob_eval, table)
        if not corners:
            return None
        T = corners["positions"].shape[0]
        if rec.get("uv") == "generated":
            uv = generated.get(rec.get("uv_group"))
            if uv is None or uv.shape[0] != T:
                status.add("ERROR", f"{name}: its generated UVs ({GENERATED_UVS} in the bake folder) are "
                                    f"missing or no longer match its mesh; not drawn: bake again")
                return None
            corners["uv"] = uv
        elif "uv" not in corners:
            status.add("ERROR", f"{name}: no '{UV_MAP}' UV map any more; not drawn: unwrap and bake again")
            return None
        if rec.get("tile"):
            corners["uv"] = apply_tile(np.asarray(corners["uv"], np.float64), rec["tile"]).astype(np.float32)
        if pset.vertex:
            try:
                table_cv = _vertex_table(pset.vertex)
            except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
                status.add("ERROR", f"{name}: cannot read {pset.vertex} ({exc}); bake again")
                table_cv = None
            if table_cv is not None and rec.get("triangles") == T:
                o = int(rec.get("offset", 0))
                corners["vidx"] = table_cv[o:o + T].astype(np.float32)
        # Ranges hold material *slots*; each frame maps them to its own table.
        mesh = pp.build_mesh(name, pset.name, corners, slot_of, key=f"{found.key}|{hash(sig)}")
        _MESHES[found.key] = (sig, mesh)
    slots = [s.material for s in ob_eval.material_slots] or [None]
    ranges = [(table.index(slots[min(k, len(slots) - 1)]), f, c) for k, f, c in mesh.ranges]
    return dataclasses.replace(mesh, ranges=ranges)


def _parts_by_key(info: dict) -> dict:
    """{identity key: record} of the bake's parts (records of bakes before
    instances had no key: they were objects, keyed by name)."""
    out = {}
    for name, rec in info.get("objects", {}).items():
        rec = dict(rec, _name=name)
        out[rec.get("key") or f"object:{name}"] = rec
    recorded = set(info.get("objects", {}))
    for set_name, names in info.get("set_objects", {}).items():     # objects without a record
        for name in names:
            if name not in recorded:
                out[f"object:{name}"] = {"_name": name, "set": set_name}
    return out


# --- the frame --------------------------------------------------------------------------

def collect(context, *, visible=None, use_bounces: bool = True, with_meshes: bool = True,
            light_fallback: str | None = None) -> tuple[pp.PreviewScene | None, PreviewStatus]:
    """The PreviewScene of ``context.scene``'s last bake, and what to tell the user.

    visible(ob) -> bool decides visibility (default: ``ob.visible_get()``);
    with_meshes=False only checks (the panel): no mesh is read;
    light_fallback: a studio HDRI's name to light the scene with when the
    World's light cannot be read (the export's; status.light_fallback says why)."""
    scene = context.scene
    status = PreviewStatus()
    info = record.last_bake(scene)
    status.bake = info
    if info is None:
        status.add("INFO", "nothing baked yet: Bake Transfer first")
        return None, status
    bands = int(info["settings"]["bands"])
    if bands > MAX_PREVIEW_BANDS:
        status.add("ERROR", f"this bake has {bands} SH bands; the preview draws up to {MAX_PREVIEW_BANDS}: "
                            f"bake with {MAX_PREVIEW_BANDS} or fewer bands to preview it (the textures "
                            f"themselves are valid)")
        return None, status
    try:
        out_dir = record.bake_folder(scene, info)
    except ValueError as exc:
        status.add("ERROR", str(exc))
        return None, status
    files = set(info.get("files", []))
    bounce_files = (info.get("bounce") or {}).get("files", [])
    sets = {}
    for set_name in info.get("set_objects", {}):
        transfer = os.path.join(out_dir, f"{set_name}.transfer.exr")
        if not os.path.isfile(transfer):
            status.add("ERROR", f"texture set {set_name!r}: {transfer} is missing; bake again")
            continue
        bounces = tuple(os.path.join(out_dir, f) for f in bounce_files
                        if f.startswith(f"{set_name}.bounce") and os.path.isfile(os.path.join(out_dir, f)))
        vfile = f"{set_name}.vertex.npz"
        vertex = os.path.join(out_dir, vfile) if vfile in files and os.path.isfile(os.path.join(out_dir, vfile)) else None
        rfile = f"{set_name}.relight.exr"
        relight = os.path.join(out_dir, rfile) if rfile in bounce_files and os.path.isfile(
            os.path.join(out_dir, rfile)) else None
        sfile, efile = f"{set_name}.sun.exr", f"{set_name}.sun_edge.exr"
        sun_mask = os.path.join(out_dir, sfile) if sfile in files and os.path.isfile(
            os.path.join(out_dir, sfile)) else None
        sun_edge = os.path.join(out_dir, efile) if sun_mask and efile in files and os.path.isfile(
            os.path.join(out_dir, efile)) else None
        lfile = f"{set_name}.lamps.exr"
        lamp_masks = os.path.join(out_dir, lfile) if lfile in files and os.path.isfile(
            os.path.join(out_dir, lfile)) else None
        sets[set_name] = pp.PreviewSet(set_name, transfer, bounces, vertex, relight, sun_mask, sun_edge,
                                       lamp_masks, len((info.get("lamps") or {}).get("lamps") or ()) if lamp_masks else 0)
    try:
        light, status.light_description = current_light(scene, bands,
                                                         view_layer=getattr(context, "view_layer", None))
    except world_panorama.Pending as exc:        # drawn from the next frame, once rendered
        status.add("INFO", f"light: {exc}")
        return None, status
    except (WorldLightError, OSError, ValueError) as exc:
        if not light_fallback:
            status.add("ERROR", f"light: {exc}")
            return None, status
        # The textures do not hold the light (transfer, relightable bounces): a named stand-in lights the export.
        light, desc = current_light(scene, bands, world_setup(scene, source="BUILTIN", builtin=light_fallback))
        status.light_fallback = str(exc)
        status.light_description = f"{desc} (the World's light cannot be read: {exc})"
        status.add("INFO", f"light: {status.light_description}")
    unbaked = unbaked_lamps(scene, getattr(context, "view_layer", None))
    if unbaked:
        status.add("INFO", unbaked)         # a note: the export carries the lamps (glTF's own lights)
    sun = preview_sun(scene, getattr(context, "view_layer", None), info, status)
    lamps = preview_lamps(scene, getattr(context, "view_layer", None), info, status)
    # A dim World is the whole light only without a sun or lamps of the bake's.
    dim = dim_light_note(light, getattr(scene.view_settings, "exposure", 0.0)) if sun is None and not lamps else ""
    if dim:
        status.add("INFO", dim)
    normal_maps = bool(info["settings"].get("normal_maps", True))
    table = _MaterialTable(normal_maps)
    depsgraph = context.evaluated_depsgraph_get()
    visible = visible or (lambda ob: ob.visible_get())
    parts = _parts_by_key(info)
    generated = {}
    if any(r.get("uv") == "generated" for r in parts.values()):
        try:
            generated = record.generated_uvs(out_dir)
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            status.add("ERROR", f"cannot read {os.path.join(out_dir, GENERATED_UVS)} ({exc}); bake again")
    meshes, moved, edited = [], [], []
    for found in scene_geometry(depsgraph, scene, context.view_layer, visible=visible):
        rec = parts.get(found.key)
        if rec is None or rec["set"] not in sets:
            continue
        name = rec["_name"]
        M = found.matrix
        if "matrix" in rec and not np.allclose(M, np.asarray(rec["matrix"]), rtol=0, atol=1e-6):
            moved.append(name)
        if not with_meshes:
            continue
        mesh = _draw_mesh(found, rec, sets[rec["set"]], table, status, generated)
        if mesh is None:
            continue
        meshes.append(dataclasses.replace(mesh, matrix=M))
        if rec.get("triangles") not in (None, mesh.triangles):
            edited.append(name)
    if moved:
        status.add("WARNING", f"moved since the bake (its shadows are where it was): {', '.join(moved[:4])}")
    if edited:
        status.add("WARNING", f"mesh edited since the bake: {', '.join(edited[:4])}")
    b = info.get("bounce")
    if b and use_bounces:
        if b.get("light_hash") and light_hash(light) != b["light_hash"]:
            status.bounce_stale.append("the World light changed")
        if b.get("light_hash") and _sun_light_changed(info.get("sun"), sun):   # baked bounces bake the sun's in
            status.bounce_stale.append("the sun's colour or strength changed")
        sig = info.get("materials_signature")
        if sig and record.materials_signature(scene) != sig:
            status.bounce_stale.append("materials changed")
        if status.bounce_stale:
            status.add("WARNING", "bounce textures are stale (" + ", ".join(status.bounce_stale)
                       + "): Bake again to update them")
    ps = pp.PreviewScene(bands=bands, meshes=meshes, materials=table.materials, sets=sets, light=light,
                         images=table.images, image_keys=table.image_keys, use_bounces=use_bounces,
                         normal_maps=normal_maps, material_names=table.names, image_names=table.image_names,
                         sun=sun, lamps=lamps)
    return ps, status


def _sun_light_changed(baked: dict | None, sun: "pp.PreviewSun | None") -> bool:
    """Whether the sun's light a baked bounce holds (the bake's sun: strength x
    colour; none without one) differs from the sun drawn now (none: gone)."""
    if not baked:
        return False                  # a bake without a sun: its bounce holds none, and none is drawn with it
    try:
        then = float(baked["strength"]) * np.asarray(baked["color"], np.float64)
    except (KeyError, TypeError, ValueError):
        return True
    now = np.zeros(3) if sun is None else np.asarray(sun.irradiance, np.float64)
    return then.shape != (3,) or not np.allclose(then, now, rtol=1e-6, atol=1e-9)


def preview_lamps(scene, view_layer, info: dict, status) -> tuple:
    """The point and spot lamps the preview draws, in the masks' channel
    order: each baked lamp where it was baked (its mask holds its shadows)
    with the scene's lamp of its name's colour, power and spot cone now (they
    change live); a moved or resized lamp makes the masks stale (a warning:
    drawn as baked until the next bake), a lamp gone is drawn dark, and a
    Point or Spot lamp the bake did not take is said."""
    spec = (info.get("lamps") or {}).get("lamps") or []
    live = {lp.name: lp for lp in scene_lamps(scene, view_layer)[0]}
    try:
        baked = lamps_from_list(list(spec))
    except LampError as exc:
        status.add("ERROR", f"the bake's lamps: {exc}; bake again")
        return ()
    new = [n for n in live if n not in {lp.name for lp in baked}]
    if new:
        status.add("INFO", f"lamp(s) not in the bake: {', '.join(repr(n) for n in new[:4])}: Bake again to add "
                           f"their light and shadows")
    out, stale, gone = [], [], []
    for lp in baked:
        now = live.get(lp.name)
        if now is None:
            gone.append(lp.name)
            out.append(dataclasses.replace(lp, power=0.0))
            continue
        why = now.moved_from(lp)
        if why:
            stale.append(why)
        out.append(dataclasses.replace(lp, power=now.power, color=now.color, axis=now.axis, kind=now.kind,
                                       spot_size=now.spot_size, spot_blend=now.spot_blend))
    if gone:
        status.add("INFO", f"baked lamp(s) gone from the scene (or hidden): {', '.join(repr(n) for n in gone[:4])}: "
                           f"drawn without them")
    if stale:
        status.lamps_stale = "; ".join(stale)
        status.add("WARNING", f"the lamps' shadows are stale ({status.lamps_stale}): drawn as baked; Bake again to "
                              f"update them")
    if out:
        status.lamps_description = ", ".join(f"{lp.kind.title()} {lp.name!r} {lp.power:.3g} W" for lp in out)
    return tuple(out)


def preview_sun(scene, view_layer, info: dict, status) -> "pp.PreviewSun | None":
    """The sun the preview draws: the baked sun's direction and disc (its
    masks hold their shadows) with the scene's Sun lamp's colour and strength
    now (they change live); a turned or resized lamp makes the masks stale
    (a warning: drawn as baked until the next bake), a Sun lamp the bake did
    not take is said, and a baked sun whose lamp is gone is not drawn."""
    live = scene_sun(scene, view_layer)[0]
    baked_spec = info.get("sun")
    if not baked_spec:
        if live is not None:
            status.add("INFO", f"the Sun {live.name!r} is not in the bake: Bake again to add its light and shadows")
        return None
    try:
        baked = Sun.from_dict({k: v for k, v in baked_spec.items() if k in ("name", "direction", "angle",
                                                                             "color", "strength", "shadow")})
    except SunError as exc:
        status.add("ERROR", f"the bake's sun: {exc}; bake again")
        return None
    if live is None:
        status.add("INFO", f"the baked sun {baked.name!r} is gone from the scene (or hidden): drawn without it")
        return None
    why = live.moved_from(baked)
    if why:
        status.sun_stale = why
        status.add("WARNING", f"the sun's shadows are stale ({why}): drawn as baked; Bake again to update them")
    status.sun_description = (f"{live.name!r}, {math.degrees(baked.angle):.2g} degree disc, {live.strength:.3g} W/m², "
                              + (f"shadows baked{' (stale)' if why else ''}" if baked.shadow else
                                 f"no shadow (its Shadow is off){' (stale)' if why else ''}"))
    return pp.PreviewSun(baked.direction, tuple(float(v) for v in live.irradiance), baked.angle)
