"""Unwrapping into the dedicated "PRTT" UV map, touching nothing else.

Methods: copy an existing map, Blender's Smart UV Project or Lightmap Pack
(on the PRTT map, made active only while the operator runs), or xatlas
in-process. Afterwards the user's active and render UV maps, the mesh's
selection flags, the active object, the selection and the mode are put back;
the PRTT map is checked for overlapping islands at the object's resolution.
"""
from __future__ import annotations

import contextlib

import bpy
import numpy as np

from ..core.raster import rasterize
from .properties import UV_MAP


class UnwrapError(ValueError):
    pass


#: The attribute behind each element collection's ``select`` flag.
_SELECT_ATTRIBUTE = {"vertices": ".select_vert", "edges": ".select_edge", "polygons": ".select_poly"}


def _select_flag_usable(me, coll: str) -> bool:
    """Whether ``coll``'s ``select`` flags can go through foreach_get/set safely.

    Blender 5.0.1's ``Mesh.from_pydata`` without explicit edges leaves
    ``.select_edge`` typed INT32_2D; ``edges.foreach_set("select", ...)`` then
    writes booleans into it and crashes Blender. Such a domain is left alone.
    """
    attr = me.attributes.get(_SELECT_ATTRIBUTE[coll])
    return attr is None or (attr.data_type == "BOOLEAN" and len(attr.data) == len(getattr(me, coll)))


@contextlib.contextmanager
def _preserved(context, objects):
    """Restore mode, selection, active object, active/render UV maps and mesh
    selection flags after the block."""
    view_layer = context.view_layer
    active = view_layer.objects.active
    mode = context.object.mode if context.object else "OBJECT"
    selected = [o for o in context.selected_objects]
    saved = {}
    for ob in objects:
        me = ob.data
        uv = me.uv_layers
        flags = {}
        for coll in ("vertices", "edges", "polygons"):
            if not _select_flag_usable(me, coll):
                continue
            c = getattr(me, coll)
            a = np.empty(len(c), bool)
            c.foreach_get("select", a)
            flags[coll] = a
        saved[ob.name] = (uv.active.name if uv.active else None,
                          next((u.name for u in uv if u.active_render), None), flags)
    try:
        yield
    finally:
        if context.object and context.object.mode != "OBJECT":
            bpy.ops.object.mode_set(mode="OBJECT")
        for ob in objects:
            me = ob.data
            act, render, flags = saved[ob.name]
            if act is not None and act in me.uv_layers:
                me.uv_layers.active = me.uv_layers[act]
            if render is not None and render in me.uv_layers:
                me.uv_layers[render].active_render = True
            for coll, a in flags.items():
                if _select_flag_usable(me, coll) and len(getattr(me, coll)) == len(a):
                    getattr(me, coll).foreach_set("select", a)
            me.update()
        for o in context.view_layer.objects:
            o.select_set(o in selected)
        view_layer.objects.active = active
        if active is not None and mode != "OBJECT" and active.mode != mode:
            try:
                bpy.ops.object.mode_set(mode=mode)
            except RuntimeError:
                pass


def prtt_layer(me):
    """The PRTT UV map of a mesh, created (as a non-render map) if missing."""
    uv = me.uv_layers.get(UV_MAP)
    if uv is None:
        render = next((u.name for u in me.uv_layers if u.active_render), None)
        uv = me.uv_layers.new(name=UV_MAP, do_init=False)
        if render is not None:                     # uv_layers.new may take the render flag
            me.uv_layers[render].active_render = True
    return uv


def _run_edit_mode_op(context, objects, op):
    """Run a UV operator with every object in edit mode, all faces selected and
    its PRTT map active."""
    if context.view_layer.objects.active is not None and context.view_layer.objects.active.mode != "OBJECT":
        bpy.ops.object.mode_set(mode="OBJECT")
    for o in context.view_layer.objects:
        o.select_set(False)
    for ob in objects:
        ob.select_set(True)
        me = ob.data
        me.uv_layers.active = prtt_layer(me)
    context.view_layer.objects.active = objects[0]
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.mesh.select_all(action="SELECT")
    op()
    bpy.ops.object.mode_set(mode="OBJECT")


def _xatlas(objects, resolution, padding, atlas):
    from ..core.unwrap import unwrap
    groups = [objects] if atlas else [[o] for o in objects]
    for group in groups:
        meshes = []
        for ob in group:
            me = ob.data
            me.calc_loop_triangles()
            T = len(me.loop_triangles)
            if T == 0:
                raise UnwrapError(f"object {ob.name!r} has no faces to unwrap")
            loops = np.empty(T * 3, np.int32)
            me.loop_triangles.foreach_get("loops", loops)
            verts = np.empty(len(me.loops), np.int32)
            me.loops.foreach_get("vertex_index", verts)
            co = np.empty(len(me.vertices) * 3, np.float32)
            me.vertices.foreach_get("co", co)
            M = np.array(ob.matrix_world, dtype=np.float64)
            world = co.reshape(-1, 3) @ M[:3, :3].T + M[:3, 3]
            meshes.append((world[verts], loops.reshape(-1, 3)))          # a vertex per loop
        uvs = unwrap(meshes, resolution, padding=padding)
        for ob, (v, f), uv in zip(group, meshes, uvs):
            per_loop = _loop_uvs(ob.data, v, f, uv)
            prtt_layer(ob.data).uv.foreach_set("vector", per_loop.ravel())
            ob.data.update()


