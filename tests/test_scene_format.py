"""The bpy-free scene/job format: round trip and validation with clear errors."""
import numpy as np
import pytest

from prtt_addon.core.io.jobfile import load_scene, save_scene
from prtt_addon.core.model.scene import Scene, SceneError, scene_hash
from tests.scenes_util import floor_and_box, floor_and_box_with_every_part


def test_round_trip_with_normal_maps_and_extra(tmp_path):
    sc = floor_and_box_with_every_part(res=16)
    save_scene(sc, tmp_path / "job.npz", extra={"settings": {"rays": 64}})
    back, extra = load_scene(tmp_path / "job.npz")
    assert extra == {"settings": {"rays": 64}}
    assert scene_hash(back) == scene_hash(sc)
    assert back.normal_maps[0].strength == pytest.approx(0.7, rel=1e-7)
    assert back.materials == sc.materials


def base_arrays():
    sc = floor_and_box(res=8)
    return dict(positions=sc.positions, normals=sc.normals, uvs=sc.uvs, set_id=sc.set_id,
                set_names=sc.set_names, set_resolution=sc.set_resolution)


@pytest.mark.parametrize("change, match", [
    (lambda a: a.update(positions=a["positions"][:0]), "no triangles"),
    (lambda a: a.update(positions=a["positions"][..., :2]), r"positions: expected shape \(T, 3, 3\)"),
    (lambda a: a["positions"].__setitem__((3, 1, 2), np.nan), "positions: triangle 3 has NaN/Inf"),
    (lambda a: a["normals"].__setitem__((5, 0, 0), np.inf), "normals: triangle 5 has NaN/Inf"),
    (lambda a: a["uvs"].__setitem__((2, 0, 0), 1.5), r"uvs: 1 triangles of set\(s\) box have UVs outside \[0, 1\]"),
    (lambda a: a.update(uvs=a["uvs"][:-1]), "uvs: has 13 triangles, positions has 14"),
    (lambda a: a["set_id"].__setitem__(0, 7), "set_id: triangle 0 refers to set 7"),
    (lambda a: a.update(set_names=["floor", "floor"]), "duplicate names"),
    (lambda a: a.update(set_names=["floor", "a/b"]), "not usable as a file name"),
    (lambda a: a.update(set_resolution=np.array([[8, 8], [0, 8]])), "asks for 0x8 texels"),
    (lambda a: a.update(set_resolution=np.array([[8, 8], [99999, 8]])), "each side must be 1..16384"),
    (lambda a: a.update(uvs=a["uvs"].astype(str)), "uvs: expected numbers"),
    (lambda a: a.update(set_id=a["set_id"].astype(np.float64)), "set_id: expected integers, got float64"),
    (lambda a: a.update(set_id=a["set_id"].astype(bool)), "set_id: expected integers, got bool"),
    (lambda a: a.update(set_id=a["set_id"].astype(np.int64) + (1 << 32)),
     "set_id: triangle 0 refers to set 4294967296"),                  # no silent wrap to 0
    (lambda a: a.update(set_resolution=np.array([[8, 8], [(1 << 32) + 8, 8]])), "asks for 4294967304x8 texels"),
    (lambda a: a.update(set_names=["floor", "b" * 300]),
     "is 300 characters .*set names become file names and may have at most 200 bytes"),
    (lambda a: a.update(set_names=["floor", "é" * 101]), r"\(202 bytes as UTF-8\)"),
    (lambda a: a.update(set_names=["floor", "tab\there"]), "not usable as a file name"),
    (lambda a: a.update(positions=a["positions"] * 1e16), "positions: a coordinate of .* at most 1e\\+15 m"),
    (lambda a: a.update(normals=a["normals"].astype(np.complex64)), "normals: expected numbers, got complex64"),
])
def test_validation_names_the_problem(change, match):
    a = base_arrays()
    a = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in a.items()}
    change(a)
    with pytest.raises(SceneError, match=match):
        Scene(**a)


def test_missing_and_foreign_files(tmp_path):
    with pytest.raises(SceneError, match="no such job/scene file"):
        load_scene(tmp_path / "nope.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(SceneError, match="not a readable .npz scene"):
        load_scene(tmp_path / "junk.npz")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(SceneError, match="not a PRTT scene"):
        load_scene(tmp_path / "other.npz")
    a = base_arrays()
    np.savez(tmp_path / "nouv.npz", format=np.array("prtt-scene"), version=np.array(1),
             positions=a["positions"], normals=a["normals"], set_id=a["set_id"],
             set_names=np.array(a["set_names"]), set_resolution=a["set_resolution"])
    with pytest.raises(SceneError, match=r"missing arrays \['uvs'\]"):
        load_scene(tmp_path / "nouv.npz")
    np.savez(tmp_path / "future.npz", format=np.array("prtt-scene"), version=np.array(99))
    with pytest.raises(SceneError, match="newer than this PRTT"):
        load_scene(tmp_path / "future.npz")


def test_load_refuses_before_allocating(tmp_path):
    """Headers are checked before any data is read: a texture declared as
    10^6 x 10^6 pixels (12 TB) is refused by its header alone, and a 0-byte or
    truncated job names its path."""
    import io
    import zipfile

    from prtt_addon.core.io.jobfile import JobFile
    save_scene(floor_and_box(res=8), tmp_path / "job.npz")
    with np.load(tmp_path / "job.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["tex_count"] = np.array(1)
    with zipfile.ZipFile(tmp_path / "lie.npz", "w") as zf:
        for k, v in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, v, allow_pickle=False)
            zf.writestr(k + ".npy", buf.getvalue())
        buf = io.BytesIO()
        np.lib.format.write_array_header_1_0(buf, {"descr": "<f4", "fortran_order": False,
                                                   "shape": (10 ** 6, 10 ** 6, 3)})
        zf.writestr("tex_0.npy", buf.getvalue())
    with pytest.raises(SceneError, match=r"lie.npz: tex_0: 1000000x1000000 pixels; at most 16384 a side"):
        load_scene(tmp_path / "lie.npz")
    (tmp_path / "empty.npz").write_bytes(b"")
    with pytest.raises(SceneError, match=r"empty.npz: the file is empty \(0 bytes\)"):
        load_scene(tmp_path / "empty.npz")
    data = (tmp_path / "job.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[:len(data) // 2])
    with pytest.raises(SceneError, match=r"cut.npz: not a readable .npz scene"):
        load_scene(tmp_path / "cut.npz")
    with JobFile(tmp_path / "job.npz") as job:           # sizes known without loading
        assert job.peak_bytes() > floor_and_box(res=8).nbytes()
        assert job.settings() == {}


def test_degenerate_3d_triangles_are_handled(tmp_path):
    """Zero-area triangles in 3D (but with UV area) still bake: their texels use
    the shading normal; a triangle whose normals also vanish loses its texels."""
    from prtt_addon.core.bake.pipeline.context import BakeSettings
    from prtt_addon.core.bake.pipeline.runner import bake_scene
    sc = floor_and_box(res=16)
    sc.positions[0] = sc.positions[0, 0]          # collapse triangle 0 of the floor to a point
    m = bake_scene(sc, tmp_path / "a", BakeSettings(rays=16))
    assert m["sets"][0]["dropped_texels"] == 0
    sc.normals[0] = 0.0
    m = bake_scene(sc, tmp_path / "b", BakeSettings(rays=16))
    assert m["sets"][0]["dropped_texels"] > 0
