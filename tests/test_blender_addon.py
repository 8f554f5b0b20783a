"""The add-on in real Blender (the bpy module): unwrap, export, bake, cancel, bad input."""
import json
import os

import numpy as np
import pytest

from tests.blender_util import addon_bpy, select_only, uv_snapshot

pytestmark = pytest.mark.blender


def plane_and_monkey(bpy, tmp_path, res=32, rays=32):
    bpy.ops.mesh.primitive_plane_add(size=4)
    plane = bpy.context.active_object
    bpy.ops.mesh.primitive_monkey_add(location=(0, 0, 1))
    monkey = bpy.context.active_object
    bpy.context.scene.world = bpy.data.worlds.new("W")
    st = bpy.context.scene.prtt
    st.resolution, st.rays, st.output_dir, st.bounces, st.bounce_rays = res, rays, str(tmp_path / "out"), 0, 8
    return plane, monkey


@pytest.mark.parametrize("method", ["EXISTING", "SMART", "LIGHTMAP", "XATLAS"])
def test_unwrap_writes_only_the_prtt_map(tmp_path, method):
    bpy = addon_bpy()
    plane, monkey = plane_and_monkey(bpy, tmp_path)
    second = monkey.data.uv_layers.new(name="Second")
    # Every face of "Second" on the same square: a layout that overlaps everywhere.
    me = monkey.data
    corners = np.array([[0.2, 0.2], [0.8, 0.2], [0.8, 0.8], [0.2, 0.8]], np.float32)
    start = np.empty(len(me.polygons), np.int32)
    me.polygons.foreach_get("loop_start", start)
    local = np.arange(len(me.loops)) - np.repeat(start, np.diff(np.r_[start, len(me.loops)]))
    second.uv.foreach_set("vector", corners[local % 4].ravel())
    monkey.data.uv_layers.active = second
    before = uv_snapshot(bpy)
    select_only(bpy, [plane, monkey])
    bpy.context.scene.prtt.unwrap_method = method
    bpy.context.scene.prtt.existing_uv_map = ""
    bpy.context.scene.prtt.resolution = 256
    assert bpy.ops.prtt.unwrap() == {"FINISHED"}
    after = uv_snapshot(bpy)
    for name, (maps, sel) in before.items():
        a_maps, a_sel = after[name]
        assert set(a_maps) == set(maps) | {"PRTT"}
        for m, (data, render, active) in maps.items():
            np.testing.assert_array_equal(a_maps[m][0], data)        # other maps untouched
            assert a_maps[m][1:] == (render, active)                 # render/active flags too
        np.testing.assert_array_equal(a_sel, sel)                     # mesh selection too
        uv = a_maps["PRTT"][0]
        assert uv.min() >= -1e-6 and uv.max() <= 1 + 1e-6
    from prtt_addon.blender.scene.uv_maps import overlap_texels
    # Non-planar quads can fold over in UV space: a few texels at most (reported).
    assert overlap_texels(monkey, 256) <= 64 and overlap_texels(plane, 256) == 0
    if method == "EXISTING":
        # copying the overlapping "Second" map: the operator warns, with texel counts
        bpy.context.scene.prtt.existing_uv_map = "Second"
        select_only(bpy, [monkey])
        assert bpy.ops.prtt.unwrap() == {"FINISHED"}
        assert overlap_texels(monkey, 64) > 1000


