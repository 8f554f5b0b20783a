"""Scenes users bring, built with bpy: instances, geometry nodes, curves, text,
faceless and zero-area meshes, linked libraries, hidden and excluded collections.

Each builder works on the current (empty) scene and returns the objects it made.
"""


def cube_mesh(bpy, name="cube", size=1.0):
    import bmesh  # importable only once bpy is
    me = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=size)
    bm.to_mesh(me)
    bm.free()
    return me


def add_object(bpy, name, data, collection=None, location=(0, 0, 0)):
    ob = bpy.data.objects.new(name, data)
    (collection or bpy.context.scene.collection).objects.link(ob)
    ob.location = location
    return ob


def floor(bpy, size=20.0, name="Floor"):
    me = bpy.data.meshes.new(name)
    h = size / 2
    me.from_pydata([(-h, -h, 0), (h, -h, 0), (h, h, 0), (-h, h, 0)], [], [(0, 1, 2, 3)])
    return add_object(bpy, name, me)


def floor_and_box(bpy, *, camera=True):
    """(floor, box): a 6 m floor and a 1 m box resting on it at the origin,
    lit by the built-in studio HDRI (light source BUILTIN), and a camera on
    them unless ``camera`` is False."""
    ground = floor(bpy, 6.0)
    box = add_object(bpy, "Box", cube_mesh(bpy, "box"), location=(0, 0, 0.5))
    if camera:
        scene_camera(bpy, (0, -7, 4), (1.05, 0, 0))
    bpy.context.scene.prtt.light_source = "BUILTIN"
    return ground, box


def scene_camera(bpy, location, rotation, name="Cam"):
    """A perspective camera at ``location`` turned by Euler ``rotation``, made the scene camera."""
    cam = bpy.data.objects.new(name, bpy.data.cameras.new(name))
    bpy.context.scene.collection.objects.link(cam)
    cam.location, cam.rotation_euler = location, rotation
    bpy.context.scene.camera = cam
    return cam


def source_collection(bpy, name="Src", exclude=True, objects=None):
    """A collection holding a cube (or ``objects``), excluded from the view layer."""
    col = bpy.data.collections.new(name)
    bpy.context.scene.collection.children.link(col)
    if objects is None:
        objects = [add_object(bpy, f"{name}Cube", cube_mesh(bpy, f"{name}_mesh"), col, (0, 0, 0.5))]
    else:
        for ob in objects:
            for c in list(ob.users_collection):
                c.objects.unlink(ob)
            col.objects.link(ob)
    if exclude:
        bpy.context.view_layer.layer_collection.children[name].exclude = True
    return col


def collection_instance(bpy, name, collection, location, parent_collection=None):
    e = bpy.data.objects.new(name, None)
    e.instance_type, e.instance_collection = "COLLECTION", collection
    e.location = location
    (parent_collection or bpy.context.scene.collection).objects.link(e)
    return e


