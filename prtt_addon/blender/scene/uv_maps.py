"""Unwrapping into the dedicated "PRTT" UV map, touching nothing else.

Methods: copy an existing map, Blender's Smart UV Project or Lightmap Pack
(on the PRTT map, made active only while the operator runs), or xatlas
in a child process (core.texels.unwrap.unwrap_loops lays the loops out). Afterwards
the user's active and render UV maps, the mesh's selection flags, the active
object, the selection and the mode are put back; the PRTT map is checked for
overlapping islands at the object's resolution.
"""
from __future__ import annotations

import contextlib
import math

import bpy
import numpy as np

from ...core.texels.raster import overlap_count
from ...core.texels.unwrap import LoopMesh, UnwrapError, unwrap_loops
from ...core.texels.uv_gaps import UNWRAP_BUDGET, narrowest_gap
from .. import versions
from ..rna_arrays import read, write
from ..shared import UV_MAP

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
    """Run the block in Object Mode; restore mode, selection, active object,
    active/render UV maps and mesh selection flags after it.

    A mesh in Edit Mode keeps its data in the edit mesh: its UV layers read
    as empty and its loops, faces and flags are those of the last mode change.
    Leaving Edit Mode first writes the edits into the mesh (what Blender's own
    bake does), so everything read and written in the block is current (a
    .blend saved in Edit Mode opens in Edit Mode, also headless)."""
    view_layer = context.view_layer
    active = view_layer.objects.active
    mode = context.object.mode if context.object else "OBJECT"
    selected = [o for o in context.selected_objects]
    if mode != "OBJECT":
        bpy.ops.object.mode_set(mode="OBJECT")
    saved = {}
    for ob in objects:
        me = ob.data
        uv = me.uv_layers
        flags = {}
        for coll in ("vertices", "edges", "polygons"):
            if _select_flag_usable(me, coll):
                flags[coll] = read(getattr(me, coll), "select", 1, bool)
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
                    write(getattr(me, coll), "select", a, 1, bool)
            me.update()
        for o in context.view_layer.objects:
            o.select_set(o in selected)
        view_layer.objects.active = active
        if active is not None and mode != "OBJECT" and active.mode != mode:
            try:
                bpy.ops.object.mode_set(mode=mode)
            except RuntimeError:
                pass


def needs_user_unwrap(ob) -> bool:
    """Whether a mesh object should get its PRTT map from Unwrap (the user's
    layout, kept through its modifiers): a local mesh with faces of its own,
    without the map and without geometry nodes. Everything else that bakes
    (linked data, faces made only by modifiers or geometry nodes, curves,
    instances) gets UVs generated at export."""
    return (ob.type == "MESH" and ob.library is None and ob.data.library is None
            and UV_MAP not in ob.data.uv_layers and len(ob.data.polygons) > 0
            and not any(m.type == "NODES" for m in ob.modifiers))


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


def _loop_mesh(ob) -> LoopMesh:
    """An object's mesh as core.texels.unwrap wants it, in world space."""
    me = ob.data
    me.calc_loop_triangles()
    loops = read(me.loop_triangles, "loops", 3, np.int32)
    verts = read(me.loops, "vertex_index", 1, np.int32)
    co = read(me.vertices, "co", 3)
    poly = read(me.loop_triangles, "polygon_index", 1, np.int32)
    start = read(me.polygons, "loop_start", 1, np.int32)
    total = read(me.polygons, "loop_total", 1, np.int32)
    M = np.array(ob.matrix_world, dtype=np.float64)
    world = co @ M[:3, :3].T + M[:3, 3]
    return LoopMesh(world[verts], loops, verts, poly, start, total)


def _xatlas(objects, resolution, padding, atlas):
    groups = [objects] if atlas else [[o] for o in objects]
    for group in groups:
        layouts = unwrap_loops([_loop_mesh(ob) for ob in group], resolution, padding=padding)
        for ob, per_loop in zip(group, layouts):
            write(prtt_layer(ob.data).uv, "vector", np.clip(per_loop, 0.0, 1.0), 2,
                  what=f"{ob.name}: UV map {UV_MAP!r}")
            ob.data.update()


