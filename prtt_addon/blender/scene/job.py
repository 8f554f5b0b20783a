"""The evaluated Blender scene -> a core Scene (the worker's job) and its light.

What goes in (scene_objects.py decides what the scene shows):

* every render-visible object and instance with faces in the evaluated
  depsgraph (modifiers and geometry nodes applied, world transforms), as
  triangles with split normals: meshes, curves, text, surfaces, metaballs,
  collection instances (nested, linked from libraries) and geometry-nodes
  instances;
* objects whose ``prtt.bake`` is on (and selected, with "Selected Only") get
  texels; every other object is an occluder only: it casts shadows and absorbs
  bounce light (scene set_id -1);
* **instances** share mesh data but not lighting: every instance gets texels
  of its own. Instances of one mesh share one texture set, laid out as a grid
  of tiles (one per instance, in depsgraph order), each tile holding the
  mesh's PRTT UV layout shrunk by a small inset (:data:`TILE_INSET`);
* UVs: the evaluated mesh's "PRTT" map where it has one. Geometry that cannot
  carry one (instances of meshes without it, curves and text, faces made by
  geometry nodes, linked library data) gets UVs generated with xatlas here, in
  memory: the user's data is not changed. They are written beside the
  textures (``generated_uvs.npz``) for the preview. A plain mesh object
  without the map is an error that says to unwrap it;
* objects with nothing to bake (no faces, zero area) are skipped with one
  warning naming them;
* materials per triangle (Principled/Diffuse/Glossy, see material_nodes.py), their
  base-colour/roughness textures and tangent-space normal maps (tangents
  from Blender's MikkTSpace ``calc_tangents``);
* the light: the World (world.py) or a studio HDRI, as RGB SH.

The parts become one core Scene through core.model.assembly (``assemble_parts``,
as meshgen's meshes do). Nothing in the .blend is modified: evaluated meshes
are temporary.
"""
from __future__ import annotations

import dataclasses
import math
import os
import re

import bpy
import numpy as np

from ...core.model.assembly import MeshPart, assemble_parts, default_tangents
from ...core.model.scene import MAX_RESOLUTION, NormalMap, Scene, SceneError
from ...core.texels.raster import overlap_count
from ...core.texels.unwrap import UnwrapError, unwrap
from ..rna_arrays import read
from ..shared import UV_MAP
from .lamps import scene_lamps, scene_sun, unbaked_lamps
from .material_nodes import image_array, parse_material
from .scene_objects import reported_without_faces, scene_geometry
from .uv_maps import generated_margin, needs_user_unwrap
from .world import world_light

#: Texels left empty on each side of an instance tile, so that bilinear lookups
#: and dilation of one instance never reach its neighbour's texels.
TILE_INSET = 2
#: Longest texture set name (it becomes a file name with a suffix).
MAX_SET_NAME = 96
#: File, beside the textures, of UVs the export generated (see module doc).
GENERATED_UVS = "generated_uvs.npz"


class ExportError(ValueError):
    """The scene cannot be baked as it is; the message says what to change."""


def output_folder(scene) -> str:
    """The absolute output folder; a relative one needs a saved .blend."""
    raw = scene.prtt.output_dir or "//prtt/"
    if raw.startswith("//") and not bpy.data.filepath:
        raise ExportError("the .blend file is not saved, so '//' has no folder: save the file, "
                          "or set an absolute Output Folder in PRTT > Bake")
    path = os.path.abspath(bpy.path.abspath(raw))
    if os.path.exists(path) and not os.path.isdir(path):
        raise ExportError(f"the output folder {path} is a file")
    return path


@dataclasses.dataclass
class ExportResult:
    scene: Scene
    set_objects: dict            # set name -> [part names]
    warnings: list
    occluders: int               # triangles that only cast shadows
    light: np.ndarray | None = None
    light_description: str = ""
    sun: object | None = None    # core.light.sun.Sun: the scene's Sun lamp, its mask baked (lamps.scene_sun)
    lamps: tuple = ()            # core.light.lamp.Lamp: its point and spot lamps, their masks baked (lamps.scene_lamps)
    objects: dict = dataclasses.field(default_factory=dict)   # part name -> record (see _records)
    generated_uvs: dict = dataclasses.field(default_factory=dict)  # uv group -> (T, 3, 2) float32


