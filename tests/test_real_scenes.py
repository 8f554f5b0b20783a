"""Scenes we did not design for (issue 13): what renders, bakes; what has
nothing to bake is skipped with one line; instances get texels of their own
and the preview draws each with its own; the user's data is not changed."""
import json
import os

import numpy as np
import pytest

from tests import real_scenes as rs
from tests.blender_util import addon_bpy, uv_snapshot

pytestmark = pytest.mark.blender


def _settings(bpy, tmp_path, res=32, rays=16):
    st = bpy.context.scene.prtt
    st.output_dir, st.resolution, st.rays, st.bounces = str(tmp_path / "out"), res, rays, 0
    return st


def _floor_with_map(bpy, size=20.0):
    fl = rs.floor(bpy, size)
    fl.data.uv_layers.new(name="PRTT")          # a unit quad's default UVs fill [0, 1]
    return fl


def _by_name(exp):
    return {name: rec for name, rec in exp.objects.items()}


def test_instances_geometry_nodes_curves_text_and_faceless_all_bake(tmp_path):
    bpy = addon_bpy()
    _settings(bpy, tmp_path)
    _floor_with_map(bpy)
    src = rs.source_collection(bpy)                                   # excluded from the view layer
    outer = bpy.data.collections.new("Outer")
    bpy.context.scene.collection.children.link(outer)
    rs.collection_instance(bpy, "Inner", src, (0, 0, 0), outer)
    bpy.context.view_layer.layer_collection.children["Outer"].exclude = True
    rs.collection_instance(bpy, "A", src, (2, 0, 0))
    rs.collection_instance(bpy, "B", outer, (-2, 0, 0))               # nested: B -> Outer -> Inner -> Src
    lib = tmp_path / "lib.blend"
    rs.write_library(bpy, lib)
    rs.collection_instance(bpy, "L", rs.link_collection(bpy, lib, "LibStuff"), (0, 4, 0))
    rs.gn_instance_on_points(bpy, "Scatter", bpy.data.objects["SrcCube"], [(0, -4, 0), (2, -4, 0), (4, -4, 0)])
    gen = rs.gn_grid(bpy, location=(5, 5, 0.1))
    rs.faceless(bpy)
    rs.zero_area(bpy)
    rs.extruded_curve(bpy)
    rs.text(bpy)
    hidden_render = rs.add_object(bpy, "NotRendered", rs.cube_mesh(bpy, "nr"), location=(8, 8, 0))
    hidden_render.hide_render = True
    eye_hidden = rs.add_object(bpy, "EyeHidden", rs.cube_mesh(bpy, "eh"), location=(-8, 8, 0.5))
    eye_hidden.prtt.bake = False                                      # an occluder the viewport hides
    eye_hidden.hide_set(True)
    before = uv_snapshot(bpy)
    from prtt_addon.blender.scene.job import export_scene
    exp = export_scene(bpy.context, with_light=False)
    recs = _by_name(exp)
    # every instance has texels of its own: 2 of Src (A, B nested), 1 linked, 3 geometry-nodes
    assert {n for n, r in recs.items() if r["kind"] == "instance"} == {
        "A/SrcCube", "B/SrcCube", "L/LibStuffCube", "Scatter[0]", "Scatter[1]", "Scatter[2]"}
    for n in ("Floor", "Generated", "Ring", "Label"):
        assert recs[n]["kind"] == "object" and recs[n]["triangles"] > 0, n
    assert recs["Floor"]["uv"] == "map" and recs["Generated"]["uv"] == "generated"
    # tiles of one set never share a texel: distinct (column, row) per instance
    tiles = [tuple(recs[n]["tile"][2:4]) for n in ("A/SrcCube", "B/SrcCube")]
    assert recs["A/SrcCube"]["set"] == recs["B/SrcCube"]["set"] and len(set(tiles)) == 2
    sc = exp.scene
    for name in ("A/SrcCube", "B/SrcCube"):
        i = sc.object_names.index(name)
        uv = sc.uvs[sc.object_id == i]
        gx, gy, col, row, _ = recs[name]["tile"]
        assert (uv[..., 0] >= col / gx).all() and (uv[..., 0] <= (col + 1) / gx).all()
        assert (uv[..., 1] >= row / gy).all() and (uv[..., 1] <= (row + 1) / gy).all()
    # skipped with one line naming them; render-hidden objects are not in the scene at all
    lines = [w for w in exp.warnings if "nothing to bake" in w]
    assert len(lines) == 1 and "Edges" in lines[0] and "Flat (zero area)" in lines[0]
    assert "NotRendered" not in sc.object_names and "NotRendered" not in lines[0]
    # the viewport-hidden occluder still casts shadows (it renders)
    assert "EyeHidden" in sc.object_names and (sc.set_id[sc.object_id == sc.object_names.index("EyeHidden")] < 0).all()
    # bake them all; textures per set; the user's meshes and UV maps untouched
    from prtt_addon.blender.bake.run import bake_blocking
    out = bake_blocking(bpy.context)
    assert out.status == "done", out.message
    files = set(os.listdir(tmp_path / "out"))
    for s in exp.scene.set_names:
        assert f"{s}.transfer.exr" in files
    assert "generated_uvs.npz" in files
    after = uv_snapshot(bpy)
    assert after.keys() == before.keys()
    for name, (maps, _sel) in before.items():
        assert after[name][0].keys() == maps.keys(), name
        for m, (data, *_f) in maps.items():
            np.testing.assert_array_equal(after[name][0][m][0], data)
    assert len(gen.data.polygons) == 0 and "PRTT" not in bpy.data.objects["SrcCube"].data.uv_layers