@pytest.mark.parametrize("method", ["SMART", "LIGHTMAP", "XATLAS"])
def test_unwrap_without_active_object_and_pydata_mesh(tmp_path, method):
    """Regression: selected objects but no active one, and a mesh made by
    from_pydata without edges (Blender 5.0.1 types its .select_edge INT32_2D,
    where edges.foreach_set("select") crashes). Unwrap must work and restore
    the selection it can."""
    bpy = addon_bpy()
    me = bpy.data.meshes.new("pydata")
    me.from_pydata([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0.5)], [], [(0, 1, 2), (0, 2, 3), (1, 4, 2)])
    ob = bpy.data.objects.new("pydata", me)
    bpy.context.scene.collection.objects.link(ob)
    bpy.ops.mesh.primitive_plane_add(location=(0, 0, -1))
    plane = bpy.context.object
    plane.data.polygons[0].select = False
    bpy.context.view_layer.update()
    for o in bpy.context.view_layer.objects:
        o.select_set(True)
    bpy.context.view_layer.objects.active = None
    before = uv_snapshot(bpy)
    st = bpy.context.scene.prtt
    st.unwrap_method, st.resolution = method, 64
    assert bpy.ops.prtt.unwrap() == {"FINISHED"}
    assert bpy.context.view_layer.objects.active is None
    assert all(o.select_get() for o in bpy.context.view_layer.objects)
    after = uv_snapshot(bpy)
    for name in ("pydata", "Plane"):
        assert "PRTT" in after[name][0]
        np.testing.assert_array_equal(after[name][1], before[name][1])
    uv = after["pydata"][0]["PRTT"][0]
    assert np.isfinite(uv).all() and uv.min() >= 0 and uv.max() <= 1


def test_bake_through_the_worker_matches_core_bake(tmp_path):
    """The operator's textures equal a core bake of the exported arrays."""
    bpy = addon_bpy()
    plane, monkey = plane_and_monkey(bpy, tmp_path)
    select_only(bpy, [plane, monkey])
    bpy.context.scene.prtt.unwrap_method = "SMART"
    bpy.ops.prtt.unwrap()
    assert bpy.ops.prtt.bake_transfer() == {"FINISHED"}
    out = tmp_path / "out"
    man = json.loads((out / "manifest.json").read_text())
    assert sorted(man["files"]) == ["Plane.transfer.exr", "Suzanne.transfer.exr"]
    assert not os.path.exists(out / ".prtt-job.npz")
    from prtt_addon.blender.bake.run import bake_settings
    from prtt_addon.blender.scene.job import export_scene
    from prtt_addon.core.bake.pipeline.runner import bake_scene
    from prtt_addon.core.io.exr_io import read_sh_exr
    exp = export_scene(bpy.context, with_light=False)
    bake_scene(exp.scene, tmp_path / "core", bake_settings(bpy.context.scene))
    for f in man["files"]:
        a, _ = read_sh_exr(out / f)
        b, _ = read_sh_exr(tmp_path / "core" / f)
        np.testing.assert_array_equal(a, b)
    info = json.loads(bpy.context.scene.prtt.last_bake)
    assert info["set_objects"] == {"Plane": ["Plane"], "Suzanne": ["Suzanne"]}
    assert "PRTT AO Plane" in bpy.data.images
    # unchanged inputs: skipped, and said so
    from prtt_addon.blender.bake.run import bake_blocking
    assert bake_blocking(bpy.context).status == "skipped"