@dataclasses.dataclass
class Part:
    """One object or instance's triangles in world space, and where they go:
    the Blender side of a core.model.assembly.MeshPart (:func:`_mesh_parts`)."""

    key: str
    kind: str                    # "object" | "instance"
    owner: object                # original Object whose settings apply
    source: object | None        # original Object of an instance's geometry
    source_name: str
    matrix: np.ndarray           # (4, 4) float64
    positions: np.ndarray        # (T, 3, 3) float64 world
    normals: np.ndarray          # (T, 3, 3) float32 world
    material: np.ndarray         # (T,) int32 index into the export's materials
    mat_uvs: np.ndarray | None   # (T, 3, 2) float64 UVs of each triangle's material textures (None: none)
    normal_mapped: np.ndarray    # (T,) bool: its material's normal map has UVs and tangents here
    nm_uvs: np.ndarray | None    # (T, 3, 2) float64 UVs of the normal map where normal_mapped, else 0
    tangents: np.ndarray | None  # (T, 3, 4) float32 world tangent + sign where normal_mapped, else (1, 0, 0, 1)
    local: tuple                 # (object-space corner positions (L, 3), triangle corner ids (T, 3)) for xatlas
    data_name: str               # the evaluated mesh's data name (instances of one mesh share it)
    baked: bool = False
    uv: np.ndarray | None = None  # (T, 3, 2) float64 of the PRTT layout, before tiling
    uv_origin: str = ""          # "map" | "generated"
    uv_group: str = ""
    name: str = ""
    tile: tuple | None = None    # (columns, rows, column, row, inset): see apply_tile
    copies_faces: bool = False   # modifiers changed the face count (Array, Mirror ... may copy UVs)
    loose: tuple = (0, 0)        # (vertices in no edge, edges in no face): not baked, not shadowing

    @property
    def triangles(self) -> int:
        return int(self.positions.shape[0])


def safe_name(name: str, taken: set) -> str:
    """A file-name-safe, unique texture set name (at most MAX_SET_NAME characters)."""
    s = re.sub(r'[\\/:*?"<>|\x00-\x1f]', "_", name).strip().lstrip(".") or "object"
    s = s[:MAX_SET_NAME]
    base, i = s, 1
    while s in taken:
        i += 1
        suffix = f"_{i}"
        s = base[:MAX_SET_NAME - len(suffix)] + suffix
    taken.add(s)
    return s


#: Texels per metre an object's own texture set gets under Tuning "Auto" when
#: Texel Density is 0 (an 8 mm texel: the demo room's floor keeps 1024², a vase
#: gets 128²; per-object Resolution Override still wins).
AUTO_TEXEL_DENSITY = 128.0


def resolution_for(obj, mesh_area: float, st) -> int:
    """Texels per side for an object: its override, else texel density (Tuning
    Auto: AUTO_TEXEL_DENSITY when none is set), else the scene's."""
    if obj is not None and obj.prtt.resolution > 0:
        return int(obj.prtt.resolution)
    density = st.texel_density
    if density <= 0 and st.tuning == "AUTO":
        density = AUTO_TEXEL_DENSITY
    if density > 0 and mesh_area > 0:
        side = density * mesh_area ** 0.5
        p2 = 1 << max(3, int(np.ceil(np.log2(max(side, 8.0)))))
        return int(min(p2, st.resolution))
    return int(st.resolution)


def unwrap_resolution(ob, st) -> int:
    """Texels per side of the texture set the bake will give ``ob`` (what
    Unwrap leaves margins and counts overlaps for): the scene's resolution in
    an atlas, else :func:`resolution_for` of the mesh's world-space area
    (Tuning Auto and a Texel Density make Resolution a cap: a 6 m floor asked
    at 16384 gets 1024). Modifiers are not applied: the base mesh's area."""
    if st.texture_sets == "ATLAS":
        return int(st.resolution)
    me = ob.data
    me.calc_loop_triangles()
    co = read(me.vertices, "co", 3, np.float64)
    tris = read(me.loop_triangles, "vertices", 3, np.int64)
    M = np.array(ob.matrix_world, dtype=np.float64)
    P = (co @ M[:3, :3].T + M[:3, 3])[tris]
    return resolution_for(ob, _surface_area(P), st)


