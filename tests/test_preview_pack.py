"""The preview's data layouts (core/preview/pack.py) and image writer, without Blender."""
import numpy as np
import pytest

from prtt_addon.core.preview import pack as pp


def test_build_mesh_merges_identical_corners_and_sorts_by_material():
    # A quad as two triangles sharing an edge, plus a third triangle with another material.
    P = np.array([[[0, 0, 0], [1, 0, 0], [1, 1, 0]], [[0, 0, 0], [1, 1, 0], [0, 1, 0]],
                  [[2, 0, 0], [3, 0, 0], [2, 1, 0]]], float)
    N = np.tile([0, 0, 1.0], (3, 3, 1))
    uv = P[..., :2] / 3
    m = pp.build_mesh("q", "s", {"positions": P, "normals": N, "uv": uv}, np.array([1, 1, 0]))
    assert m.positions.shape[0] == 7                  # 4 quad corners + 3, not 9
    assert [r[0] for r in m.ranges] == [0, 1] and m.ranges[1] == (1, 1, 2)
    # every triangle survives with its corners, in material order
    got = {tuple(map(tuple, m.positions[t])) for t in m.indices}
    want = {tuple(map(tuple, p)) for p in P.astype(np.float32)}
    assert got == want
    # the same position with another material is another vertex (vertex baselines shade per material)
    m2 = pp.build_mesh("q", "s", {"positions": P[:2], "normals": N[:2]}, np.array([0, 1]))
    assert m2.positions.shape[0] == 6
    # world corners honour the matrix, normals the inverse transpose
    M = np.diag([2.0, 1.0, 1.0, 1.0])
    M[:3, 3] = [0, 0, 5]
    m.matrix = M
    wp = m.world_corners("positions")
    np.testing.assert_allclose(wp[..., 0], 2 * m.positions[m.indices][..., 0])
    np.testing.assert_allclose(wp[..., 2], 5.0)
    S = np.diag([1.0, 1.0, 4.0, 1.0])                  # squash z: normals must stay unit-ish along z
    m.matrix = S
    assert np.allclose(m.world_corners("normals")[..., 2], 0.25)


def test_zero_normals_become_face_normals():
    P = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], float)
    N = np.zeros((1, 3, 3))
    fixed = pp.fix_corner_normals(N, P)
    np.testing.assert_allclose(fixed, np.tile([0, 0, 1.0], (1, 3, 1)))
    degenerate = np.zeros((1, 3, 3))
    np.testing.assert_allclose(pp.fix_corner_normals(N, degenerate), np.tile([0, 0, 1.0], (1, 3, 1)))