def gn_instance_on_points(bpy, name, instance_object, points):
    """A mesh object whose geometry nodes put an instance of ``instance_object``
    on each of ``points`` (its own vertices)."""
    me = bpy.data.meshes.new(name)
    me.from_pydata(points, [], [])
    ob = add_object(bpy, name, me)
    ng = bpy.data.node_groups.new(name, "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gi, go = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    iop = ng.nodes.new("GeometryNodeInstanceOnPoints")
    info = ng.nodes.new("GeometryNodeObjectInfo")
    info.inputs["Object"].default_value = instance_object
    ng.links.new(gi.outputs[0], iop.inputs["Points"])
    ng.links.new(info.outputs["Geometry"], iop.inputs["Instance"])
    ng.links.new(iop.outputs["Instances"], go.inputs[0])
    ob.modifiers.new("GN", "NODES").node_group = ng
    return ob


def gn_grid(bpy, name="Generated", size=2.0, location=(0, 0, 0)):
    """An object with an empty mesh whose faces all come from a Grid node."""
    ob = add_object(bpy, name, bpy.data.meshes.new(name), location=location)
    ng = bpy.data.node_groups.new(name, "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    go, g = ng.nodes.new("NodeGroupOutput"), ng.nodes.new("GeometryNodeMeshGrid")
    g.inputs["Size X"].default_value = g.inputs["Size Y"].default_value = size
    g.inputs["Vertices X"].default_value = g.inputs["Vertices Y"].default_value = 4
    ng.links.new(g.outputs["Mesh"], go.inputs[0])
    ob.modifiers.new("GN", "NODES").node_group = ng
    return ob


def faceless(bpy, name="Edges", location=(3, 3, 0)):
    me = bpy.data.meshes.new(name)
    me.from_pydata([(0, 0, 0), (1, 0, 0), (1, 1, 0)], [(0, 1), (1, 2)], [])
    return add_object(bpy, name, me, location=location)


def zero_area(bpy, name="Flat", location=(-3, 3, 0)):
    """Faces whose corners are collinear: they show nothing."""
    me = bpy.data.meshes.new(name)
    me.from_pydata([(0, 0, 0), (1, 0, 0), (2, 0, 0), (3, 0, 0)], [], [(0, 1, 2), (1, 2, 3)])
    return add_object(bpy, name, me, location=location)


def extruded_curve(bpy, name="Ring", location=(-3, -3, 0.5)):
    cu = bpy.data.curves.new(name, "CURVE")
    cu.dimensions = "3D"
    sp = cu.splines.new("POLY")
    sp.points.add(3)
    for p, co in zip(sp.points, [(0, 0, 0, 1), (1, 0, 0, 1), (1, 1, 0, 1), (0, 1, 0, 1)]):
        p.co = co
    sp.use_cyclic_u = True
    cu.extrude = 0.3
    return add_object(bpy, name, cu, location=location)


def text(bpy, name="Label", body="PRTT", location=(3, -3, 0.2)):
    cu = bpy.data.curves.new(name, "FONT")
    cu.body = body
    cu.extrude = 0.1
    return add_object(bpy, name, cu, location=location)


def write_library(bpy, path, collection_name="LibStuff"):
    """Write a library .blend holding a collection with a cube, and return to
    an empty scene. Uses bpy.data.libraries.write (no file switch)."""
    col = bpy.data.collections.new(collection_name)
    ob = bpy.data.objects.new(f"{collection_name}Cube", cube_mesh(bpy, f"{collection_name}_mesh", 0.8))
    ob.location = (0, 0, 0.4)
    col.objects.link(ob)
    bpy.data.libraries.write(str(path), {col}, fake_user=True)
    bpy.data.collections.remove(col)
    bpy.data.objects.remove(ob)
    return collection_name


def link_collection(bpy, path, name):
    with bpy.data.libraries.load(str(path), link=True) as (src, dst):
        dst.collections = [name]
    return dst.collections[0]


def particle_instances(bpy, name="Emitter", count=4, location=(0, -5, 0)):
    """A plane emitting ``count`` object particles (small icospheres) at frame 1."""
    me = bpy.data.meshes.new(name)
    me.from_pydata([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], [], [(0, 1, 2, 3)])
    em = add_object(bpy, name, me, location=location)
    bpy.ops.mesh.primitive_ico_sphere_add(radius=0.15, location=(0, -30, 0))
    dot = bpy.context.active_object
    dot.name = f"{name}Dot"
    ps = em.modifiers.new("particles", "PARTICLE_SYSTEM").particle_system
    ps.settings.count, ps.settings.frame_end = count, 1
    ps.settings.render_type, ps.settings.instance_object = "OBJECT", dot
    return em, dot


def skinned_cube(bpy, name="Skinned", location=(-5, 0, 1)):
    """A cube deformed by an armature (the bone rotated)."""
    ob = add_object(bpy, name, cube_mesh(bpy, name), location=location)
    arm = bpy.data.objects.new(f"{name}Rig", bpy.data.armatures.new(f"{name}Rig"))
    bpy.context.scene.collection.objects.link(arm)
    arm.location = location
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")
    b = arm.data.edit_bones.new("bone")
    b.head, b.tail = (0, 0, -1), (0, 0, 1)
    bpy.ops.object.mode_set(mode="OBJECT")
    arm.pose.bones["bone"].rotation_mode = "XYZ"
    arm.pose.bones["bone"].rotation_euler = (0.4, 0, 0)
    vg = ob.vertex_groups.new(name="bone")
    vg.add(list(range(len(ob.data.vertices))), 1.0, "REPLACE")
    ob.modifiers.new("rig", "ARMATURE").object = arm
    return ob, arm


def link_object(bpy, path, name):
    """Link an object (not a collection) from a library into the scene."""
    with bpy.data.libraries.load(str(path), link=True) as (src, dst):
        dst.objects = [name]
    ob = dst.objects[0]
    bpy.context.scene.collection.objects.link(ob)
    return ob


def chain_scene(bpy, *, generated: bool = False):
    """test_headless_chain's scene in the current file: a floor and a cube
    without PRTT maps, cube instances from an excluded collection, a
    geometry-nodes grid, a faceless helper, a camera, Blender's studio light
    (the factory-empty file has no World); with ``generated``, also an
    extruded curve, a text and geometry-nodes instances of an unwrapped cube
    (UVs the bake generates)."""
    floor(bpy, 8.0)
    add_object(bpy, "Box", cube_mesh(bpy, "box"), location=(0, 0, 0.5))
    src = source_collection(bpy)
    collection_instance(bpy, "A", src, (2, 0, 0))
    collection_instance(bpy, "B", src, (-2, 0, 0))
    gn_grid(bpy, location=(0, 2.5, 0.05), size=1.5)
    faceless(bpy)                                          # a helper with edges only
    if generated:
        extruded_curve(bpy)
        text(bpy)
        dot = add_object(bpy, "Dot", cube_mesh(bpy, "dot", 0.3), location=(0, 0, -20))
        gn_instance_on_points(bpy, "Scatter", dot, [(3, 1, 0.2), (3, 2, 0.2), (-3, 1.5, 0.2)])
    scene_camera(bpy, (0, -9, 5), (1.05, 0, 0))
    bpy.context.scene.prtt.light_source = "BUILTIN"