def _surface_area(P: np.ndarray) -> float:
    return 0.5 * float(np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1).sum())


def _bakes(found, st) -> bool:
    """Does the user want texels for this object/instance?"""
    owner = found.owner
    if not owner.prtt.bake or (st.selection_only and not owner.select_get()):
        return False
    return found.source is None or found.source == owner or found.source.prtt.bake


def export_scene(context, *, with_light: bool = True) -> ExportResult:
    """Collect the evaluated scene. Raises ExportError with the objects to fix."""
    st = context.scene.prtt
    depsgraph = context.evaluated_depsgraph_get()
    warnings, missing_uv, empty = [], [], []
    parts: list[Part] = []
    mats, mat_index = [], {}
    with_faces, loose = set(), {}
    for found in scene_geometry(depsgraph, context.scene, context.view_layer, include_viewport_hidden=True):
        ob = found.evaluated
        try:
            mesh = ob.to_mesh()
        except RuntimeError:
            continue
        try:
            part = _mesh_part(found, mesh, mats, mat_index, warnings)
        finally:
            ob.to_mesh_clear()
        if part is None:
            continue
        if _surface_area(part.positions) <= 0.0:
            empty.append(f"{found.owner.name} (zero area)")   # shows nothing, shadows nothing
            continue
        with_faces.add(found.owner.name)
        if any(part.loose):
            loose.setdefault(found.owner.name, part.loose)
        part.baked = _bakes(found, st)
        if part.baked and part.uv is None and found.kind == "object" and needs_user_unwrap(found.owner):
            missing_uv.append(found.owner.name)
            continue
        parts.append(part)
    zero = {e.split(" (")[0] for e in empty} - with_faces
    faceless = reported_without_faces(context.scene, context.view_layer, with_faces | zero)
    skipped = faceless + sorted(f"{n} (zero area)" for n in zero)
    if skipped:
        more = f" and {len(skipped) - 8} more" if len(skipped) > 8 else ""
        warnings.append(f"skipped {len(skipped)} object(s) with nothing to bake (no faces): "
                        f"{', '.join(skipped[:8])}{more}")
    if loose:
        warnings.append(loose_geometry_note(loose))
    if missing_uv:
        raise ExportError(f"{len(missing_uv)} object(s) have no '{UV_MAP}' UV map: "
                          f"{', '.join(sorted(missing_uv)[:8])}; run PRTT > Unwrap first "
                          f"(or turn off their Bake Transfer)")
    if not any(p.baked for p in parts):
        raise ExportError("no object to bake: give an object with faces Bake Transfer (and a PRTT UV map)"
                          + (f"; {warnings[-1]}" if skipped else ""))
    _name_parts(parts)
    return _assemble(context, parts, mats, warnings, st, with_light)


def loose_geometry_note(loose: dict) -> str:
    """The one line about loose geometry ({object: (vertices in no edge, edges
    in no face)}): it has no surface to bake or to cast shadows."""
    def count(v, e):
        words = [f"{v} loose {'vertex' if v == 1 else 'vertices'}"] if v else []
        return " and ".join(words + ([f"{e} loose edge{'' if e == 1 else 's'}"] if e else []))
    names = sorted(loose)
    more = f" and {len(names) - 8} more" if len(names) > 8 else ""
    return (f"ignored loose vertices and edges (in no face: nothing to bake, no shadow) in "
            f"{len(names)} object(s): " + ", ".join(f"{n} ({count(*loose[n])})" for n in names[:8]) + more)