def test_all_zero_area_and_faceless_scene_says_why(tmp_path):
    bpy = addon_bpy()
    _settings(bpy, tmp_path)
    rs.faceless(bpy)
    rs.zero_area(bpy)
    from prtt_addon.blender.bake.run import bake_blocking
    out = bake_blocking(bpy.context)
    assert out.status == "failed"
    assert "no object to bake" in out.message and "Flat (zero area)" in out.message and "Edges" in out.message


def _instances_under_roof(bpy, tmp_path):
    """Cube instances A (under a low roof) and B (open sky), an occluder-only
    roof, a camera looking at both from the front."""
    st = _settings(bpy, tmp_path, res=32, rays=64)
    src = rs.source_collection(bpy)
    rs.collection_instance(bpy, "A", src, (-2, 0, 0))
    rs.collection_instance(bpy, "B", src, (2, 0, 0))
    # a canopy over A reaching far forward (above the camera's horizontal rays)
    roof = rs.add_object(bpy, "Roof", rs.cube_mesh(bpy, "roof"), location=(-2, -1.6, 1.35))
    roof.scale = (1.6, 4.8, 0.1)
    roof.prtt.bake = False
    cam = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
    bpy.context.scene.collection.objects.link(cam)
    cam.data.type, cam.data.ortho_scale = "ORTHO", 8.0
    cam.location, cam.rotation_euler = (0, -10, 0.5), (np.pi / 2, 0, 0)
    bpy.context.scene.camera = cam
    st.light_source, st.builtin_environment = "BUILTIN", "forest"
    return st


