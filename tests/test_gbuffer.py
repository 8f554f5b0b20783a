"""UV rasterisation and the G-buffer: coverage, fill rule, overlaps, normals, normal maps."""

import numpy as np

from prtt_addon.core.model.scene import NormalMap
from prtt_addon.core.texels.gbuffer import build_gbuffer
from prtt_addon.core.texels.raster import rasterize
from prtt_addon.dev.bench import meshgen as mg
from tests.scenes_util import planar_uvs, scene_from


def supersampled_touch(uvs, W, H, n=32):
    """Brute force: texels touched by any triangle, from n x n samples per texel
    plus the triangle vertices themselves (catches sub-texel triangles)."""
    touched = np.zeros((H, W), bool)
    P = uvs * [W, H]
    g = (np.arange(n) + 0.5) / n
    for t in P:
        x0, y0 = np.floor(t.min(0)).astype(int)
        x1, y1 = np.ceil(t.max(0)).astype(int)
        for j in range(max(y0, 0), min(y1, H)):
            for i in range(max(x0, 0), min(x1, W)):
                px, py = np.meshgrid(i + g, j + g)
                def e(a, b, px=px, py=py):
                    return (b[0] - a[0]) * (py - a[1]) - (b[1] - a[1]) * (px - a[0])
                e0, e1, e2 = e(t[1], t[2]), e(t[2], t[0]), e(t[0], t[1])
                inside = ((e0 >= 0) & (e1 >= 0) & (e2 >= 0)) | ((e0 <= 0) & (e1 <= 0) & (e2 <= 0))
                if inside.any():
                    touched[j, i] = True
        for v in t:
            vi, vj = int(min(v[0], W - 1e-9)), int(min(v[1], H - 1e-9))
            touched[vj, vi] = True
    return touched


def test_full_quad_each_texel_once_no_overlap():
    quad = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]], float)
    for W, H in [(16, 8), (33, 17), (1, 1)]:
        r = rasterize(quad, W, H)
        assert r.n == W * H and r.overlap_texels == 0 and r.mask().all()
        # barycentrics reproduce the texel centre
        q = np.einsum("nk,nkc->nc", r.bary, quad[r.tri])
        i, j = r.texel % W, r.texel // W
        np.testing.assert_allclose(q, np.c_[(i + 0.5) / W, (j + 0.5) / H], atol=1e-12)


def test_fill_rule_shared_edges_exact_in_a_dense_grid():
    """A 60 x 60 grid of 7200 triangles whose edges pass exactly through texel
    centres: every centre belongs to exactly one triangle."""
    n = 60
    g = np.linspace(0, 1, n + 1)
    X, Y = np.meshgrid(g, g)
    a = np.stack([X[:-1, :-1], Y[:-1, :-1]], -1).reshape(-1, 2)
    b = np.stack([X[:-1, 1:], Y[:-1, 1:]], -1).reshape(-1, 2)
    c = np.stack([X[1:, 1:], Y[1:, 1:]], -1).reshape(-1, 2)
    d = np.stack([X[1:, :-1], Y[1:, :-1]], -1).reshape(-1, 2)
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    # 120 texels over 60 cells: cell edges and diagonals hit texel-centre lines.
    r = rasterize(tris, 120, 120)
    assert r.overlap_texels == 0 and r.n == 120 * 120 and r.conservative_texels == 0


def test_thin_and_sub_texel_islands_have_no_holes(rng):
    tris = [
        [[0.05, 0.1], [0.95, 0.1], [0.95, 0.104]],     # sliver thinner than a texel
        [[0.50, 0.50], [0.51, 0.50], [0.50, 0.51]],     # inside one texel
        [[0.2, 0.3], [0.21, 0.9], [0.205, 0.9]],        # thin diagonal
    ]
    tris += [list(rng.uniform(0.0, 1.0, (3, 2))) for _ in range(5)]
    tris = np.array(tris)
    W = H = 32
    r = rasterize(tris, W, H)
    touched = supersampled_touch(tris, W, H)
    assert np.all(r.mask()[touched]), "a touched texel got no sample"
    # every sample lies on its triangle
    q = np.einsum("nk,nkc->nc", r.bary, tris[r.tri])
    assert np.all(r.bary >= -1e-9) and np.allclose(r.bary.sum(1), 1)
    assert np.all((q >= -1e-9) & (q <= 1 + 1e-9))
    assert r.conservative_texels > 0
    # conservative texels are on the triangle closest to their centre
    assert np.all(r.coverage > 0) and np.all(r.coverage <= 1)


def test_overlapping_islands_are_detected():
    quad = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]], float)
    small = quad * 0.5 + 0.25                       # a second island on top of the first
    r = rasterize(np.concatenate([quad, small]), 16, 16)
    assert r.overlap_texels == 64                   # the small island's 8 x 8 texels
    assert set(r.overlap_triangles.tolist()) == {0, 1, 2, 3}
    # mirrored (clockwise) island on top is an overlap too
    r2 = rasterize(np.concatenate([quad, small[:, ::-1]]), 16, 16)
    assert r2.overlap_texels == 64


def test_zero_area_uv_triangles_are_reported_not_rasterised():
    tris = np.array([[[0.1, 0.1], [0.5, 0.5], [0.9, 0.9]], [[0, 0], [1, 0], [0, 1]]], float)
    r = rasterize(tris, 8, 8)
    assert r.zero_area_triangles.tolist() == [0]
    assert np.all(r.tri == 1)