def _name_parts(parts) -> None:
    """Unique display names: the object's name, "Instancer/Source" for
    collection instances, "Instancer[n]" for geometry-nodes instances."""
    count: dict = {}
    for p in parts:
        if p.kind == "object":
            base = p.owner.name
        elif p.source is None:
            base = f"{p.owner.name}[{{}}]"
        else:
            base = f"{p.owner.name}/{p.source_name}"
        count.setdefault(base, []).append(p)
    for base, group in count.items():
        for i, p in enumerate(group):
            if "{}" in base:
                p.name = base.format(i)
            else:
                p.name = base if len(group) == 1 else f"{base}[{i}]"

def _mesh_part(found, mesh, mats, mat_index, warnings) -> Part | None:
    """A Part from an evaluated mesh (None when it has no faces)."""
    mesh.calc_loop_triangles()
    T = len(mesh.loop_triangles)
    if T == 0:
        return None
    M = found.matrix
    L = len(mesh.loops)
    loops = read(mesh.loop_triangles, "loops", 3, np.int32)
    verts = read(mesh.loop_triangles, "vertices", 3, np.int32)
    mat_idx = read(mesh.loop_triangles, "material_index", 1, np.int32)
    co = read(mesh.vertices, "co", 3).astype(np.float64)
    cn = read(mesh.corner_normals, "vector", 3, expect=L, what=f"{found.owner.name}: corner normals").astype(np.float64)
    world = co @ M[:3, :3].T + M[:3, 3]
    N = np.linalg.inv(M[:3, :3]).T if abs(np.linalg.det(M[:3, :3])) > 1e-300 else np.eye(3)
    nw = cn @ N.T                                 # normals transform by the inverse transpose
    nw /= np.maximum(np.linalg.norm(nw, axis=1, keepdims=True), 1e-30)
    uvl = mesh.uv_layers.get(UV_MAP)
    uv = None
    if uvl is not None:
        uv = read(uvl.uv, "vector", 2, expect=L, what=f"{found.owner.name}: UV map {UV_MAP!r}").astype(np.float64)[loops]
    ob = found.evaluated
    who = found.owner.name
    # Materials of this object's slots, shared across objects (name_full: a
    # linked library's "Material" is not the local "Material").
    slots = [s.material for s in ob.material_slots] or [None]
    ids = np.empty(T, np.int32)
    for k in np.unique(mat_idx):
        mat = slots[k] if 0 <= k < len(slots) else slots[-1]
        key = mat.name_full if mat is not None else None
        if key not in mat_index:
            mat_index[key] = len(mats)
            mats.append(parse_material(mat, warnings.append))
        ids[mat_idx == k] = mat_index[key]
    # UV maps the object's textures and normal maps are sampled with.
    render_uv = next((u.name for u in mesh.uv_layers if u.active_render), None)
    wanted = set()
    for k in np.unique(ids):
        ex = mats[k]
        if ex.base_image is not None or ex.rough_image is not None:
            wanted.add(ex.texture_uv or render_uv)
        if ex.normal_image is not None:
            wanted.add(ex.normal_uv or render_uv)
    mesh_uvs = {}
    for name in wanted:
        if name is None or name not in mesh.uv_layers:
            warnings.append(f"object {who!r}: UV map {name!r} for its textures is missing")
            continue
        tuv = read(mesh.uv_layers[name].uv, "vector", 2, expect=L,
                   what=f"{who}: UV map {name!r}").astype(np.float64)[loops]
        tangents = None
        if any(mats[k].normal_image is not None and (mats[k].normal_uv or render_uv) == name for k in np.unique(ids)):
            try:
                mesh.calc_tangents(uvmap=name)
                tan = read(mesh.loops, "tangent", 3).astype(np.float64) @ M[:3, :3].T
                tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-30)
                sgn = read(mesh.loops, "bitangent_sign")
                if np.linalg.det(M[:3, :3]) < 0:
                    sgn = -sgn                        # mirrored objects flip the bitangent
                tangents = np.concatenate([tan, sgn[:, None]], axis=1)[loops].astype(np.float32)
            except RuntimeError as exc:
                warnings.append(f"object {who!r}: tangents for {name!r} failed ({exc}); "
                                f"its normal map is ignored")
        mesh_uvs[name] = (tuv, tangents)
    mat_uvs, normal_mapped, nm_uvs, tangents = _sampling_uvs(ids, mats, render_uv, mesh_uvs)
    data = getattr(ob, "data", None)
    # xatlas gets a vertex per corner (loop): it welds equal positions itself but
    # keeps the mesh's UV seams, and charts indexed vertices far worse (330
    # overlapping texels on Suzanne at 1024^2, against none).
    loop_vert = read(mesh.loops, "vertex_index", 1, np.int32)
    # Blender's loose elements: vertices in no edge, edges in no face.
    in_edge = np.zeros(len(mesh.vertices), bool)
    in_edge[read(mesh.edges, "vertices", 2, np.int32).ravel()] = True
    edges_in_faces = np.unique(read(mesh.loops, "edge_index", 1, np.int32)).size
    owner = found.owner
    copies = (found.kind == "object" and owner.type == "MESH"
              and len(mesh.polygons) != len(owner.data.polygons))
    return Part(key=found.key, kind=found.kind, owner=owner, source=found.source,
                source_name=found.source_name, matrix=M, positions=world[verts],
                normals=nw[loops].astype(np.float32), material=ids, mat_uvs=mat_uvs,
                normal_mapped=normal_mapped, nm_uvs=nm_uvs, tangents=tangents,
                local=(co[loop_vert], loops), uv=uv,
                data_name=data.name_full if data is not None else found.source_name,
                copies_faces=copies,
                loose=(int(len(in_edge) - in_edge.sum()), int(len(mesh.edges) - edges_in_faces)))