def test_export_modifiers_transforms_instances(tmp_path):
    bpy = addon_bpy()
    bpy.ops.mesh.primitive_cube_add(location=(1, 2, 3), rotation=(0.3, 0.2, 0.1), scale=(1, 2, 0.5))
    cube = bpy.context.active_object
    cube.modifiers.new("arr", "ARRAY").count = 3
    cube.modifiers.new("sub", "SUBSURF").levels = 1
    col = bpy.data.collections.new("Inst")
    bpy.context.scene.collection.children.link(col)
    bpy.ops.mesh.primitive_ico_sphere_add()
    ico = bpy.context.active_object
    for c in list(ico.users_collection):
        c.objects.unlink(ico)
    col.objects.link(ico)
    bpy.context.view_layer.layer_collection.children["Inst"].exclude = True
    inst = bpy.data.objects.new("inst", None)
    inst.instance_type, inst.instance_collection = "COLLECTION", col
    inst.location = (5, 0, 0)
    bpy.context.scene.collection.objects.link(inst)
    bpy.ops.object.camera_add()
    bpy.ops.object.light_add(type="POINT")
    select_only(bpy, [cube])
    bpy.context.scene.prtt.unwrap_method = "XATLAS"
    bpy.ops.prtt.unwrap()
    from prtt_addon.blender.scene.job import export_scene
    exp = export_scene(bpy.context, with_light=False)
    sc = exp.scene
    dg = bpy.context.evaluated_depsgraph_get()
    ev = cube.evaluated_get(dg).to_mesh()
    ev.calc_loop_triangles()
    n_cube = len(ev.loop_triangles)
    cube.evaluated_get(dg).to_mesh_clear()
    assert (sc.set_id == 0).sum() == n_cube and sc.set_names == ["Cube", "Icosphere_instances"]
    # the instanced icosphere gets texels of its own (UVs generated: its mesh has no PRTT map)
    ins = sc.set_id == 1
    assert ins.sum() == 80 and not (sc.set_id < 0).any()
    np.testing.assert_allclose(sc.positions[ins].reshape(-1, 3).mean(0), [5, 0, 0], atol=1e-6)
    assert exp.objects["inst/Icosphere"]["uv"] == "generated"
    assert "PRTT" not in ico.data.uv_layers                  # the user's mesh is untouched
    # world-space bounds of the cube part: Blender's own matrix_world @ vertex (mathutils)
    ev_ob = cube.evaluated_get(dg)
    ev = ev_ob.to_mesh()
    world = np.array([tuple(ev_ob.matrix_world @ v.co) for v in ev.vertices])
    ev_ob.to_mesh_clear()
    P = sc.positions[sc.set_id == 0].reshape(-1, 3)
    np.testing.assert_allclose(P.min(0), world.min(0), atol=1e-5)
    np.testing.assert_allclose(P.max(0), world.max(0), atol=1e-5)
    # split normals are unit and point outward (away from the cube's centre)
    n = sc.normals[sc.set_id == 0].reshape(-1, 3)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, atol=1e-5)


def test_normal_mapped_floor(tmp_path):
    bpy = addon_bpy()
    bpy.ops.mesh.primitive_plane_add(size=2)
    floor = bpy.context.active_object
    img = bpy.data.images.new("nm", 8, 8, float_buffer=True)
    img.colorspace_settings.name = "Non-Color"
    px = np.zeros((8, 8, 4), np.float32)
    px[..., :3] = (np.array([0.6, 0.0, 0.8]) + 1) / 2
    px[..., 3] = 1
    img.pixels.foreach_set(px.ravel())
    img.pack()
    mat = bpy.data.materials.new("Bumpy")
    if bpy.app.version < (5, 0, 0):          # always nodes from 5.0 (use_nodes deprecated)
        mat.use_nodes = True
    nt = mat.node_tree
    bsdf = nt.nodes["Principled BSDF"]
    tex = nt.nodes.new("ShaderNodeTexImage")
    tex.image = img
    nmap = nt.nodes.new("ShaderNodeNormalMap")
    nt.links.new(tex.outputs["Color"], nmap.inputs["Color"])
    nt.links.new(nmap.outputs["Normal"], bsdf.inputs["Normal"])
    floor.data.materials.append(mat)
    select_only(bpy, [floor])
    bpy.context.scene.prtt.unwrap_method = "SMART"
    bpy.ops.prtt.unwrap()
    from prtt_addon.blender.scene.job import export_scene
    from prtt_addon.core.texels.gbuffer import build_gbuffer
    exp = export_scene(bpy.context, with_light=False)
    sc = exp.scene
    assert len(sc.normal_maps) == 1 and (sc.nm_index == 0).all()
    gb = build_gbuffer(sc, 0)
    # the default plane's UVs run along +X: the map tilts normals towards +X
    np.testing.assert_allclose(gb.normal.mean(0), [0.6, 0, 0.8], atol=0.02)
    sc.normal_maps.clear()
    st = bpy.context.scene.prtt
    st.normal_maps = False
    assert len(export_scene(bpy.context, with_light=False).scene.normal_maps) == 0


