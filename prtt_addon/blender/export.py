"""The evaluated Blender scene -> a core Scene (the worker's job) and its light.

What goes in:

* every visible object with geometry in the evaluated depsgraph (modifiers
  applied, world transforms, instances), as triangles with split normals;
* objects whose ``prtt.bake`` is on (and selected, with "Selected Only") get
  texture sets and must have the "PRTT" UV map; every other object, and every
  instance (collection/geometry-node instances share one mesh, so they cannot
  hold a texture each), is an occluder only: it casts shadows and absorbs
  bounce light (scene set_id -1);
* materials per triangle (Principled/Diffuse/Glossy, see materials.py), their
  base-colour/roughness textures and tangent-space normal maps (tangents
  from Blender's MikkTSpace ``calc_tangents``);
* the light: the World (world.py) or a studio HDRI, as RGB SH.

Nothing in the .blend is modified: evaluated meshes are temporary.
"""
from __future__ import annotations

import dataclasses
import re

import numpy as np

from ..core.scene import NormalMap, Scene, SceneError
from .materials import image_array, parse_material
from .properties import UV_MAP

GEOMETRY_TYPES = {"MESH", "CURVE", "SURFACE", "META", "FONT"}


class ExportError(ValueError):
    """The scene cannot be baked as it is; the message says what to change."""


@dataclasses.dataclass
class ExportResult:
    scene: Scene
    set_objects: dict            # set name -> [object names]
    warnings: list
    occluders: int               # triangles that only cast shadows
    light: np.ndarray | None = None
    light_description: str = ""
    objects: dict = dataclasses.field(default_factory=dict)   # baked object -> set, triangles, offset, matrix


def safe_name(name: str, taken: set) -> str:
    """A file-name-safe, unique texture set name for an object name."""
    s = re.sub(r'[\\/:*?"<>|\x00-\x1f]', "_", name).strip().lstrip(".") or "object"
    base, i = s, 1
    while s in taken:
        i += 1
        s = f"{base}_{i}"
    taken.add(s)
    return s


def _foreach(coll, attr, n, width, dtype=np.float32):
    a = np.empty(n * width, dtype)
    coll.foreach_get(attr, a)
    return a.reshape(n, width) if width > 1 else a


def resolution_for(obj, mesh_area: float, st) -> int:
    """Texels per side for an object: its override, else texel density, else the scene's."""
    if obj.prtt.resolution > 0:
        return int(obj.prtt.resolution)
    if st.texel_density > 0 and mesh_area > 0:
        side = st.texel_density * mesh_area ** 0.5
        p2 = 1 << max(3, int(np.ceil(np.log2(max(side, 8.0)))))
        return int(min(p2, st.resolution))
    return int(st.resolution)


def export_scene(context, *, with_light: bool = True) -> ExportResult:
    """Collect the evaluated scene. Raises ExportError with the objects to fix."""
    st = context.scene.prtt
    depsgraph = context.evaluated_depsgraph_get()
    warnings, missing_uv = [], []
    parts = []                      # per object/instance dicts
    mats, mat_index = [], {}
    for inst in depsgraph.object_instances:
        ob = inst.object
        if ob.type not in GEOMETRY_TYPES:
            continue
        orig = ob.original
        baked = (not inst.is_instance and ob.type == "MESH" and orig.prtt.bake
                 and (not st.selection_only or orig.select_get()))
        try:
            mesh = ob.to_mesh()
        except RuntimeError:
            continue
        try:
            part = _mesh_part(ob, mesh, np.array(inst.matrix_world, dtype=np.float64), baked,
                              mats, mat_index, warnings)
        finally:
            ob.to_mesh_clear()
        if part is None:
            if baked:
                warnings.append(f"object {orig.name!r} has no faces; nothing to bake")
            continue
        if baked and part["uv"] is None:
            missing_uv.append(orig.name)
            continue
        part["name"] = orig.name
        part["baked"] = baked
        part["matrix"] = np.array(inst.matrix_world, dtype=np.float64)
        part["obj"] = orig
        parts.append(part)
    if missing_uv:
        raise ExportError(f"{len(missing_uv)} object(s) have no '{UV_MAP}' UV map: "
                          f"{', '.join(sorted(missing_uv)[:8])}; run PRTT > Unwrap first "
                          f"(or turn off their Bake Transfer)")
    if not any(p["baked"] for p in parts):
        raise ExportError("no object to bake: give a mesh object Bake Transfer (and a PRTT UV map)")
    return _assemble(context, parts, mats, warnings, st, with_light)