#: Smart UV Project angle limits, tried in turn until the layout has no
#: overlapping texels: Blender's default first; a lower limit cuts folded
#: regions (Suzanne's ears at 66 degrees) into more islands.
SMART_ANGLES = (66.0, 45.0, 30.0, 15.0)
#: Fewest texels between islands: one for bilinear lookups, one because the
#: rasteriser counts every texel a triangle touches.
MIN_MARGIN = 2


#: Texels between islands per step of the bounce grid's downscale: with
#: 3 f, no texel of the grid f times coarser sees two islands within its
#: 3 x 3 neighbourhood (core/texels/islands.coarse_grid_conflicts), so
#: tuning auto can bake the bounce on it. Measured on the demo room's Smart
#: UV Project atlas at 1024²: margin 4 -> 3,701 coarse texels mixing islands
#: at 1/2 (the bounce fell back to the full grid), 6 -> none, at 1 % fewer
#: covered texels.
MARGIN_PER_DOWNSCALE = 3


def margin_texels(padding: int, dilate: int = 0, bounce_downscale: int = 1) -> int:
    """Texels between UV islands at the object's resolution: the user's margin,
    at least MIN_MARGIN and at least the dilation, so that dilated borders of
    two islands do not meet (their mip levels stay apart too), and at least
    MARGIN_PER_DOWNSCALE x ``bounce_downscale`` when the bounce textures will
    be baked on a coarser grid (bake_downscale)."""
    coarse = MARGIN_PER_DOWNSCALE * int(bounce_downscale) if bounce_downscale > 1 else 0
    return max(int(padding), MIN_MARGIN, int(dilate), coarse)


def generated_margin(st) -> int:
    """Texels between the charts of UVs generated at bake time (meshes without
    a PRTT map): room for tuning auto's coarse bounce grid whatever the
    bounce settings, so that changing only those does not change the
    geometry (its hash holds the UVs) and bake the transfer again."""
    from ...core.bake.pipeline.bounce_stage import AUTO_DOWNSCALE  # see bake_downscale
    return margin_texels(st.padding, st.dilate, AUTO_DOWNSCALE)


def bake_downscale(st) -> int:
    """The bounce grid's downscale the bake will ask for with scene settings
    ``st`` (core/bake/pipeline/context.asked_downscale): what the unwrap leaves
    room for."""
    from ...core.bake.pipeline.bounce_stage import asked_downscale  # numpy-only core: cheap, but not needed at import
    tuning = str(st.tuning).lower()
    return asked_downscale(int(st.bounces), tuning, int(st.bounce_downscale))


def _overlap_of(objects, resolution: int, atlas: bool) -> int:
    """Overlapping texels: per object, or of all objects together for an atlas."""
    if not atlas or len(objects) == 1:
        return sum(overlap_texels(ob, resolution) for ob in objects)
    return overlap_count(np.concatenate([_tri_uvs(ob) for ob in objects]), resolution, resolution)


def _separate_and_pack(context, group, margin: float) -> None:
    """Make every face that overlaps another an island of its own and pack all
    islands again (Blender's Pack Islands, with rotation): what remains are
    whole faces, which cannot overlap themselves."""
    import bmesh
    ts = context.scene.tool_settings
    sync = ts.use_uv_select_sync

    def op():
        bpy.ops.uv.select_all(action="DESELECT")
        bpy.ops.uv.select_overlap()
        for ob in group:
            bm = bmesh.from_edit_mesh(ob.data)
            uvl = bm.loops.layers.uv.active
            # A different offset per face breaks its UV connection to every neighbour.
            for i, f in enumerate(x for x in bm.faces if x.select):
                for loop in f.loops:
                    loop[uvl].uv.x += 0.01 * (i + 1)
            bmesh.update_edit_mesh(ob.data)
        bpy.ops.mesh.select_all(action="SELECT")
        bpy.ops.uv.select_all(action="SELECT")
        bpy.ops.uv.pack_islands(margin_method="FRACTION", margin=margin, rotate=True)

    ts.use_uv_select_sync = True            # UV selection = face selection, as bmesh sees it
    try:
        _run_edit_mode_op(context, group, op)
    finally:
        ts.use_uv_select_sync = sync


