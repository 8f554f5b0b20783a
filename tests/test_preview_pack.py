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
    """The renderer's uploads (LayerSource: bands of rows of the file's
    channels decoded in a child, no copy of the texture) equal pack_layers /
    pack_relight_operator of the readers' arrays, bit for bit: shared glossy
    rows (tuning auto) tinted per colour as expand_shared_glossy, per-colour
    rows (fixed) as stored."""
    from prtt_addon.core.bake.pipeline.context import BakeSettings
    from prtt_addon.core.bake.pipeline.runner import bake_scene
    from prtt_addon.core.io.exr_io import read_relight_exr, read_sh_exr
    from prtt_addon.core.light.envmap import builtin_environment_path, environment_light
    from prtt_addon.dev.bench.scene_library import room_scene
    sc = room_scene(64, atlas=True, materials=True)
    bake_scene(sc, tmp_path, BakeSettings(rays=16, bounce_rays=8, bounces=1, tuning=tuning),
               light=environment_light(builtin_environment_path("forest"), 5))
    t = str(tmp_path / "atlas.transfer.exr")
    src = pp.transfer_layers(t)
    got = np.full((src.layers, src.height, src.width, 4), np.nan, np.float32)
    src.fill(got)
    assert src.coeffs == 25 and not src.rgb
    want = pp.pack_layers(read_sh_exr(t)[0])
    assert got.tobytes() == want.tobytes()
    r = str(tmp_path / "atlas.relight.exr")
    src = pp.relight_operator_layers(r)
    got = np.full((src.layers, src.height, src.width, 4), np.nan, np.float32)
    src.fill(got, rows=5)               # bands of 5 rows: a short last band, tints made per band
    assert src.glossy_bands == 3 and (src.tint_from is not None) == (tuning == "auto")
    dc, glossy, _ = read_relight_exr(r)
    assert glossy is not None
    assert got.tobytes() == pp.pack_relight_operator(dc, glossy).tobytes()


def test_layer_source_names_a_missing_channel(tmp_path):
    from prtt_addon.core.io.exr_io import TextureError, write_sh_planes
    p = str(tmp_path / "t.exr")
    write_sh_planes(p, np.ones((9, 4, 4), np.float32), kind="transfer", attrs={"bands": 4}, names=None, bands=None)
    with pytest.raises(TextureError, match="missing channels"):
        pp.transfer_layers(p)


def test_level_sum_source_is_load_bounce_packed_exactly(tmp_path):
    """Baked bounce levels go up as a band-by-band sum (LevelSumSource) equal
    to pack_bounce(PreviewSet.load_bounce(K)) bit for bit: two levels, one
    band-limited (tuning auto) and padded, bands of 7 rows (a short last
    band); the sum is not half-exact, so the renderer checks it."""
    from prtt_addon.core.bake.pipeline.context import BakeSettings
    from prtt_addon.core.bake.pipeline.runner import bake_scene
    from prtt_addon.core.light.envmap import builtin_environment_path, environment_light
    from prtt_addon.dev.bench.scene_library import room_scene
    sc = room_scene(48, atlas=True, materials=True)
    bake_scene(sc, tmp_path, BakeSettings(rays=16, bounce_rays=8, bounces=2, bounce_mode="baked", tuning="auto"),
               light=environment_light(builtin_environment_path("forest"), 5))
    levels = sorted(str(p) for p in tmp_path.glob("atlas.bounce*.exr"))
    assert len(levels) == 2
    want = pp.pack_bounce(pp.PreviewSet("atlas", "", tuple(levels)).load_bounce(25))
    src = pp.bounce_level_layers(levels, 25)
    got = np.full((src.layers, src.height, src.width, 4), np.nan, np.float32)
    src.fill(got, rows=7)
    assert got.tobytes() == want.tobytes()
    assert not src.half_exact and src.dtypes