def _mesh_part(ob, mesh, M, baked, mats, mat_index, warnings):
    mesh.calc_loop_triangles()
    T = len(mesh.loop_triangles)
    if T == 0:
        return None
    loops = _foreach(mesh.loop_triangles, "loops", T, 3, np.int32)
    verts = _foreach(mesh.loop_triangles, "vertices", T, 3, np.int32)
    mat_idx = _foreach(mesh.loop_triangles, "material_index", T, 1, np.int32)
    co = _foreach(mesh.vertices, "co", len(mesh.vertices), 3).astype(np.float64)
    cn = _foreach(mesh.corner_normals, "vector", len(mesh.loops), 3).astype(np.float64)
    world = co @ M[:3, :3].T + M[:3, 3]
    N = np.linalg.inv(M[:3, :3]).T                # normals transform by the inverse transpose
    nw = cn @ N.T
    nw /= np.maximum(np.linalg.norm(nw, axis=1, keepdims=True), 1e-30)
    part = {"positions": world[verts], "normals": nw[loops].astype(np.float32), "loops": loops,
            "uv": None, "mesh_uvs": {}}
    uvl = mesh.uv_layers.get(UV_MAP) if baked else None
    if uvl is not None:
        part["uv"] = _foreach(uvl.uv, "vector", len(mesh.loops), 2).astype(np.float64)[loops]
    # Materials of this object's slots, shared across objects.
    slots = [s.material for s in ob.material_slots] or [None]
    ids = np.empty(T, np.int32)
    for k in np.unique(mat_idx):
        mat = slots[k] if 0 <= k < len(slots) else None
        key = mat.name if mat is not None else None
        if key not in mat_index:
            mat_index[key] = len(mats)
            mats.append(parse_material(mat, warnings.append))
        ids[mat_idx == k] = mat_index[key]
    part["material"] = ids
    # UV maps the object's textures and normal maps are sampled with.
    render_uv = next((u.name for u in mesh.uv_layers if u.active_render), None)
    wanted = set()
    for k in np.unique(ids):
        ex = mats[k]
        if ex.base_image is not None or ex.rough_image is not None:
            wanted.add(ex.texture_uv or render_uv)
        if ex.normal_image is not None:
            wanted.add(ex.normal_uv or render_uv)
    part["render_uv"] = render_uv
    for name in wanted:
        if name is None or name not in mesh.uv_layers:
            warnings.append(f"object {ob.original.name!r}: UV map {name!r} for its textures is missing")
            continue
        uv = _foreach(mesh.uv_layers[name].uv, "vector", len(mesh.loops), 2).astype(np.float64)[loops]
        tangents = None
        if any(mats[k].normal_image is not None and (mats[k].normal_uv or render_uv) == name for k in np.unique(ids)):
            try:
                mesh.calc_tangents(uvmap=name)
                tan = _foreach(mesh.loops, "tangent", len(mesh.loops), 3).astype(np.float64) @ M[:3, :3].T
                tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-30)
                sgn = _foreach(mesh.loops, "bitangent_sign", len(mesh.loops), 1)
                if np.linalg.det(M[:3, :3]) < 0:
                    sgn = -sgn                        # mirrored objects flip the bitangent
                tangents = np.concatenate([tan, sgn[:, None]], axis=1)[loops].astype(np.float32)
            except RuntimeError as exc:
                warnings.append(f"object {ob.original.name!r}: tangents for {name!r} failed ({exc}); "
                                f"its normal map is ignored")
        part["mesh_uvs"][name] = (uv, tangents)
    return part


