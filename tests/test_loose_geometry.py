"""Meshes with loose vertices and edges beside their faces, and .blend files
saved in Edit Mode (issue 32): `bake --unwrap SMART|LIGHTMAP`, the panel's
Unwrap, `render` afterwards and a second bake, each on a scene built with bpy.

A .blend saved in Edit Mode opens in Edit Mode, headless too; there a mesh's
UV layers read as empty, which is what crashed `bake --unwrap SMART`.
"""
import os

import numpy as np
import pytest

from tests import real_scenes as rs
from tests.blender_util import addon_bpy
from tests.test_headless_chain import digest, run

pytestmark = pytest.mark.blender

BAKE = ["--resolution", "32", "--rays", "16", "--bounces", "0"]
#: name -> (loose vertices, loose edges) added beside a cube's six faces
LOOSE = {"LooseVerts": (3, 0), "LooseEdges": (0, 2), "LooseBoth": (2, 1)}


def cube_with_loose(bpy, name, verts, edges):
    """A cube with ``verts`` isolated vertices and a chain of ``edges`` loose
    edges (edges + 1 more vertices) beside its faces."""
    import bmesh
    me = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=1.0)
    for i in range(verts):
        bm.verts.new((2.0 + i, 0.0, 0.0))
    chain = [bm.verts.new((0.0, 2.0 + i, 0.5 * i)) for i in range(edges + 1)] if edges else []
    for a, b in zip(chain, chain[1:]):
        bm.edges.new((a, b))
    bm.to_mesh(me)
    bm.free()
    me.uv_layers.new(name="UVMap")
    return me


def build_scene(bpy, *, edit_mode: str | None):
    """Floor, three cubes with loose geometry, a camera, the built-in light;
    ``edit_mode``: the object left in Edit Mode (active) when saved."""
    rs.floor(bpy, 8.0)
    obs = {}
    for i, (name, (v, e)) in enumerate(LOOSE.items()):
        obs[name] = rs.add_object(bpy, name, cube_with_loose(bpy, name, v, e), location=(3.0 * (i - 1), 0, 0.5))
    rs.scene_camera(bpy, (0, -9, 5), (1.05, 0, 0))
    bpy.context.scene.prtt.light_source = "BUILTIN"
    if edit_mode:
        for o in bpy.context.view_layer.objects:
            o.select_set(o.name == edit_mode)
        bpy.context.view_layer.objects.active = obs[edit_mode]
        bpy.ops.object.mode_set(mode="EDIT")
    return obs


@pytest.fixture(scope="module")
def blends(tmp_path_factory):
    """Two saved .blend files: one in Object Mode, one with LooseBoth in Edit Mode."""
    tmp = tmp_path_factory.mktemp("loose")
    out = {}
    for mode in (None, "LooseBoth"):
        bpy = addon_bpy()
        build_scene(bpy, edit_mode=mode)
        path = tmp / f"{'edit' if mode else 'object'}.blend"
        bpy.ops.wm.save_as_mainfile(filepath=str(path))
        if mode:
            bpy.ops.object.mode_set(mode="OBJECT")
        out["edit" if mode else "object"] = path
    return out


def loose_line(text):
    lines = [ln for ln in text.splitlines() if "ignored loose vertices and edges" in ln]
    assert len(lines) == 1, text
    return lines[0]