def _loop_uvs(me, loop_pos, tris, tri_uv) -> np.ndarray:
    """Per-loop UVs from xatlas's per-triangle-corner UVs.

    Blender stores one UV per loop, shared by all triangles of a polygon; xatlas
    works on triangles and may put two triangles of a non-planar quad in
    different charts. Such polygons are mapped as a whole through the affine
    3D -> UV map of their largest triangle, so they stay in one chart.
    """
    n_loops = len(me.loops)
    per_loop = np.zeros((n_loops, 2), np.float64)
    per_loop[tris.reshape(-1)] = tri_uv.reshape(-1, 2)
    conflict = np.abs(per_loop[tris] - tri_uv).max(axis=(1, 2)) > 1e-7      # per triangle
    if not conflict.any():
        return per_loop.astype(np.float32)
    poly = np.empty(len(me.loop_triangles), np.int32)
    me.loop_triangles.foreach_get("polygon_index", poly)
    start = np.empty(len(me.polygons), np.int32)
    me.polygons.foreach_get("loop_start", start)
    total = np.empty(len(me.polygons), np.int32)
    me.polygons.foreach_get("loop_total", total)
    for p in np.unique(poly[conflict]):
        ts = np.flatnonzero(poly == p)
        P = loop_pos[tris[ts]]                                             # (t, 3, 3)
        area = np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1)
        best = ts[int(np.argmax(area))]
        a, b, c = loop_pos[tris[best]]
        e1, e2 = b - a, c - a
        n = np.cross(e1, e2)
        # Barycentric coordinates in the best triangle's plane -> its UVs.
        G = np.array([[e1 @ e1, e1 @ e2], [e1 @ e2, e2 @ e2]])
        loops = np.arange(start[p], start[p] + total[p])
        d = loop_pos[loops] - a
        d = d - np.outer(d @ n, n) / max(n @ n, 1e-300)
        st = np.linalg.solve(G, np.stack([d @ e1, d @ e2]))                 # (2, k)
        ua, ub, uc = tri_uv[best]
        per_loop[loops] = ua + np.outer(st[0], ub - ua) + np.outer(st[1], uc - ua)
    return np.clip(per_loop, 0.0, 1.0).astype(np.float32)


def unwrap_objects(context, objects, *, method: str, resolution: int, padding: int = 4,
                   atlas: bool = False, source_map: str = "") -> dict:
    """Write the PRTT UV map of ``objects``. Returns {object name: overlapping
    texels}. Meshes without faces (points, edges, or faces made only by
    geometry nodes, which get generated UVs at bake time) are left out of
    the result; only if every object is such a mesh is it an error."""
    objects = [o for o in objects if o.type == "MESH"]
    if not objects:
        raise UnwrapError("select one or more mesh objects to unwrap")
    faceless = [ob.name for ob in objects if len(ob.data.polygons) == 0]
    objects = [ob for ob in objects if len(ob.data.polygons) > 0]
    if not objects:
        raise UnwrapError(f"{', '.join(faceless[:8])}: no faces to unwrap (faces made by geometry "
                          f"nodes get UVs generated when baking)")
    margin = padding / max(resolution, 1)
    with _preserved(context, objects):
        if method == "EXISTING":
            for ob in objects:
                me = ob.data
                name = source_map or next((u.name for u in me.uv_layers if u.active_render and u.name != UV_MAP),
                                          None)
                if not name or name not in me.uv_layers or name == UV_MAP:
                    raise UnwrapError(f"object {ob.name!r} has no UV map {name or '(render UV map)'!r} to copy; "
                                      f"choose another method")
                src = np.empty(len(me.loops) * 2, np.float32)
                me.uv_layers[name].uv.foreach_get("vector", src)
                prtt_layer(me).uv.foreach_set("vector", src)
                me.update()
        elif method == "SMART":
            # Objects edited together are packed together: one call per object
            # for per-object texture sets, one call for an atlas.
            for group in ([objects] if atlas else [[o] for o in objects]):
                _run_edit_mode_op(context, group, lambda: bpy.ops.uv.smart_project(
                    island_margin=margin, scale_to_bounds=False))
        elif method == "LIGHTMAP":
            _run_edit_mode_op(context, objects, lambda: bpy.ops.uv.lightmap_pack(
                PREF_CONTEXT="ALL_FACES", PREF_PACK_IN_ONE=atlas,
                PREF_MARGIN_DIV=max(0.001, min(1.0, padding * 0.1 / 4.0))))
        elif method == "XATLAS":
            _xatlas(objects, resolution, padding, atlas)
        else:
            raise UnwrapError(f"unknown unwrap method {method!r}")
    return {ob.name: overlap_texels(ob, resolution) for ob in objects}


def overlap_texels(ob, resolution: int) -> int:
    """Texels of the object's PRTT map covered by more than one UV island."""
    me = ob.data
    me.calc_loop_triangles()
    T = len(me.loop_triangles)
    loops = np.empty(T * 3, np.int32)
    me.loop_triangles.foreach_get("loops", loops)
    uv = np.empty(len(me.loops) * 2, np.float32)
    me.uv_layers[UV_MAP].uv.foreach_get("vector", uv)
    tri_uv = uv.reshape(-1, 2).astype(np.float64)[loops].reshape(T, 3, 2)
    return rasterize(np.clip(tri_uv, 0.0, 1.0), resolution, resolution).overlap_texels