def _assemble(context, parts, mats, warnings, st, with_light) -> ExportResult:
    taken, set_names, set_res, set_objects = set(), [], [], {}
    set_of_part = []
    if st.texture_sets == "ATLAS":
        set_names, set_res = ["atlas"], [[st.resolution, st.resolution]]
        set_objects["atlas"] = [p["name"] for p in parts if p["baked"]]
    for p in parts:
        if not p["baked"]:
            set_of_part.append(-1)
        elif st.texture_sets == "ATLAS":
            set_of_part.append(0)
        else:
            P = p["positions"]
            area = 0.5 * float(np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1).sum())
            name = safe_name(p["name"], taken)
            set_names.append(name)
            r = resolution_for(p["obj"], area, st)
            set_res.append([r, r])
            set_objects[name] = [p["name"]]
            set_of_part.append(len(set_names) - 1)
    # Textures and normal maps, each image once.
    textures, tex_index, nmaps, nm_of_mat = [], {}, [], {}

    def tex(img, linear):
        key = (img.name, linear)
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
    T = sum(p["positions"].shape[0] for p in parts)
    cat = lambda key: np.concatenate([p[key] for p in parts])  # noqa: E731
    uvs = np.concatenate([p["uv"] if p["uv"] is not None else np.zeros((p["positions"].shape[0], 3, 2))
                          for p in parts])
    set_id = np.concatenate([np.full(p["positions"].shape[0], s, np.int32) for p, s in zip(parts, set_of_part)])
    object_names = [p["name"] for p in parts]
    object_id = np.concatenate([np.full(p["positions"].shape[0], i, np.int32) for i, p in enumerate(parts)])
    material_id = cat("material")
    mat_uvs = np.zeros((T, 3, 2))
    nm_index = np.full(T, -1, np.int32)
    nm_uvs = np.zeros((T, 3, 2))
    tangents = np.zeros((T, 3, 4), np.float32)
    tangents[..., 0] = 1.0
    tangents[..., 3] = 1.0
    off = 0
    for p in parts:
        n = p["positions"].shape[0]
        for k in np.unique(p["material"]):
            sel = np.flatnonzero(p["material"] == k) + off
            ex = mats[k]
            tex_uv = ex.texture_uv or p["render_uv"]
            if tex_uv in p["mesh_uvs"]:
                mat_uvs[sel] = p["mesh_uvs"][tex_uv][0][sel - off]
            if k in nm_of_mat:
                nuv = ex.normal_uv or p["render_uv"]
                got = p["mesh_uvs"].get(nuv)
                if got is not None and got[1] is not None:
                    nm_index[sel] = nm_of_mat[k]
                    nm_uvs[sel] = got[0][sel - off]
                    tangents[sel] = got[1][sel - off]
        off += n
    occluders = int((set_id < 0).sum())
    try:
        sc = Scene(positions=cat("positions"), normals=cat("normals"), uvs=uvs,
                   set_id=set_id, set_names=set_names, set_resolution=np.array(set_res),
                   object_id=object_id, object_names=object_names,
                   nm_index=nm_index if nmaps else None, nm_uvs=nm_uvs if nmaps else None,
                   tangents=tangents if nmaps else None, normal_maps=nmaps,
                   material_id=material_id, materials=spec, mat_uvs=mat_uvs, textures=textures)
    except SceneError as exc:
        raise ExportError(_explain(exc, parts, set_of_part)) from exc
    res = ExportResult(sc, set_objects, warnings, occluders)
    # Where each baked object's triangles sit in its set (vertex transfer rows
    # follow this order) and where the object was, for the preview's checks.
    in_set: dict = {}
    for p, s in zip(parts, set_of_part):
        if s < 0:
            continue
        n = int(p["positions"].shape[0])
        res.objects[p["name"]] = {"set": set_names[s], "triangles": n, "offset": in_set.get(s, 0),
                                  "matrix": p["matrix"].tolist()}
        in_set[s] = in_set.get(s, 0) + n
    if with_light:
        from .world import world_light
        res.light, res.light_description = world_light(context.scene, max(st.bands, 1),
                                                       source=st.light_source,
                                                       builtin=st.builtin_environment or "forest")
    return res


def _explain(exc, parts, set_of_part) -> str:
    msg = str(exc)
    if "UVs outside [0, 1]" in msg:
        bad = [p["name"] for p, s in zip(parts, set_of_part)
               if s >= 0 and (p["uv"].min() < -1e-6 or p["uv"].max() > 1 + 1e-6)]
        return (f"the PRTT UV map of {', '.join(bad[:8])} leaves the [0, 1] square; "
                f"re-run PRTT > Unwrap (Smart UV Project, Lightmap Pack or xatlas)")
    return msg