def _sampling_uvs(ids, mats, render_uv, mesh_uvs):
    """Per triangle, the UVs its material's textures and normal map are
    sampled with: (mat_uvs or None, normal_mapped, nm_uvs or None, tangents
    or None). ``mesh_uvs``: {UV map name: ((T, 3, 2) UVs, (T, 3, 4) tangents
    or None)} of the maps the materials use."""
    T = ids.shape[0]
    mat_uvs = nm_uvs = tangents = None
    normal_mapped = np.zeros(T, bool)
    for k in np.unique(ids):
        sel = ids == k
        ex = mats[k]
        got = mesh_uvs.get(ex.texture_uv or render_uv)
        if got is not None:
            if mat_uvs is None:
                mat_uvs = np.zeros((T, 3, 2))
            mat_uvs[sel] = got[0][sel]
        got = mesh_uvs.get(ex.normal_uv or render_uv) if ex.normal_image is not None else None
        if got is not None and got[1] is not None:
            if nm_uvs is None:
                nm_uvs = np.zeros((T, 3, 2))
                tangents = default_tangents(T)
            normal_mapped[sel] = True
            nm_uvs[sel] = got[0][sel]
            tangents[sel] = got[1][sel]
    return mat_uvs, normal_mapped, nm_uvs, tangents


def apply_tile(uv: np.ndarray, tile) -> np.ndarray:
    """UVs of a PRTT layout placed in an instance's tile.

    tile = (columns, rows, column, row, inset) with inset the empty border as a
    fraction of the tile; uv (..., 2) in [0, 1] -> the set's [0, 1] square."""
    if tile is None:
        return uv
    gx, gy, col, row, inset = tile
    scale = 1.0 - 2.0 * inset
    out = np.empty_like(uv)
    out[..., 0] = (col + inset + uv[..., 0] * scale) / gx
    out[..., 1] = (row + inset + uv[..., 1] * scale) / gy
    return out


def _generate_uvs(part: Part, resolution: int, padding: int) -> np.ndarray:
    """xatlas UVs (T, 3, 2) for a part's object-space mesh, in memory, with
    ``padding`` texels between charts (unwrap.margin_texels, as Unwrap uses)."""
    co, tris = part.local
    try:
        return unwrap([(co, tris)], max(8, int(resolution)), padding=padding)[0]
    except (UnwrapError, ValueError) as exc:
        raise ExportError(f"could not generate UVs for {part.name!r}: {exc}") from exc