def test_missing_normal_map_image_warns_and_bakes(tmp_path):
    bpy = addon_bpy()
    bpy.ops.mesh.primitive_plane_add(size=2)
    floor = bpy.context.active_object
    mat = bpy.data.materials.new("Gone")
    if bpy.app.version < (5, 0, 0):          # always nodes from 5.0 (use_nodes deprecated)
        mat.use_nodes = True
    nt = mat.node_tree
    tex = nt.nodes.new("ShaderNodeTexImage")
    tex.image = bpy.data.images.load(str(tmp_path / "nope.png"), check_existing=False) \
        if os.path.exists(tmp_path / "nope.png") else bpy.data.images.new("nope", 4, 4)
    tex.image.source = "FILE"
    tex.image.filepath = str(tmp_path / "does-not-exist.png")
    nmap = nt.nodes.new("ShaderNodeNormalMap")
    nt.links.new(tex.outputs["Color"], nmap.inputs["Color"])
    nt.links.new(nmap.outputs["Normal"], nt.nodes["Principled BSDF"].inputs["Normal"])
    floor.data.materials.append(mat)
    select_only(bpy, [floor])
    bpy.ops.prtt.unwrap()
    st = bpy.context.scene.prtt
    st.resolution, st.rays, st.output_dir, st.bounces = 16, 16, str(tmp_path / "out"), 0
    from prtt_addon.blender.scene.job import export_scene
    exp = export_scene(bpy.context, with_light=False)
    assert any("normal map image" in w and "baking without it" in w for w in exp.warnings)
    assert bpy.ops.prtt.bake_transfer() == {"FINISHED"}


def test_auto_tuning_sizes_object_sets_by_texel_density(tmp_path):
    """Tuning Auto (the default) with Texel Density 0: each object's set from its surface area
    at AUTO_TEXEL_DENSITY (a power of two, up to the scene resolution); an
    object's Resolution Override still wins; Fixed keeps the scene resolution."""
    bpy = addon_bpy()
    from prtt_addon.blender.scene.job import AUTO_TEXEL_DENSITY, export_scene
    bpy.ops.mesh.primitive_plane_add(size=6.0)                  # 36 m²
    floor = bpy.context.active_object
    bpy.ops.mesh.primitive_cube_add(size=0.2, location=(0, 0, 1))  # 0.24 m²
    small = bpy.context.active_object
    bpy.ops.mesh.primitive_cube_add(size=0.2, location=(1, 0, 1))
    pinned = bpy.context.active_object
    pinned.prtt.resolution = 512
    select_only(bpy, [floor, small, pinned])
    bpy.context.scene.prtt.unwrap_method = "XATLAS"
    bpy.ops.prtt.unwrap()
    st = bpy.context.scene.prtt
    st.resolution, st.texel_density, st.texture_sets, st.bounces = 1024, 0.0, "OBJECT", 0
    st.output_dir = str(tmp_path / "out")
    assert st.tuning == "AUTO"                                   # the default
    st.tuning = "FIXED"

    def sizes():
        sc = export_scene(bpy.context, with_light=False).scene
        return {n: int(r[0]) for n, r in zip(sc.set_names, sc.set_resolution)}

    assert sizes() == {floor.name: 1024, small.name: 1024, pinned.name: 512}
    st.tuning = "AUTO"
    want_small = 1 << int(np.ceil(np.log2(AUTO_TEXEL_DENSITY * 0.24 ** 0.5)))
    got = sizes()
    assert got == {floor.name: 1024, small.name: want_small, pinned.name: 512}, got
    assert want_small == 64
    st.texel_density = 1024.0                                    # an explicit density wins over auto's
    assert sizes()[small.name] == 512
