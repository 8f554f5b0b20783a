"""One mesh assembly path (core.model.assembly): meshgen's and the Blender export's."""
import numpy as np
import pytest

from prtt_addon.core.model.assembly import MeshPart, assemble_parts
from prtt_addon.core.model.scene import NormalMap
from prtt_addon.core.texels.unwrap import unwrap
from prtt_addon.dev.bench import meshgen as mg


def _meshes():
    """A box (with its own non-overlapping UVs) and a flat-shaded icosphere
    moved away from the origin (UVs from xatlas), as meshgen meshes."""
    box = mg.box((1.0, 2.0, 0.5), (0.5, 0.0, 0.25))
    box.uvs = mg.box_face_uvs(box)
    ball = mg.icosphere(0.5, 1, smooth=False).transformed(translate=(2.0, 0.0, 1.0))
    ball.uvs = unwrap([(ball.vertices, ball.faces)], 64, padding=2)[0]
    return [("Box", box), ("Ball", ball)]


def test_meshgen_assemble_concatenates_in_order():
    objects = _meshes()
    sc = mg.assemble(objects, resolution=64, keep_uvs=True, resolutions={"Ball": 32})
    (_, box), (_, ball) = objects
    nb, ni = box.n_faces, ball.n_faces
    np.testing.assert_array_equal(sc.positions, np.concatenate([box.vertices[box.faces],
                                                                ball.vertices[ball.faces]]))
    np.testing.assert_array_equal(sc.uvs, np.concatenate([box.uvs, ball.uvs]))
    np.testing.assert_array_equal(sc.set_id, [0] * nb + [1] * ni)
    np.testing.assert_array_equal(sc.object_id, [0] * nb + [1] * ni)
    assert sc.set_names == ["Box", "Ball"] and sc.object_names == ["Box", "Ball"]
    np.testing.assert_array_equal(sc.set_resolution, [[64, 64], [32, 32]])
    # flat shading: every corner carries its face's unit normal
    P = sc.positions
    fn = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    np.testing.assert_allclose(sc.normals, np.repeat(fn[:, None], 3, axis=1), atol=1e-6)
    assert sc.material_id is None and sc.mat_uvs is None and sc.nm_index is None


def test_parts_leave_out_what_the_format_defaults():
    """An occluder without UVs, a normal-mapped part and a plain one: what a
    part leaves out takes the format's defaults, per triangle."""
    (_, box), (_, ball) = _meshes()
    T0, T1 = box.n_faces, ball.n_faces
    nm_index = np.where(np.arange(T0) % 2 == 0, 0, -1).astype(np.int32)
    tangents = np.zeros((T0, 3, 4), np.float32)
    tangents[..., 1] = 1.0
    tangents[..., 3] = -1.0
    parts = [MeshPart("Box", box.corner_positions(), box.corner_normals(), box.uvs, 0,
                      material=np.full(T0, 1, np.int32), mat_uvs=np.full((T0, 3, 2), 0.25),
                      nm_index=nm_index, nm_uvs=np.full((T0, 3, 2), 0.5), tangents=tangents),
             MeshPart("Occluder", ball.corner_positions(), ball.corner_normals())]
    nm = NormalMap(np.full((4, 4, 3), 0.5, np.float32))
    sc = assemble_parts(parts, ["Box"], [[16, 16]], materials=[{}, {}], normal_maps=[nm])
    box_t, occ = slice(0, T0), slice(T0, T0 + T1)
    np.testing.assert_array_equal(sc.set_id[occ], -1)
    np.testing.assert_array_equal(sc.uvs[occ], 0.0)
    np.testing.assert_array_equal(sc.object_id, [0] * T0 + [1] * T1)
    np.testing.assert_array_equal(sc.material_id, [1] * T0 + [0] * T1)
    np.testing.assert_array_equal(sc.mat_uvs[box_t], 0.25)
    np.testing.assert_array_equal(sc.mat_uvs[occ], 0.0)
    np.testing.assert_array_equal(sc.nm_index, np.concatenate([nm_index, np.full(T1, -1)]))
    np.testing.assert_array_equal(sc.nm_uvs[box_t], 0.5)
    np.testing.assert_array_equal(sc.nm_uvs[occ], 0.0)
    np.testing.assert_array_equal(sc.tangents[box_t], tangents)
    np.testing.assert_array_equal(sc.tangents[occ], np.broadcast_to([1, 0, 0, 1], (T1, 3, 4)))
    # no normal maps: no per-triangle normal-map arrays at all
    plain = assemble_parts(parts, ["Box"], [[16, 16]], materials=[{}, {}])
    assert plain.nm_index is None and plain.nm_uvs is None and plain.tangents is None


@pytest.mark.blender
def test_blender_export_and_meshgen_give_the_same_scene(tmp_path):
    """The same two meshes, as Blender objects with those UVs in their PRTT map
    (exported from the evaluated depsgraph) and as meshgen meshes: one scene."""
    from tests.blender_util import addon_bpy
    bpy = addon_bpy()
    from prtt_addon.blender.scene.job import export_scene
    objects = _meshes()
    for name, m in objects:
        me = bpy.data.meshes.new(name)
        me.from_pydata(m.vertices.tolist(), [], m.faces.tolist())
        me.update()
        layer = me.uv_layers.new(name="PRTT")
        layer.uv.foreach_set("vector", m.uvs.astype(np.float32).ravel())   # a triangle's loops in corner order
        bpy.context.scene.collection.objects.link(bpy.data.objects.new(name, me))
    bpy.data.objects["Ball"].prtt.resolution = 32
    st = bpy.context.scene.prtt
    st.resolution, st.texel_density, st.texture_sets, st.bounces = 64, 0.0, "OBJECT", 0
    st.output_dir = str(tmp_path / "out")
    got = export_scene(bpy.context, with_light=False).scene
    want = mg.assemble(objects, resolution=64, keep_uvs=True, resolutions={"Ball": 32})
    assert got.object_names == want.object_names and got.set_names == want.set_names
    np.testing.assert_array_equal(got.set_resolution, want.set_resolution)
    np.testing.assert_array_equal(got.set_id, want.set_id)
    np.testing.assert_array_equal(got.object_id, want.object_id)
    # Blender stores float32 positions and UVs
    np.testing.assert_allclose(got.positions, want.positions, atol=1e-6)
    np.testing.assert_allclose(got.normals, want.normals, atol=1e-6)
    np.testing.assert_allclose(got.uvs, want.uvs, atol=1e-7)
    # what only the export has: the default material everywhere, no normal maps
    assert (got.material_id == 0).all() and got.nm_index is None