def test_layer_packing_layouts():
    H, W, K = 3, 5, 25
    tex = np.arange(H * W * K, dtype=np.float32).reshape(H, W, K)
    L = pp.pack_layers(tex)
    assert L.shape == (7, H, W, 4)
    for k in (0, 3, 4, 24):
        np.testing.assert_array_equal(L[k // 4, :, :, k % 4], tex[..., k])
    assert np.all(L[6, :, :, 1:] == 0)                 # padding
    b = np.random.default_rng(1).random((H, W, 3, K)).astype(np.float32)
    B = pp.pack_bounce(b)
    assert B.shape == (21, H, W, 4)
    for c in range(3):
        for k in (0, 7, 24):
            np.testing.assert_array_equal(B[c * 7 + k // 4, :, :, k % 4], b[:, :, c, k])
    coeffs = np.random.default_rng(2).random((10, K)).astype(np.float32)
    V = pp.pack_vertex_transfer(coeffs, width=4)
    assert V.shape == (7, 3, 4, 4)
    for i in (0, 5, 9):
        np.testing.assert_array_equal(V[:, i // 4, i % 4, :].ravel()[:K], coeffs[i])


def test_light_block_holds_the_tpfl_matrix():
    from prtt_addon.core.sh.gaunt import sparse_gaunt
    bands, K = 5, 25
    L = np.random.default_rng(3).normal(size=(K, 3))
    blk = pp.light_block(L, bands)
    rows = blk[:3 * K * 28].reshape(3, K, 28)[:, :, :K]
    # M_ik = sum_j tau_ijk L_j, from the sparse tensor directly
    g = sparse_gaunt(bands)
    want = np.zeros((3, K, K))
    for c in range(3):
        np.add.at(want[c], (g.i, g.k), g.value * L[g.j, c])
    np.testing.assert_allclose(rows, want, atol=1e-6)
    np.testing.assert_allclose(blk[3 * K * 28:].reshape(K, 4)[:, :3], L, rtol=1e-6)
    assert blk.nbytes == 16 * (3 * K * 7 + K)
    from prtt_addon.core.preview.shader_source import light_block_bytes
    assert light_block_bytes(bands) == blk.nbytes


def test_half_exact():
    assert pp.half_exact(np.array([0.5, 1.0, 65504.0], np.float32))
    assert not pp.half_exact(np.array([0.1], np.float32))
    assert not pp.half_exact(np.array([70000.0], np.float32))


def test_image_writer(tmp_path):
    import matplotlib.image as mpimg

    from prtt_addon.core.io.image_write import read_exr_rgba, srgb_encode, write_image
    a = np.random.default_rng(4).random((6, 9, 4)).astype(np.float32)
    a[0, 0, :3] = [np.nan, 5.0, -1.0]
    write_image(str(tmp_path / "x.png"), a, exposure=0.5)
    png = mpimg.imread(str(tmp_path / "x.png"))
    assert png.shape == (6, 9, 4)
    want = np.round(srgb_encode(0.5 * a[..., :3]) * 255) / 255
    np.testing.assert_allclose(png[::-1, :, :3], want, atol=1e-6)        # file is top row first
    assert tuple(png[-1, 0, :3]) == (0.0, 1.0, 0.0)                        # NaN -> 0, clipped
    write_image(str(tmp_path / "x.exr"), a)
    np.testing.assert_array_equal(read_exr_rgba(str(tmp_path / "x.exr")), a)
    with pytest.raises(ValueError, match=".png or .exr"):
        write_image(str(tmp_path / "x.jpg"), a)


def test_shader_variants_are_described():
    from prtt_addon.core.preview.shader_source import MODES, depth_variant, variant
    for mode in MODES:
        for bounce in (False, True):
            v = variant(mode, 5, bounce=bounce)
            src = v.vertex_source() + v.fragment_source()
            assert "void main()" in src
            names = {s[2] for s in v.samplers}
            assert ("bounceTex" in names) == bounce
            assert ("gauntTex" in names) == (mode in ("tp", "vertex-tp"))
            assert len({s[0] for s in v.samplers}) == len(v.samplers)      # distinct slots
    assert "prtt_view.glsl" in depth_variant().vertex_files
    with pytest.raises(ValueError, match="1 to 8"):
        variant("tpfl", 9)
    with pytest.raises(ValueError, match="unknown preview mode"):
        variant("phong", 5)


@pytest.mark.parametrize("tuning", ["auto", "fixed"])
def test_layer_sources_fill_the_packed_layers_exactly(tmp_path, tuning):
    """The renderer's uploads (LayerSource: one layer at a time from the file's
    channels, no float32 copy of the texture) equal pack_layers /
    pack_relight_operator of the readers' arrays, bit for bit: shared glossy
    rows (tuning auto) tinted per colour as expand_shared_glossy, per-colour
    rows (fixed) as stored."""
    from prtt_addon.bench.scene_library import room_scene
    from prtt_addon.core.bake.pipeline.context import BakeSettings
    from prtt_addon.core.bake.pipeline.runner import bake_scene
    from prtt_addon.core.io.exr_io import read_relight_exr, read_sh_exr
    from prtt_addon.core.light.envmap import builtin_environment_path, environment_light
    sc = room_scene(64, atlas=True, materials=True)
    bake_scene(sc, tmp_path, BakeSettings(rays=16, bounce_rays=8, bounces=1, tuning=tuning),
               light=environment_light(builtin_environment_path("forest"), 5))
    t = str(tmp_path / "atlas.transfer.exr")
    with pp.transfer_layers(t) as src:
        got = np.full((src.layers, src.height, src.width, 4), np.nan, np.float32)
        src.fill(got)
        assert src.coeffs == 25 and not src.rgb
    want = pp.pack_layers(read_sh_exr(t)[0])
    assert got.tobytes() == want.tobytes()
    r = str(tmp_path / "atlas.relight.exr")
    with pp.relight_operator_layers(r) as src:
        got = np.full((src.layers, src.height, src.width, 4), np.nan, np.float32)
        src.fill(got)
        assert src.glossy_bands == 3 and (src.tint is not None) == (tuning == "auto")
    dc, glossy, _ = read_relight_exr(r)
    assert glossy is not None
    assert got.tobytes() == pp.pack_relight_operator(dc, glossy).tobytes()


def test_layer_source_names_a_missing_channel(tmp_path):
    from prtt_addon.core.io.exr_io import TextureError, write_sh_planes
    p = str(tmp_path / "t.exr")
    write_sh_planes(p, np.ones((9, 4, 4), np.float32), kind="transfer", attrs={"bands": 4}, names=None, bands=None)
    with pytest.raises(TextureError, match="missing channels"):
        with pp.transfer_layers(p):
            pass
