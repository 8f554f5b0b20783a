"""What a scene shows: every object and instance with faces, its identity and visibility.

The bake (scene/job.py) and the preview (preview/drawlist.py) walk the evaluated
scene the same way, through :func:`scene_geometry`, so that the n-th instance a
bake gave texels to is the one the preview draws with them.

* Real objects: each evaluated object of a geometry type (mesh, curve, text,
  surface, metaball), modifiers and geometry nodes applied.
* Instances (``DepsgraphObjectInstance.is_instance``): collection instances,
  nested ones, those of linked libraries, and geometry-nodes instances (Instance
  on Points). Each has its own identity ``instance:<instancer>:<persistent id>:<source>``;
  the persistent id is stable across evaluations of the same scene.
* A curve or text object's own mesh comes out of the depsgraph twice, as the
  object and as an instance of itself; the instance copy is dropped.

Visibility follows Blender's *render* visibility: ``hide_render`` of the object
(and of the instancer), collections disabled in renders, collections excluded
from the view layer (the depsgraph leaves those out). Objects hidden only in the
viewport (eye icon, monitor icon) still render, so the bake includes them
(``include_viewport_hidden``); the preview, which draws the viewport, does not.
Geometry is evaluated as the viewport shows it (modifier viewport levels), so
the preview's meshes match the bake's triangle for triangle.
"""
from __future__ import annotations

import dataclasses

import numpy as np

#: Object types whose evaluated data can hold faces.
GEOMETRY_TYPES = {"MESH", "CURVE", "SURFACE", "META", "FONT"}
#: Types a user may expect to bake that can be faceless; reported when skipped.
REPORTED_TYPES = GEOMETRY_TYPES | {"EMPTY", "POINTCLOUD", "CURVES"}
#: Unused levels of a DepsgraphObjectInstance.persistent_id.
_UNUSED_ID = 2 ** 31 - 1


@dataclasses.dataclass
class Found:
    """One thing with geometry. ``evaluated`` is valid only while the
    iteration that produced it is on its current item (depsgraph instances are
    temporary)."""

    key: str                 # stable identity (see module doc)
    kind: str                # "object" or "instance"
    owner: object            # original Object whose PRTT settings apply (instancer for instances)
    source: object | None    # original Object the instance's geometry comes from (None: generated)
    source_name: str
    evaluated: object        # evaluated Object to call to_mesh() on
    matrix: np.ndarray       # (4, 4) float64 object -> world
    persistent_id: tuple = ()


def render_enabled(scene, view_layer) -> set:
    """Names of the view layer's objects that a render shows: the object's
    ``hide_render`` is off and at least one collection holding it is neither
    excluded from the view layer nor disabled in renders (itself or a parent)."""
    enabled: set = set()

    def walk(layer_coll, disabled):
        coll = layer_coll.collection
        off = disabled or layer_coll.exclude or coll.hide_render
        if not off:
            for ob in coll.objects:
                if not ob.hide_render:
                    enabled.add(ob.name)
        for child in layer_coll.children:
            walk(child, off)

    walk(view_layer.layer_collection, False)
    return enabled


def instance_key(parent_name: str, persistent_id, source_name: str) -> str:
    pid = ",".join(str(int(v)) for v in persistent_id if int(v) != _UNUSED_ID)
    return f"instance:{parent_name}:{pid}:{source_name}"


def scene_geometry(depsgraph, scene, view_layer, *, include_viewport_hidden: bool = False,
                   visible=None):
    """Yield a :class:`Found` for each render-visible object or instance of a
    geometry type, in depsgraph order.

    visible(owner) -> bool: an extra filter on the owning object (the preview
    passes ``Object.visible_get``). include_viewport_hidden: also yield the
    view layer's render-enabled objects the viewport hides (evaluated on
    their own; their instances are not expanded).
    """
    enabled = render_enabled(scene, view_layer)
    seen = set()
    for inst in depsgraph.object_instances:
        ob = inst.object
        if ob.type not in GEOMETRY_TYPES:
            continue
        orig = ob.original
        if not inst.is_instance:
            if orig.name not in enabled or (visible is not None and not visible(orig)):
                continue
            seen.add(orig.name)
            yield Found(f"object:{orig.name}", "object", orig, orig, orig.name, ob,
                        np.array(inst.matrix_world, dtype=np.float64))
            continue
        parent = inst.parent.original if inst.parent is not None else None
        if parent is None or parent.name not in enabled or (visible is not None and not visible(parent)):
            continue
        pid = tuple(int(v) for v in inst.persistent_id)
        if orig == parent and parent.type != "MESH" and len(pid) > 1 and pid[1] == _UNUSED_ID:
            continue              # a curve/text object's own mesh, already yielded as the object
        # Geometry-nodes instances report the instancer as their original.
        source = None if orig == parent else orig
        if source is not None and source.hide_render:
            continue
        yield Found(instance_key(parent.name, pid, orig.name), "instance", parent, source, orig.name, ob,
                    np.array(inst.matrix_world, dtype=np.float64), pid)
    if not include_viewport_hidden:
        return
    for orig in view_layer.objects:
        if orig.type in GEOMETRY_TYPES and orig.name in enabled and orig.name not in seen:
            ob = orig.evaluated_get(depsgraph)
            yield Found(f"object:{orig.name}", "object", orig, orig, orig.name, ob,
                        np.array(ob.matrix_world, dtype=np.float64))


def reported_without_faces(scene, view_layer, with_faces: set) -> list:
    """Render-enabled objects of REPORTED_TYPES that gave no faces (names), for
    the one "nothing to bake" warning. Empties that instance something and
    objects whose instances have faces are not listed."""
    enabled = render_enabled(scene, view_layer)
    out = []
    for ob in view_layer.objects:
        if ob.name not in enabled or ob.type not in REPORTED_TYPES or ob.name in with_faces:
            continue
        if ob.type == "EMPTY" and ob.instance_type != "NONE":
            continue
        if not ob.prtt.bake:
            continue
        out.append(ob.name)
    return sorted(out)


def rendered_lamps(scene, view_layer=None) -> list:
    """Light objects that light the render: in the view layer, not disabled in
    renders, with power."""
    layer = view_layer if view_layer is not None else scene.view_layers[0]
    return [ob for ob in layer.objects
            if ob.type == "LIGHT" and not ob.hide_render and getattr(ob.data, "energy", 0.0) > 0]