@pytest.mark.parametrize("method", ["SMART", "LIGHTMAP"])
@pytest.mark.parametrize("mode", ["object", "edit"])
def test_bake_unwrap_render_bake_again(blends, tmp_path, method, mode):
    scene = tmp_path / "scene.blend"
    scene.write_bytes(blends[mode].read_bytes())
    r = run("bake", "scene.blend", "--out", "textures", "--unwrap", method, *BAKE, cwd=tmp_path)
    assert r.returncode == 0, r.stderr + r.stdout
    assert "Traceback" not in r.stderr
    line = loose_line(r.stdout + r.stderr)
    assert ("LooseVerts (3 loose vertices)" in line and "LooseEdges (2 loose edges)" in line
            and "LooseBoth (2 loose vertices and 1 loose edge)" in line), line
    names = sorted(os.listdir(tmp_path / "textures"))
    for name in LOOSE:
        assert f"{name}.transfer.exr" in names, names
    r = run("render", "scene.blend", "--out", "first.png", "--size", "64x48", cwd=tmp_path)
    assert r.returncode == 0, r.stderr + r.stdout
    textures = {n: digest(tmp_path / "textures" / n) for n in names}
    r = run("bake", "scene.blend", "--out", "textures", *BAKE, cwd=tmp_path)
    assert r.returncode == 0, r.stderr + r.stdout
    assert "unchanged" in r.stdout, r.stdout
    assert {n: digest(tmp_path / "textures" / n) for n in names} == textures
    r = run("render", "scene.blend", "--out", "second.png", "--size", "64x48", cwd=tmp_path)
    assert r.returncode == 0, r.stderr + r.stdout
    assert digest(tmp_path / "first.png") == digest(tmp_path / "second.png")


def _prtt_uvs(me):
    from prtt_addon.blender.rna_arrays import read
    return read(me.uv_layers["PRTT"].uv, "vector", 2, expect=len(me.loops))


@pytest.mark.parametrize("method", ["SMART", "LIGHTMAP", "XATLAS"])
def test_panel_unwrap_from_edit_mode_then_bake_and_render(tmp_path, method):
    """The panel's Unwrap with a mesh in Edit Mode: the map is written from
    the current edit mesh, the mode comes back, the loose vertices keep no
    UVs of their own (they have no loops), and the scene bakes and renders."""
    bpy = addon_bpy()
    obs = build_scene(bpy, edit_mode="LooseBoth")
    for o in bpy.context.view_layer.objects:
        o.select_set(o.type == "MESH")                  # the floor too
    bpy.context.scene.prtt.unwrap_method = method
    assert bpy.ops.prtt.unwrap() == {"FINISHED"}
    assert obs["LooseBoth"].mode == "EDIT"
    bpy.ops.object.mode_set(mode="OBJECT")
    for o in obs.values():
        uv = _prtt_uvs(o.data)
        assert len(uv) == len(o.data.loops) == 24
        assert np.all((uv >= 0) & (uv <= 1)) and np.ptp(uv[:, 0]) > 0.05, (o.name, uv)
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    bpy.ops.object.mode_set(mode="OBJECT")
    r = run("bake", "scene.blend", "--out", "textures", *BAKE, cwd=tmp_path)
    assert r.returncode == 0, r.stderr + r.stdout
    loose_line(r.stdout + r.stderr)
    r = run("render", "scene.blend", "--out", "p.png", "--size", "64x48", cwd=tmp_path)
    assert r.returncode == 0, r.stderr + r.stdout


def test_rna_arrays_size_from_the_data_read():
    """read/write size their buffers from the collection; a UV layer of a mesh
    in Edit Mode (empty there) is a clear error, and a write of the wrong
    length changes nothing."""
    from prtt_addon.blender.rna_arrays import RnaArrayError, read, write
    bpy = addon_bpy()
    obs = build_scene(bpy, edit_mode=None)
    me = obs["LooseBoth"].data
    assert read(me.vertices, "co", 3).shape == (8 + 2 + 2, 3)
    uv = read(me.uv_layers["UVMap"].uv, "vector", 2, expect=len(me.loops))
    assert uv.shape == (24, 2)
    with pytest.raises(RnaArrayError, match="UV map 'UVMap': 25 values for 24 elements"):
        write(me.uv_layers["UVMap"].uv, "vector", np.ones((25, 2)), 2, what="UV map 'UVMap'")
    assert np.array_equal(read(me.uv_layers["UVMap"].uv, "vector", 2), uv)
    bpy.context.view_layer.objects.active = obs["LooseBoth"]
    bpy.ops.object.mode_set(mode="EDIT")
    try:
        with pytest.raises(RnaArrayError, match="UV map 'UVMap': 0 elements where 24 were expected"):
            read(me.uv_layers["UVMap"].uv, "vector", 2, expect=len(me.loops), what="UV map 'UVMap'")
    finally:
        bpy.ops.object.mode_set(mode="OBJECT")