def _overlaps(uv: np.ndarray, resolution: int) -> bool:
    """Do the (T, 3, 2) UVs overlap at this resolution (a texel centre in two triangles)?"""
    return overlap_count(np.clip(uv, 0.0, 1.0), resolution, resolution) > 0


def _layout(parts, st, warnings):
    """Texture sets, instance tiles and generated UVs of the baked parts.

    Returns (set names, set resolutions [[w, h]], set index per part (-1 for
    occluders), {uv group: generated (T, 3, 2) float32 UVs})."""
    taken, names, res = set(), [], []
    set_of = [-1] * len(parts)

    def new_set(name, w, h):
        names.append(safe_name(name, taken))
        res.append([int(w), int(h)])
        return len(names) - 1

    atlas = None
    groups: dict = {}
    for i, p in enumerate(parts):
        if not p.baked:
            continue
        p.uv_origin = "map" if p.uv is not None else "generated"
        if p.kind == "instance":
            groups.setdefault((p.source_name, p.data_name, p.triangles, p.uv_origin), []).append(i)
            continue
        p.uv_group = p.key
        in_atlas = st.texture_sets == "ATLAS"
        r = st.resolution if in_atlas else resolution_for(p.owner, _surface_area(p.positions), st)
        if p.uv_origin == "map" and p.copies_faces and _overlaps(p.uv, r):
            # Array/Mirror copies share the map's UVs: each copy needs texels of its own.
            p.uv_origin, p.uv = "generated", None
            warnings.append(f"object {p.owner.name!r}: its modifiers copy faces onto the same PRTT "
                            f"UVs (Array, Mirror...); baked with generated UVs (a layout with every "
                            f"copy, in a texture set of its own)")
            if in_atlas:
                r = resolution_for(p.owner, _surface_area(p.positions), st)
        if in_atlas and p.uv_origin == "map":
            if atlas is None:
                atlas = new_set("atlas", st.resolution, st.resolution)
            set_of[i] = atlas
            continue
        set_of[i] = new_set(p.owner.name, r, r)
    generated = {}
    for i, p in enumerate(parts):
        if p.baked and p.kind == "object" and p.uv_origin == "generated":
            w = res[set_of[i]][0]
            p.uv = _generate_uvs(p, w, generated_margin(st))
            generated[p.uv_group] = p.uv.astype(np.float32)
    for (source, _data, _T, origin), members in groups.items():
        first = parts[members[0]]
        settings_of = first.source if first.source is not None else first.owner
        r = resolution_for(settings_of, _surface_area(first.positions), st)
        n = len(members)
        gx = math.ceil(math.sqrt(n))
        gy = math.ceil(n / gx)
        if gx * r > MAX_RESOLUTION:
            fit = 1 << int(math.floor(math.log2(MAX_RESOLUTION // gx))) if MAX_RESOLUTION // gx >= 1 else 0
            if fit < 8:
                raise ExportError(f"{n} instances of {source!r} do not fit one texture set of "
                                  f"{MAX_RESOLUTION}^2 texels with 8 or more texels each")
            warnings.append(f"{n} instances of {source!r}: {fit}^2 texels each (not {r}^2) so their "
                            f"tiles fit one {MAX_RESOLUTION}-texel texture")
            r = fit
        s = new_set(f"{source}_instances", gx * r, gy * r)
        group = f"instances:{source}:{first.data_name}:{first.triangles}"
        if origin == "generated":
            uv = _generate_uvs(first, r, generated_margin(st))
            generated[group] = uv.astype(np.float32)
        inset = TILE_INSET / r if r > 4 * TILE_INSET else 0.0
        for j, i in enumerate(members):
            p = parts[i]
            if origin == "generated":
                p.uv = uv
            p.uv_group = group
            p.tile = (gx, gy, j % gx, j // gx, inset)
            set_of[i] = s
    return names, res, set_of, generated


def _assemble(context, parts, mats, warnings, st, with_light) -> ExportResult:
    set_names, set_res, set_of_part, generated = _layout(parts, st, warnings)
    set_objects = {n: [] for n in set_names}
    for p, s in zip(parts, set_of_part):
        if s >= 0:
            set_objects[set_names[s]].append(p.name)
    # Textures and normal maps, each image once.
    textures, tex_index, nmaps = [], {}, []
    nm_of_mat = np.full(len(mats), -1, np.int32)          # material -> normal map, -1 none

    def tex(img, linear):
        key = (img.name_full, linear)
        if key not in tex_index:
            tex_index[key] = len(textures)
            textures.append(image_array(img, linearise=linear))
        return tex_index[key]

    spec = []
    for k, ex in enumerate(mats):
        d = dict(ex.spec)
        if ex.base_image is not None:
            d["base_color_texture"] = tex(ex.base_image, True)
        if ex.rough_image is not None:
            d["roughness_texture"] = tex(ex.rough_image, False)
        if ex.normal_image is not None and st.normal_maps:
            nm_of_mat[k] = len(nmaps)
            nmaps.append(NormalMap(image_array(ex.normal_image, linearise=False)[..., :3], ex.normal_strength))
        spec.append(d)
    try:
        sc = assemble_parts(_mesh_parts(parts, set_of_part, nm_of_mat), set_names, set_res,
                            materials=spec, textures=textures, normal_maps=nmaps)
    except SceneError as exc:
        raise ExportError(_explain(exc, parts, set_of_part)) from exc
    occluders = int((sc.set_id < 0).sum())
    res = ExportResult(sc, set_objects, warnings, occluders, generated_uvs=generated)
    res.objects = _records(parts, set_of_part, set_names)
    if with_light:
        res.light, res.light_description = world_light(context.scene, max(st.bands, 1),
                                                       source=st.light_source,
                                                       builtin=st.builtin_environment or "forest",
                                                       view_layer=context.view_layer)
    res.sun = scene_sun(context.scene, context.view_layer)[0]
    res.lamps = scene_lamps(context.scene, context.view_layer)[0]
    lamps = unbaked_lamps(context.scene, context.view_layer)
    if lamps:
        warnings.append(lamps)
    return res


def _mesh_parts(parts, set_of_part, nm_of_mat) -> list[MeshPart]:
    """The core's view of the parts: world-space triangles laid out in their
    sets (instance tiles applied), materials, normal maps by index
    (``nm_of_mat``: material -> normal map, -1 none)."""
    out = []
    for p, s in zip(parts, set_of_part):
        nm_index = np.where(p.normal_mapped, nm_of_mat[p.material], -1).astype(np.int32)
        out.append(MeshPart(p.name, p.positions, p.normals, apply_tile(p.uv, p.tile) if p.baked else None, s,
                            material=p.material, mat_uvs=p.mat_uvs, nm_index=nm_index, nm_uvs=p.nm_uvs,
                            tangents=p.tangents))
    return out


def _records(parts, set_of_part, set_names) -> dict:
    """Per baked part, what the preview needs to draw it with its texels:
    its set, where its triangles sit in the set (vertex transfer rows follow
    this order), where it was (for the "moved" check), its identity among the
    depsgraph's instances, its UV origin and tile."""
    out: dict = {}
    in_set: dict = {}
    for p, s in zip(parts, set_of_part):
        if s < 0:
            continue
        out[p.name] = {"set": set_names[s], "triangles": p.triangles, "offset": in_set.get(s, 0),
                       "matrix": p.matrix.tolist(), "kind": p.kind, "key": p.key,
                       "owner": p.owner.name, "uv": p.uv_origin, "uv_group": p.uv_group,
                       "tile": list(p.tile) if p.tile is not None else None}
        in_set[s] = in_set.get(s, 0) + p.triangles
    return out


def _explain(exc, parts, set_of_part) -> str:
    msg = str(exc)
    if "UVs outside [0, 1]" in msg:
        bad = [p.name for p, s in zip(parts, set_of_part)
               if s >= 0 and (p.uv.min() < -1e-6 or p.uv.max() > 1 + 1e-6)]
        return (f"the PRTT UV map of {', '.join(bad[:8])} leaves the [0, 1] square; "
                f"re-run PRTT > Unwrap (Smart UV Project, Lightmap Pack or xatlas)")
    return msg