def test_each_instance_has_its_own_texels_in_bake_and_preview(tmp_path):
    bpy = addon_bpy()
    _instances_under_roof(bpy, tmp_path)
    from prtt_addon.blender.bake.run import bake_blocking
    out = bake_blocking(bpy.context)
    assert out.status == "done", out.message
    info = json.loads(bpy.context.scene.prtt.last_bake)
    a, b = info["objects"]["A/SrcCube"], info["objects"]["B/SrcCube"]
    assert a["set"] == b["set"]
    # the texture: the roofed instance's tile sees less sky (DC term) than the open one's
    from prtt_addon.core.io.exr_io import read_sh_exr
    T, _ = read_sh_exr(tmp_path / "out" / f"{a['set']}.transfer.exr")
    H, W = T.shape[:2]

    def tile_dc(rec):
        gx, gy, col, row, _ = rec["tile"]
        t = T[row * H // gy:(row + 1) * H // gy, col * W // gx:(col + 1) * W // gx, 0]
        return t[t != 0].mean()

    assert tile_dc(a) < 0.9 * tile_dc(b)
    # the preview draws each instance with its own texels: the roofed cube is darker
    from prtt_addon.blender.preview.offscreen import render_scene
    pixels, stats, status, _ = render_scene(bpy.context, mode="diffuse", size=(64, 32))
    assert sorted(stats.drawn) == ["A/SrcCube", "B/SrcCube"], (stats.drawn, status.messages)
    lum = pixels[..., :3].mean(axis=2)                     # row 0 = bottom; x -4..4 over 64 px
    face_a = lum[12:16, 12:20].mean()                      # cube fronts span x +-0.5 around -2 / +2
    face_b = lum[12:16, 44:52].mean()
    assert face_b > 0 and face_a < 0.85 * face_b, (face_a, face_b)


def test_more_kinds_metaball_surface_skinned_particles_linked_object(tmp_path):
    bpy = addon_bpy()
    _settings(bpy, tmp_path)
    bpy.ops.object.metaball_add(location=(0, 0, 3))
    bpy.ops.surface.primitive_nurbs_surface_sphere_add(location=(3, 0, 3))
    skinned, _rig = rs.skinned_cube(bpy)
    skinned.data.uv_layers.new(name="PRTT")
    emitter, dot = rs.particle_instances(bpy)
    emitter.data.uv_layers.new(name="PRTT")
    dot.data.uv_layers.new(name="PRTT")
    lib = tmp_path / "lib.blend"
    rs.write_library(bpy, lib)
    linked = rs.link_object(bpy, lib, "LibStuffCube")
    # a collection disabled in renders, and one excluded from the view layer: not in the bake
    for cname, how in (("NoRender", "hide_render"), ("Excluded", "exclude")):
        col = bpy.data.collections.new(cname)
        bpy.context.scene.collection.children.link(col)
        rs.add_object(bpy, f"{cname}Cube", rs.cube_mesh(bpy, cname), col, (9, 9, 0))
        if how == "hide_render":
            col.hide_render = True
        else:
            bpy.context.view_layer.layer_collection.children[cname].exclude = True
    from prtt_addon.blender.scene.job import export_scene
    exp = export_scene(bpy.context, with_light=False)
    recs = exp.objects
    kinds = {"Mball": "generated", "SurfSphere": "generated", "Skinned": "map", "Emitter": "map",
             "LibStuffCube": "generated"}
    for name, uv in kinds.items():
        assert recs[name]["uv"] == uv and recs[name]["triangles"] > 0, (name, recs.get(name))
    parts = [n for n in recs if n.startswith("Emitter/EmitterDot")]
    assert len(parts) == 4 and len({tuple(recs[n]["tile"][2:4]) for n in parts}) == 4
    assert linked.library is not None and "PRTT" not in linked.data.uv_layers
    assert not any(n.startswith(("NoRender", "Excluded")) for n in exp.scene.object_names)
    # the armature deforms the bake's copy: its top face is tilted like the render's
    i = exp.scene.object_names.index("Skinned")
    P = exp.scene.positions[exp.scene.object_id == i].reshape(-1, 3)
    assert np.ptp(P[:, 1]) > 1.2                          # a 1 m cube turned by 0.4 rad reaches further in y
    from prtt_addon.blender.bake.run import bake_blocking
    out = bake_blocking(bpy.context)
    assert out.status == "done", out.message


def test_preview_of_generated_uvs_fails_clearly_when_they_are_gone(tmp_path):
    """A render must not draw an object without its UVs: a clear error, no partial image."""
    bpy = addon_bpy()
    _instances_under_roof(bpy, tmp_path)
    from prtt_addon.blender.bake.run import bake_blocking
    assert bake_blocking(bpy.context).status == "done"
    from prtt_addon.blender.preview import drawlist as preview_scene
    from prtt_addon.blender.preview.offscreen import RenderError, render_scene
    for damage in (b"", b"not a zip"):
        (tmp_path / "out" / "generated_uvs.npz").write_bytes(damage)
        preview_scene.clear_caches()
        with pytest.raises(RenderError, match="generated_uvs.npz"):
            render_scene(bpy.context, mode="diffuse", size=(16, 8))


@pytest.mark.parametrize("method", ["SMART", "LIGHTMAP", "XATLAS"])
def test_unwrap_has_no_overlapping_texels(tmp_path, method):
    """Every unwrap method: zero overlapping texels at the chosen resolution on
    Suzanne and the room; an Array stack gets a layout per copy at export."""
    bpy = addon_bpy()
    _settings(bpy, tmp_path, res=1024)
    from prtt_addon.blender.scene.uv_maps import overlap_texels, unwrap_objects
    bpy.ops.mesh.primitive_monkey_add()
    suzanne = bpy.context.active_object
    stack = rs.add_object(bpy, "Stack", rs.cube_mesh(bpy, "stack"), location=(4, 0, 0.5))
    stack.modifiers.new("arr", "ARRAY").count = 4
    got = unwrap_objects(bpy.context, [suzanne, stack], method=method, resolution=1024, padding=4, dilate=3)
    assert got == {"Suzanne": 0, "Stack": 0}
    assert overlap_texels(suzanne, 1024) == 0
    from prtt_addon.blender.scene.job import export_scene
    exp = export_scene(bpy.context, with_light=False)
    assert exp.objects["Stack"]["uv"] == "generated" and exp.objects["Suzanne"]["uv"] == "map"
    from prtt_addon.core.texels.raster import rasterize
    sc = exp.scene
    for name in ("Stack", "Suzanne"):
        uv = sc.uvs[sc.object_id == sc.object_names.index(name)]
        assert rasterize(uv, 1024, 1024).overlap_texels == 0, name
    assert any("copy faces onto the same PRTT UVs" in w for w in exp.warnings)


def test_unwrap_room_has_no_overlapping_texels(tmp_path):
    bpy = addon_bpy()
    _settings(bpy, tmp_path, res=1024)
    from prtt_addon.dev.bench.scene_build import mesh_object
    from prtt_addon.dev.bench.scene_library import room_objects
    objects = [mesh_object(name, mesh) for name, mesh in room_objects()]
    from prtt_addon.blender.scene.uv_maps import unwrap_objects
    for method in ("SMART", "LIGHTMAP", "XATLAS"):
        got = unwrap_objects(bpy.context, objects, method=method, resolution=1024, padding=4, dilate=3, atlas=True)
        assert set(got.values()) == {0}, (method, got)


def test_preview_of_a_bake_with_more_bands_than_it_draws_says_so(tmp_path):
    bpy = addon_bpy()
    st = _instances_under_roof(bpy, tmp_path)
    st.bands, st.rays = 9, 16
    from prtt_addon.blender.bake.run import bake_blocking
    assert bake_blocking(bpy.context).status == "done"
    from prtt_addon.blender.preview.offscreen import RenderError, render_scene
    with pytest.raises(RenderError, match="this bake has 9 SH bands; the preview draws up to 8"):
        render_scene(bpy.context, mode="diffuse", size=(16, 8))
