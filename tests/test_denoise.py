"""Texture-space denoisers: island labels, the edge-aware filter never mixing
islands, OIDN on normalised SH (when pyoidn is installed)."""
import numpy as np
import pytest
from scipy import ndimage

from prtt_addon.core.bake.estimators.denoise import edge_aware, oidn_available, oidn_sh
from prtt_addon.core.base import jit
from prtt_addon.core.texels.islands import island_labels, island_labels_numpy


@pytest.mark.parametrize("path", ["numba", "numpy"])
def test_island_labels_match_scipy(path):
    rng = np.random.default_rng(5)
    mask = ndimage.binary_opening(rng.random((80, 96)) > 0.45)
    mask[10:70, 40] = True                               # a long thin island joining others
    mask[5, 5:90] = True
    mask[79, 95] = mask[0, 0] = True                     # corners
    if path == "numba":
        assert jit.load("prtt_addon.core.texels.islands_jit") is not None, "numba is pinned in requirements.txt"
    ours = island_labels(mask) if path == "numba" else island_labels_numpy(mask)
    ref, n = ndimage.label(mask, structure=np.ones((3, 3)))
    assert n > 5
    assert np.all((ours >= 0) == mask)
    # Same partition: a bijection between our labels and scipy's.
    pairs = set(zip(ours[mask].tolist(), ref[mask].tolist()))
    assert len(pairs) == n == len(set(ours[mask].tolist()))
    # Labels are the smallest flat index of their island.
    flat = np.arange(mask.size).reshape(mask.shape)
    for lab in set(ours[mask].tolist()):
        assert lab == flat[ours == lab].min()


def test_island_labels_paths_agree_on_spirals_and_noise():
    """The union-find (numba) and the min-label propagation (numpy) label
    alike: a spiral (one island whose smallest index is reached last along
    it), diagonal-only contacts and random masks of several densities."""
    rng = np.random.default_rng(9)
    masks = [rng.random((64, 80)) > p for p in (0.3, 0.5, 0.6, 0.8)]
    spiral = np.zeros((41, 41), bool)
    y, x, dy, dx, n = 20, 20, 0, 1, 1
    while 0 <= y < 41 and 0 <= x < 41:
        for _ in range(2):
            for _ in range(n):
                if 0 <= y < 41 and 0 <= x < 41:
                    spiral[y, x] = True
                y, x = y + 2 * dy, x + 2 * dx
                if 0 <= y - dy < 41 and 0 <= x - dx < 41:
                    spiral[y - dy, x - dx] = True
            dy, dx = dx, -dy
        n += 1
    diag = np.eye(30, dtype=bool) | np.eye(30, dtype=bool)[::-1]
    assert jit.load("prtt_addon.core.texels.islands_jit") is not None, jit.failures    # not numpy against numpy
    for mask in masks + [spiral, diag, np.zeros((5, 7), bool), np.ones((5, 7), bool)]:
        assert np.array_equal(island_labels(mask), island_labels_numpy(mask))
    assert len(set(island_labels(diag)[diag].tolist())) == 1


def _two_islands(noise=0.2, seed=0):
    """Two 20x20 islands two texels apart, one at radiance 1, the other at 5,
    on the same flat surface (world positions continuous across the gap: only
    the island labels keep them apart)."""
    H, W = 24, 46
    mask = np.zeros((H, W), bool)
    mask[2:22, 2:22] = True
    mask[2:22, 24:44] = True
    yy, xx = np.mgrid[0:H, 0:W].astype(float)
    pos = np.stack([xx * 0.01, yy * 0.01, np.zeros_like(xx)], -1)
    nrm = np.zeros((H, W, 3))
    nrm[..., 2] = 1.0
    rng = np.random.default_rng(seed)
    truth = np.where(xx < 23, 1.0, 5.0)
    planes = np.zeros((75, H, W), np.float32)
    for c in range(3):
        planes[c * 25] = np.where(mask, truth * (1 + noise * rng.normal(size=(H, W))), 0.0)
        planes[c * 25 + 2] = np.where(mask, 0.3 * truth, 0.0)
    return planes, mask, pos, nrm, truth


def test_edge_aware_never_mixes_islands_and_reduces_noise():
    planes, mask, pos, nrm, truth = _two_islands()
    out = edge_aware(planes, mask, pos, nrm, radius=3, sigma_texels=2.0)
    left, right = mask & (np.arange(46) < 23), mask & (np.arange(46) >= 23)
    # Constant coefficients per island stay exactly constant (weights sum to one
    # within an island; a texel of the other island would move them).
    assert np.allclose(out[2][left], 0.3) and np.allclose(out[2][right], 1.5)
    # The noisy DC term gets closer to the truth on both islands.
    for side in (left, right):
        before = np.sqrt(np.mean((planes[0][side] - truth[side]) ** 2))
        after = np.sqrt(np.mean((out[0][side] - truth[side]) ** 2))
        assert after < 0.6 * before
    # Along the gap: the left island's border texels are not pulled towards 5.
    assert out[0][2:22, 21].mean() < 1.3
    # Empty texels unchanged.
    assert np.array_equal(out[:, ~mask], planes[:, ~mask])