def island_margin(padding: int, resolution: int) -> float:
    """Blender's ``FRACTION`` island margin (Pack Islands, Smart UV Project)
    for islands ``padding`` texels apart at ``resolution``: Blender keeps that
    fraction of the UV square around every island, so two islands end up
    twice it apart (measured on the UV map, core/texels/uv_gaps.py: 12 texels for
    a margin of 6 texels; PRTT's repacking of overlaps passed padding /
    resolution, twice the gap asked)."""
    return padding / (2.0 * max(resolution, 1))


def lightmap_divisions(padding: int, resolution: int, *, triangles: bool) -> int:
    """Lightmap Pack's margin divisions (versions.lightmap_pack) for islands
    ``padding`` texels apart or more at ``resolution``: every box is inset
    by 1 / divisions of the UV square on each side, so two boxes end up two
    insets apart. A quad or n-gon has a box of its own: an inset of half the
    padding. Triangles are paired into boxes, cut along the diagonal, and the
    two sit one inset or more apart (m (w + h - 2 m) / |diagonal| >= m for a
    w x h box): with ``triangles`` the inset is the whole padding. Before,
    PRTT passed the operator padding * 0.1 / 4, a fixed 1/2000 of the UV
    square per inset whatever the resolution: a 1-texel gap at 512² (issue 53)."""
    inset = max(int(padding), 1) if triangles else max(int(padding), 1) / 2.0
    return max(1, int(resolution / inset))


def _lightmap_pack(context, group, atlas: bool, padding: int, resolution: int) -> None:
    """Lightmap Pack of one set's objects into their PRTT maps, ``padding`` texels apart."""
    if context.view_layer.objects.active is not None and context.view_layer.objects.active.mode != "OBJECT":
        bpy.ops.object.mode_set(mode="OBJECT")
    triangles = False
    for ob in group:
        ob.data.uv_layers.active = prtt_layer(ob.data)
        sides = read(ob.data.polygons, "loop_total", 1, np.int32)
        triangles = triangles or bool((sides == 3).any())
    versions.lightmap_pack([ob.data for ob in group], pack_in_one=atlas,
                           divisions=lightmap_divisions(padding, resolution, triangles=triangles))


def _editable(ob) -> bool:
    return ob.visible_get() and not ob.hide_select and ob.library is None