def test_band_stream_refuses_what_it_cannot_decode(tmp_path, monkeypatch):
    """The band reader's child: a missing channel, a cut file and a decoder
    that dies are each a TextureError naming the file, never a hang or a
    short band."""
    from prtt_addon.core.io import exr_bands
    from prtt_addon.core.io.exr_io import TextureError, read_sh_exr, write_sh_planes
    p = tmp_path / "t.exr"
    write_sh_planes(p, np.random.default_rng(1).normal(size=(9, 64, 64)).astype(np.float32), kind="transfer",
                    attrs={"bands": 3}, names=None, bands=None)
    names = [f"sh{k:03d}" for k in range(9)]
    with exr_bands.channel_bands(p, names, 64, 64, 10, error=TextureError) as st:
        got = np.concatenate([c["sh004"].astype(np.float32) for _, _, c in st])   # file rows, top first
    assert got.tobytes() == np.ascontiguousarray(read_sh_exr(p)[0][::-1, :, 4]).tobytes()
    with pytest.raises(TextureError, match=r"t\.exr: unreadable EXR \(missing channels \['sh009'\]"):
        with exr_bands.channel_bands(p, names + ["sh009"], 64, 64, 10, error=TextureError):
            pass
    cut = tmp_path / "cut.exr"
    cut.write_bytes(p.read_bytes()[:-4000])
    with pytest.raises(TextureError, match=r"cut\.exr: unreadable EXR"):
        with exr_bands.channel_bands(cut, names, 64, 64, 10, error=TextureError) as st:
            for _ in st:
                pass
    with pytest.raises(TextureError, match="data window"):
        with exr_bands.channel_bands(p, names, 32, 64, 10, error=TextureError):
            pass
    # One band must fit beside what the process holds (a header can declare many wide channels).
    from prtt_addon.core.base import memory
    monkeypatch.setattr(memory, "available_bytes", lambda: 20_000)
    with pytest.raises(TextureError, match=r"t\.exr \(10 rows of 9 channels\) needs about .* GiB is available"):
        with exr_bands.channel_bands(p, names, 64, 64, 10, error=TextureError):
            pass


def test_band_stream_protocol_is_guarded(tmp_path, monkeypatch):
    """Print noise in the decoder goes to stderr and leaves the stream intact;
    bytes past the texture, or a decoder that goes silent (the watchdog kills
    it: blocking reads, no select), are TextureErrors naming the file."""
    from prtt_addon.core.io import exr_bands
    from prtt_addon.core.io.exr_io import TextureError, read_sh_exr, write_sh_planes
    p = tmp_path / "t.exr"
    write_sh_planes(p, np.random.default_rng(2).normal(size=(4, 40, 24)).astype(np.float32), kind="transfer",
                    attrs={"bands": 2}, names=None, bands=None)
    names = [f"sh{k:03d}" for k in range(4)]
    child = exr_bands._CHILD
    assert "os.dup2(2, 1)\n" in child and child.rstrip().endswith("out.close()")

    def read():
        with exr_bands.channel_bands(p, names, 40, 24, 16, error=TextureError) as st:
            return np.concatenate([c["sh002"].astype(np.float32) for _, _, c in st])
    monkeypatch.setattr(exr_bands, "_CHILD", child.replace("os.dup2(2, 1)\n", "os.dup2(2, 1)\nprint('noise')\n"))
    assert read().tobytes() == np.ascontiguousarray(read_sh_exr(p)[0][::-1, :, 2]).tobytes()
    monkeypatch.setattr(exr_bands, "_CHILD", child.rstrip()[:-len("out.close()")] + "out.write(b'x')\nout.close()\n")
    with pytest.raises(TextureError, match=r"t\.exr: unreadable EXR \(its decoder sent more than the texture holds"):
        read()
    monkeypatch.setattr(exr_bands, "_CHILD", child.replace("req = json.loads", "import time; time.sleep(60)\nreq = json.loads"))
    monkeypatch.setattr(exr_bands, "BAND_TIMEOUT", 1)
    with pytest.raises(TextureError, match=r"t\.exr: unreadable EXR \(its decoder sent nothing for 1 s\)"):
        read()