def test_edge_aware_respects_normals_and_positions():
    planes, mask, pos, nrm, truth = _two_islands(noise=0.0)
    # One island, folded: the right half faces another way (a box edge).
    mask[:, 22:24] = True
    planes[:, :, 22:24] = planes[:, :, 24:25]
    nrm[:, 22:] = [1.0, 0.0, 0.0]
    out = edge_aware(planes, mask, pos, nrm, radius=2, normal_power=16.0)
    assert np.abs(out[0][2:22, 20] - 1.0).max() < 1e-6       # the fold keeps the sides apart


@pytest.mark.skipif(not oidn_available(), reason="pyoidn is optional and not installed")
def test_oidn_sh_restores_normalisation_and_keeps_empty_texels():
    planes, mask, pos, nrm, truth = _two_islands(noise=0.0)
    out = oidn_sh(planes, mask, 5)
    assert out.shape == planes.shape and out.dtype == np.float32
    assert np.array_equal(out[:, ~mask], planes[:, ~mask])
    # A noise-free constant field stays close (normalised coefficient 0.3/sqrt(5)).
    inner = np.zeros_like(mask)
    inner[6:18, 6:18] = True
    assert np.allclose(out[0][inner], 1.0, rtol=0.05)
    assert np.allclose(out[2][inner], 0.3, rtol=0.08)
    with pytest.raises(ValueError, match="expected 25 or 75"):
        oidn_sh(planes[:10], mask, 5)
    scalar = oidn_sh(planes[:25], mask, 5)                    # a transfer texture
    assert np.allclose(scalar[0][inner], 1.0, rtol=0.05)
    assert np.allclose(scalar[2][inner], 0.3, rtol=0.08)


def test_bake_option_filters_bounces_within_islands(tmp_path, monkeypatch):
    from prtt_addon.core.bake.pipeline.context import BakeSettings
    from prtt_addon.core.bake.pipeline.runner import bake_scene
    from prtt_addon.core.base.errors import BakeError
    from prtt_addon.core.io import exr_io
    from tests.test_bounce import corner_scene, sky
    sc = corner_scene({"name": "w", "base_color": [0.6, 0.5, 0.4], "specular": 0.0}, res=24)
    st = dict(rays=64, bounces=1, bounce_rays=16, half=False, bounce_mode="baked")
    raw_m = bake_scene(sc, tmp_path / "raw", BakeSettings(bounce_denoise="none", **st), light=sky())
    m = bake_scene(sc, tmp_path / "den", BakeSettings(bounce_denoise="edge-aware", **st), light=sky())
    assert m["bounce"]["key"] != raw_m["bounce"]["key"]
    rep = [r for r in m["bounce"]["sets"] if r["name"] == "floor"][0]
    assert rep["denoise"]["filter"] == "edge-aware" and rep["denoise"]["seconds"] >= 0
    raw, _ = exr_io.read_sh_exr(tmp_path / "raw" / "floor.bounce1.exr")
    den, _ = exr_io.read_sh_exr(tmp_path / "den" / "floor.bounce1.exr")
    assert not np.array_equal(raw, den)
    # Smoother: neighbouring texels of the floor differ less after filtering.
    rough = lambda t: np.abs(np.diff(t[4:20, 4:20, :, 0], axis=1)).mean()  # noqa: E731
    assert rough(den) < 0.8 * rough(raw)
    # Same transfer (only the bounce changed).
    assert (tmp_path / "raw" / "floor.transfer.exr").read_bytes() == (tmp_path / "den" / "floor.transfer.exr").read_bytes()
    # "auto" is edge-aware below 128 bounce rays, none from there on; the default is none.
    assert BakeSettings().bounce_denoise == "none"
    auto = bake_scene(sc, tmp_path / "auto", BakeSettings(bounce_denoise="auto", **st), light=sky())
    assert [r["denoise"]["filter"] for r in auto["bounce"]["sets"] if "denoise" in r] == ["edge-aware"] * 2
    assert (tmp_path / "auto" / "floor.bounce1.exr").read_bytes() == (tmp_path / "den" / "floor.bounce1.exr").read_bytes()
    many = bake_scene(sc, tmp_path / "many", BakeSettings(bounce_denoise="auto", **dict(st, bounce_rays=128)),
                      light=sky())
    assert not any("denoise" in r for r in many["bounce"]["sets"])
    import prtt_addon.core.bake.estimators.denoise as dn
    monkeypatch.setattr(dn, "oidn_available", lambda: False)
    with pytest.raises(BakeError, match="needs the optional package pyoidn"):
        bake_scene(sc, tmp_path / "o", BakeSettings(bounce_denoise="oidn", **st), light=sky())
    assert not (tmp_path / "o" / "floor.transfer.exr").exists()