def unwrap_objects(context, objects, *, method: str, resolution: int, padding: int = 4,
                   atlas: bool = False, source_map: str = "", dilate: int = 0, bounce_downscale: int = 1,
                   resolution_of=None) -> dict:
    """Write the PRTT UV map of ``objects``, ``padding`` texels apart or more
    (margin_texels) at the resolution each will be baked at:
    ``resolution_of(ob)`` for an object's own set (job.unwrap_resolution),
    ``resolution`` for an atlas or without it. Returns {object name:
    overlapping texels at that resolution}. Meshes
    without faces (points, edges, or faces made only by
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
    padding = margin_texels(padding, dilate, bounce_downscale)
    groups = [objects] if atlas else [[o] for o in objects]
    # per group: the texels a side of the set it is baked into
    res = [int(resolution) if atlas or resolution_of is None else int(resolution_of(g[0])) for g in groups]
    res_of = {ob.as_pointer(): r for g, r in zip(groups, res) for ob in g}     # (names can repeat across libraries)
    with _preserved(context, objects):
        if method == "EXISTING":
            for ob in objects:
                me = ob.data
                name = source_map or next((u.name for u in me.uv_layers if u.active_render and u.name != UV_MAP),
                                          None)
                if not name or name not in me.uv_layers or name == UV_MAP:
                    raise UnwrapError(f"object {ob.name!r} has no UV map {name or '(render UV map)'!r} to copy; "
                                      f"choose another method")
                src = read(me.uv_layers[name].uv, "vector", 2, expect=len(me.loops),
                           what=f"{ob.name}: UV map {name!r}")
                write(prtt_layer(me).uv, "vector", src, 2, what=f"{ob.name}: UV map {UV_MAP!r}")
                me.update()
        elif method == "SMART":
            # Objects edited together are packed together: one call per object
            # for per-object texture sets, one call for an atlas.
            for group, r in zip(groups, res):
                # Blender's SCALED margin follows the islands' scale: 7.25 texels on the
                # demo room where 6 are asked, but 2.5 on a cube and 3.2 on a torus
                # (core/texels/uv_gaps.py). Its exact FRACTION margin packs much sparser
                # (the demo: 6.6 % fewer texels; the web test's room at 256²: a 2.5x
                # smaller export). So the scaled margin is kept and raised, measured on
                # the map, until the islands are as far apart as asked (_smart_margin).
                for angle in SMART_ANGLES:
                    _smart_project(context, group, angle, padding, r)
                    if _overlap_of(group, r, atlas) == 0:
                        break
        elif method == "LIGHTMAP":
            for group, r in zip(groups, res):
                _lightmap_pack(context, group, atlas, padding, r)
        elif method == "XATLAS":
            if atlas or resolution_of is None:
                _xatlas(objects, resolution, padding, atlas)
            else:
                for group, r in zip(groups, res):
                    _xatlas(group, r, padding, False)
        else:
            raise UnwrapError(f"unknown unwrap method {method!r}")
        if method != "EXISTING":           # a copied map is the user's layout, kept as it is
            for group, r in zip(groups, res):
                if _overlap_of(group, r, atlas) and all(_editable(o) for o in group):
                    _separate_and_pack(context, group, island_margin(padding, r))
        # Counted before the mode is put back: in Edit Mode the map reads as empty.
        return {ob.name: overlap_texels(ob, res_of[ob.as_pointer()]) for ob in objects}


#: Tries of Smart UV Project's margin, each raised by what the last one left short.
SMART_MARGIN_TRIES = 4


def _smart_project(context, group, angle: float, padding: int, resolution: int) -> float | None:
    """Smart UV Project of ``group`` at ``angle`` degrees whose islands end at
    least ``padding`` texels of ``resolution`` apart: Blender's scaled margin
    asked for padding / resolution, then, while the narrowest gap measured on
    the map (core.texels.uv_gaps) is short of it, asked again for that much
    more (at most 4x a try, SMART_MARGIN_TRIES tries). Returns the narrowest
    gap in texels (inf: no two islands within padding + 1 texels; 0: islands
    touch, which a larger margin does not mend; None: too many triangles a
    texel to measure within UNWRAP_BUDGET, the first try kept)."""
    margin = padding / max(resolution, 1)
    gap = 0.0
    for _ in range(SMART_MARGIN_TRIES):
        _run_edit_mode_op(context, group, lambda a=angle, m=margin: bpy.ops.uv.smart_project(
            angle_limit=math.radians(a), island_margin=min(m, 1.0), scale_to_bounds=False))
        # Only whether a gap is under the padding matters: pairs further apart are not measured.
        gap = narrowest_gap(np.concatenate([_tri_uvs(ob) for ob in group]), resolution,
                            within=padding + 1.0, budget=UNWRAP_BUDGET)
        if gap is None or not (0.0 < gap < padding - 0.05) or margin >= 1.0:
            break                            # held; touching; or too many triangles a texel to measure
        margin *= min(4.0, 1.05 * padding / gap)
    return gap


def _tri_uvs(ob) -> np.ndarray:
    """(T, 3, 2) float64 corner UVs of the object's PRTT map, clipped to [0, 1]."""
    me = ob.data
    me.calc_loop_triangles()
    loops = read(me.loop_triangles, "loops", 3, np.int32)
    uv = read(me.uv_layers[UV_MAP].uv, "vector", 2, expect=len(me.loops),
              what=f"{ob.name}: UV map {UV_MAP!r} (is the mesh in Edit Mode?)")
    return np.clip(uv.astype(np.float64)[loops], 0.0, 1.0)


def overlap_texels(ob, resolution: int) -> int:
    """Texels of the object's PRTT map covered by more than one UV island."""
    return overlap_count(_tri_uvs(ob), resolution, resolution)