def test_banded_rasterisation_matches_whole(rng):
    m = mg.uv_sphere(1.0, 24, 12)
    from prtt_addon.core.texels.unwrap import unwrap
    uvs = unwrap([(m.vertices, m.faces)], 64)[0]
    whole = rasterize(uvs, 64, 64)
    parts = [rasterize(uvs, 64, 64, (a, b)) for a, b in [(0, 20), (20, 41), (41, 64)]]
    np.testing.assert_array_equal(np.concatenate([p.texel for p in parts]), whole.texel)
    np.testing.assert_array_equal(np.concatenate([p.tri for p in parts]), whole.tri)
    np.testing.assert_allclose(np.concatenate([p.bary for p in parts]), whole.bary)


def test_gbuffer_positions_and_normals():
    f = mg.plane(2.0).transformed(translate=(0, 0, 0.5))
    sc = scene_from([("floor", f, planar_uvs(f))], 8)
    gb = build_gbuffer(sc, 0)
    assert gb.n == 64
    i, j = gb.texel % 8, gb.texel // 8
    np.testing.assert_allclose(gb.position[:, 0], -1 + 2 * (i + 0.5) / 8)
    np.testing.assert_allclose(gb.position[:, 1], -1 + 2 * (j + 0.5) / 8)
    np.testing.assert_allclose(gb.position[:, 2], 0.5)
    np.testing.assert_allclose(gb.normal, np.tile([0, 0, 1.0], (64, 1)), atol=1e-7)
    np.testing.assert_allclose(gb.geo_normal, gb.normal, atol=1e-7)


def test_geometric_normal_turns_to_the_shaded_side():
    f = mg.plane(2.0)
    sc = scene_from([("floor", f, planar_uvs(f))], 4)
    sc.normals[:] = [0, 0, -1.0]                   # split normals point down
    gb = build_gbuffer(sc, 0)
    np.testing.assert_allclose(gb.geo_normal, np.tile([0, 0, -1.0], (gb.n, 1)))


def normal_mapped_floor(tangent_space_normal, res, strength=1.0):
    """A +Z floor with tangent +X and a constant tangent-space normal map."""
    f = mg.plane(2.0)
    sc = scene_from([("floor", f, planar_uvs(f))], res)
    T = sc.n_triangles
    px = np.full((4, 4, 3), (np.asarray(tangent_space_normal, float) + 1) / 2, np.float32)
    sc.normal_maps = [NormalMap(px, strength)]
    sc.nm_index = np.zeros(T, np.int32)
    sc.nm_uvs = sc.uvs.copy()
    sc.tangents = np.zeros((T, 3, 4), np.float32)
    sc.tangents[..., 0] = 1.0
    sc.tangents[..., 3] = 1.0
    from prtt_addon.core.model.scene import validate
    validate(sc)
    return sc


def test_normal_map_sets_shading_normal():
    """A constant tangent-space map (x=0.6, y=0, z=0.8) on a +Z floor with
    tangent +X tilts every shading normal to (0.6, 0, 0.8)."""
    sc = normal_mapped_floor([0.6, 0.0, 0.8], 16)
    px = sc.normal_maps[0].pixels
    gb = build_gbuffer(sc, 0)
    assert gb.normal_mapped.all()
    np.testing.assert_allclose(gb.normal, np.tile([0.6, 0, 0.8], (gb.n, 1)), atol=2e-3)
    np.testing.assert_allclose(gb.geo_normal, np.tile([0, 0, 1.0], (gb.n, 1)))
    half = build_gbuffer(sc, 0, normal_maps=False)
    np.testing.assert_allclose(half.normal, np.tile([0, 0, 1.0], (gb.n, 1)), atol=1e-7)
    # strength 0.5 blends halfway (Blender's Normal Map node)
    sc.normal_maps = [NormalMap(px, 0.5)]
    gb5 = build_gbuffer(sc, 0)
    want = np.array([0.3, 0, 0.9]) / np.linalg.norm([0.3, 0, 0.9])
    np.testing.assert_allclose(gb5.normal[0], want, atol=2e-3)


def test_extreme_normal_map_is_kept_above_the_horizon():
    sc = normal_mapped_floor([1.0, 0.0, 0.0], 4)         # a normal lying in the plane
    gb = build_gbuffer(sc, 0)
    cos = np.einsum("nc,nc->n", gb.normal, gb.geo_normal)
    assert np.all(cos >= 0.05 - 1e-9) and np.all(np.isfinite(gb.normal))


def test_more_row_bands_build_the_same_gbuffer(monkeypatch):
    """Large sets are built in more row bands (gbuffer.BAND_TEXELS, bounded
    temporaries); the G-buffer is the same array for array."""
    import concurrent.futures as cf

    from prtt_addon.core.texels import gbuffer as gbm
    from prtt_addon.dev.bench.scene_library import room_scene
    sc = room_scene(256, atlas=True)
    sc.set_resolution[:] = 512
    with cf.ThreadPoolExecutor(3) as ex:
        two = gbm.build_gbuffer(sc, 0, executor=ex, bands=2)
        monkeypatch.setattr(gbm, "BAND_TEXELS", 512 * 512 // 7)
        many = gbm.build_gbuffer(sc, 0, executor=ex, bands=2)
    for f in ("texel", "tri", "bary", "position", "normal", "geo_normal", "coverage", "normal_mapped"):
        assert np.array_equal(getattr(two, f), getattr(many, f)), f
    assert two.stats == many.stats
