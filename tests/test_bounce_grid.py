"""Bounce textures on a coarser grid than the transfer (settings.bounce_downscale):
the island check, the grid choice, and bakes on it."""
import numpy as np
import pytest

from prtt_addon.core.bake.pipeline import bounce_stage
from prtt_addon.core.bake.pipeline.context import BakeSettings
from prtt_addon.core.bake.pipeline.runner import bake_scene
from prtt_addon.core.io import exr_io
from prtt_addon.core.preview.pack import PreviewSet
from prtt_addon.core.texels.islands import block_labels, coarse_grid_conflicts, island_labels
from tests.test_bounce import corner_scene, sky


def _two_islands(gap: int, size=64):
    """Two square islands on a size x size grid, ``gap`` empty columns apart."""
    m = np.zeros((size, size), bool)
    m[8:40, 4:20] = True
    m[8:40, 20 + gap:36 + gap] = True
    return m


@pytest.mark.parametrize("gap,f,expect", [
    (8, 2, 0), (4, 2, 0),      # 4 fine texels = 2 coarse: no coarse texel within 1 of both
    (2, 2, 1),                 # 1 coarse texel apart: the texel between sees both
    (0, 2, 0),                 # touching: one 8-connected island already at full resolution
    (8, 4, 0), (4, 4, 1),
])
def test_conflicts_follow_the_gap_in_coarse_texels(gap, f, expect):
    m = _two_islands(gap)
    n = coarse_grid_conflicts(m, f)
    assert (n > 0) == bool(expect), (gap, f, n)


def test_conflicts_brute_force():
    """Against a direct reading of the rule on random layouts: a coarse texel
    conflicts when its 3 x 3 neighbourhood of f x f blocks holds covered fine
    texels of two islands."""
    rng = np.random.default_rng(3)
    for _ in range(20):
        m = rng.random((32, 32)) < 0.08
        m[rng.integers(0, 32), :] = True               # a long island too
        lab = island_labels(m)
        for f in (2, 4):
            h = 32 // f
            want = 0
            for y in range(h):
                for x in range(h):
                    ys = slice(max(0, (y - 1) * f), min(32, (y + 2) * f))
                    xs = slice(max(0, (x - 1) * f), min(32, (x + 2) * f))
                    want += len(set(lab[ys, xs][lab[ys, xs] >= 0].tolist())) > 1
            assert coarse_grid_conflicts(m, f, lab) == want


def test_block_labels_needs_a_multiple():
    with pytest.raises(ValueError, match="not a multiple of 4"):
        block_labels(np.full((10, 12), -1), 4)


class _GB:
    def __init__(self, mask):
        self.height, self.width = mask.shape
        self.texel = np.flatnonzero(mask.reshape(-1))
        self._mask = mask

    def mask(self):
        return self._mask


def test_choose_grid_steps_down_and_says_why():
    g = bounce_stage.choose_grid(_GB(_two_islands(8)), 4)
    assert (g.downscale, g.width, g.height) == (4, 16, 16)
    g = bounce_stage.choose_grid(_GB(_two_islands(4)), 4)
    assert g.downscale == 2 and "1/4:" in g.why and "would mix UV islands" in g.why
    g = bounce_stage.choose_grid(_GB(_two_islands(1)), 4)
    assert g.downscale == 1 and g.width == 64 and "the transfer's grid" in g.why
    g = bounce_stage.choose_grid(_GB(np.ones((48, 44), bool)), 2)
    assert g.downscale == 2
    g = bounce_stage.choose_grid(_GB(np.ones((48, 44), bool)), 8)       # 44 is not a multiple of 8
    assert g.downscale == 2 and "not a multiple of 8" in g.why and "fewer than 16" in g.why


def _corner(res):
    return corner_scene({"name": "wall", "base_color": [0.9, 0.2, 0.1], "roughness": 0.3}, res)


def _light():
    return sky(5)


def test_half_grid_bake_matches_the_full_grid_block_means(tmp_path):
    """Baked at 1/2, the bounce texture is the full-grid bake averaged over 2 x 2
    blocks, to within the Monte Carlo noise of both (same rays per texel)."""
    sc = _corner(64)
    st = dict(bounces=1, bounce_rays=512, rays=256, half=False, dilate=0, tuning="fixed", bounce_mode="baked")
    full = bake_scene(sc, tmp_path / "full", BakeSettings(**st), light=_light())
    half = bake_scene(sc, tmp_path / "half", BakeSettings(**st, bounce_downscale=2), light=_light())
    assert full["bounce"]["sets"][0].get("grid") is None
    assert [r["grid"]["downscale"] for r in half["bounce"]["sets"]] == [2, 2]
    assert half["bounce"]["rays_traced"] < 0.3 * full["bounce"]["rays_traced"]
    for name in sc.set_names:
        a, _ = exr_io.read_sh_exr(tmp_path / "full" / f"{name}.bounce1.exr")      # (64, 64, 3, 25)
        b, _ = exr_io.read_sh_exr(tmp_path / "half" / f"{name}.bounce1.exr")      # (32, 32, 3, 25)
        assert a.shape[:2] == (64, 64) and b.shape[:2] == (32, 32)
        mean = a.reshape(32, 2, 32, 2, 3, 25).mean(axis=(1, 3))
        dc_a, dc_b = mean[..., 0], b[..., 0]
        rel = np.sqrt(np.mean((dc_a - dc_b) ** 2) / np.mean(dc_a ** 2))
        assert dc_a.mean() > 0 and rel < 0.05, (name, rel)


def test_downscale_one_is_todays_bake(tmp_path):
    """tuning fixed with bounce_downscale 1 is the bake before per-set tuning
    (no grid entry); asking for 1/2 changes the key and the textures."""
    sc = _corner(32)
    a = bake_scene(sc, tmp_path / "a", BakeSettings(bounces=1, bounce_rays=16, rays=32, tuning="fixed"), light=_light())
    b = bake_scene(sc, tmp_path / "b", BakeSettings(bounces=1, bounce_rays=16, rays=32, bounce_downscale=2, tuning="fixed"),
                   light=_light())
    assert a["bounce"]["key"] != b["bounce"]["key"]
    assert "grid" not in a["bounce"]["sets"][0]
    for f in a["bounce"]["files"]:
        assert (tmp_path / "a" / f).read_bytes() != (tmp_path / "b" / f).read_bytes()


def test_auto_tuning_stores_the_bands_each_set_reads(tmp_path):
    """tuning auto: the diffuse floor keeps 1 band (its DC equals the full-band
    bake's on the same grid, bit for bit), the glossy wall 3; the preview's
    loader pads them back with zeros; the manifest says what and why."""
    sc = _corner(64)
    sc.materials[0]["specular"] = 0.0          # a purely diffuse floor (the default has a Phong lobe)
    sc.materials[1]["roughness"] = 0.8         # a rough wall: Phong exponent 0.72, |A_3|, |A_4| < 0.05 A_0
    st = dict(bounces=1, rays=64, half=False, bounce_mode="baked")
    # auto traces 1.5x the bounce rays on its coarser grid: 32 -> 48
    full = bake_scene(sc, tmp_path / "full", BakeSettings(**st, bounce_rays=48, bounce_downscale=2, tuning="fixed"),
                      light=_light())
    auto = bake_scene(sc, tmp_path / "auto", BakeSettings(**st, bounce_rays=32, tuning="auto"), light=_light())
    grids = {r["name"]: r["grid"] for r in auto["bounce"]["sets"]}
    assert grids["floor"]["bands"] == 1 and "DC term" in grids["floor"]["bands_why"]
    assert grids["wall"]["bands"] == 3 and "3 of 5 bands pass their Phong lobes" in grids["wall"]["bands_why"]
    assert {g["downscale"] for g in grids.values()} == {2} and {g["rays"] for g in grids.values()} == {48}
    assert full["bounce"]["key"] != auto["bounce"]["key"] and full["settings_hash"] == auto["settings_hash"]
    assert auto["bounce"]["rays_traced"] == full["bounce"]["rays_traced"]
    for name, kb in (("floor", 1), ("wall", 9)):
        a, _ = exr_io.read_sh_exr(tmp_path / "full" / f"{name}.bounce1.exr")
        b, attrs = exr_io.read_sh_exr(tmp_path / "auto" / f"{name}.bounce1.exr")
        assert b.shape == a.shape[:3] + (kb,) and attrs["band_limited"] == 1 and attrs["shading_bands"] == 5
        assert attrs["rays"] == 48                                       # what each coarse texel traced
        np.testing.assert_array_equal(b, a[..., :kb])
        ps = PreviewSet(name, str(tmp_path / "auto" / f"{name}.transfer.exr"),
                        (str(tmp_path / "auto" / f"{name}.bounce1.exr"),))
        padded = ps.load_bounce(25)
        assert padded.shape == a.shape and not padded[..., kb:].any()
        np.testing.assert_array_equal(padded[..., :kb], a[..., :kb])
    bytes_of = lambda m, d: sum((d / f).stat().st_size for f in m["bounce"]["files"])  # noqa: E731
    assert bytes_of(auto, tmp_path / "auto") < 0.5 * bytes_of(full, tmp_path / "full")


def test_band_limited_levels_are_padded_only_when_marked(tmp_path):
    """A bounce file with too few coefficients and no band_limited mark (an
    older or foreign bake) is not silently padded."""
    planes = np.ones((3 * 9, 4, 4), np.float32)
    exr_io.write_sh_planes(tmp_path / "x.bounce1.exr", planes, kind="bounce", rgb=True, half=False)
    ps = PreviewSet("x", "", (str(tmp_path / "x.bounce1.exr"),))
    assert ps.load_bounce(25).shape[-1] == 9


@pytest.mark.parametrize("roughness,bands", [(0.3, 5), (0.6, 5), (0.7, 4), (0.8, 3), (1.0, 4)])
def test_bounce_bands_follow_the_phong_lobe(roughness, bands):
    """Against the lobe factors computed here independently (the normalised
    Phong lobe's zonal coefficients by quadrature, not zonal.phong_factors)."""
    sc = _corner(8)
    sc.materials[1]["roughness"] = roughness
    glossy = bounce_stage.glossy_triangles(sc)
    got, _ = bounce_stage.choose_bounce_bands(sc, 1, glossy, 5)
    from numpy.polynomial.legendre import leggauss, legval

    from prtt_addon.core.shading.materials import phong_exponent
    s = float(phong_exponent(np.array([roughness]))[0])
    x, w = leggauss(200)
    lobe = (s + 1) / (2 * np.pi) * np.where(x > 0, np.abs(x) ** s, 0.0)   # normalised Phong, cos = x
    A = np.array([2 * np.pi * np.sum(w * lobe * legval(x, np.eye(5)[l])) for l in range(5)])
    want = 1 + max(l for l in range(5) if abs(A[l] / A[0]) >= bounce_stage.AUTO_LOBE_TOLERANCE)
    assert got == want == bands, (got, want, A / A[0])


def _quantize_reference(v: np.ndarray, keep: int) -> np.ndarray:
    """Round float64 values of float16 numbers to ``keep`` mantissa bits, ties
    to even, by arithmetic on the values: the quantum is 2^(e - keep) for a
    normal half of exponent e, 2^(-24 + 10 - keep) for a subnormal one."""
    a = np.abs(v)
    e = np.floor(np.log2(np.where(a > 0, a, 1.0)))
    q = np.where(a >= 2.0 ** -14, 2.0 ** (e - keep), 2.0 ** (-24 + 10 - keep))
    return np.round(v / q) * q                         # np.round: ties to even


@pytest.mark.parametrize("keep", [1, 3, 6, 9, 10])
def test_quantize_half_rounds_every_half_to_nearest_even(keep):
    from prtt_addon.core.io.exr_io import quantize_half
    h = np.arange(1 << 16, dtype=np.uint32).astype(np.uint16).view(np.float16)
    h = h[np.isfinite(h)]
    got = quantize_half(h, keep).astype(np.float64)
    ref = _quantize_reference(h.astype(np.float64), keep)
    fits = np.abs(ref) <= 65504.0                      # rounding past the largest half keeps the value
    assert np.array_equal(got[fits], ref[fits])
    assert np.array_equal(got[~fits], h[~fits].astype(np.float64))
    err, a = np.abs(got - h)[fits], np.abs(h.astype(np.float64))[fits]
    assert np.all(err <= np.where(a >= 2.0 ** -14, 2.0 ** -(keep + 1) * a, 2.0 ** (-15 - keep)))
    with pytest.raises(ValueError):
        quantize_half(h, 0)


def test_tuning_auto_stores_higher_bands_with_six_mantissa_bits(tmp_path):
    """Tuning auto: the transfer's DC channel is fixed's, bit for bit, and
    bands l >= 1 are fixed's rounded to 6 mantissa bits (same rays); bounce
    textures likewise; the header says so; fixed writes all 10 bits as before."""
    import OpenEXR

    from prtt_addon.core.io.exr_io import quantize_half
    sc = corner_scene({"name": "wall", "base_color": [0.9, 0.2, 0.1], "roughness": 0.3}, res=32)
    light = sky()
    out = {}
    for tuning in ("fixed", "auto"):
        d = tmp_path / tuning
        bake_scene(sc, str(d), BakeSettings(rays=32, bounces=1, bounce_rays=16, tuning=tuning,
                                            bounce_mode="baked"), light=light)
        out[tuning] = d
    for name in ("floor", "wall"):
        fx = OpenEXR.File(str(out["fixed"] / f"{name}.transfer.exr"))
        au = OpenEXR.File(str(out["auto"] / f"{name}.transfer.exr"))
        assert au.header()["prtt_mantissa_bits"] == 6 and "prtt_mantissa_bits" not in fx.header()
        fc, ac = fx.channels(), au.channels()
        assert np.array_equal(ac["sh000"].pixels, fc["sh000"].pixels)
        for k in range(1, 25):
            n = f"sh{k:03d}"
            assert np.array_equal(ac[n].pixels.view(np.uint16), quantize_half(fc[n].pixels, 6).view(np.uint16)), n
        b = OpenEXR.File(str(out["auto"] / f"{name}.bounce1.exr"))
        assert b.header()["prtt_mantissa_bits"] == 6
        for n, c in b.channels().items():
            low = c.pixels.view(np.uint16) & 0xF
            assert (n.endswith("sh000") or not low.any()), n


def test_tuning_auto_rounds_relightable_channels_but_the_dc_response(tmp_path):
    """A relightable bounce texture under tuning auto: every channel but the
    out-DC response to the light's DC (``c.dc.i000``) carries no low mantissa
    bits; those three keep all 10 (and use them); fixed writes every bit."""
    import OpenEXR
    sc = corner_scene({"name": "wall", "base_color": [0.9, 0.2, 0.1], "roughness": 0.3}, res=32)
    for tuning in ("fixed", "auto"):
        d = tmp_path / tuning
        m = bake_scene(sc, str(d), BakeSettings(rays=32, bounces=2, bounce_rays=16, tuning=tuning,
                                                bounce_mode="relightable"), light=sky())
        said = {r.get("glossy_colour", "") for r in m["bounce"]["sets"] if r["name"] == "wall"}
        assert said == ({""} if tuning == "fixed" else {"shared: tuning auto stores the glossy rows once, "
                                                        "tinted per colour on reading"})
        f = OpenEXR.File(str(d / "floor.relight.exr"))
        ch = f.channels()
        assert any(".o001." in n for n in ch)                 # the glossy rows are there too
        low = {n: bool((c.pixels.view(np.uint16) & 0xF).any()) for n, c in ch.items()}
        if tuning == "fixed":
            assert "prtt_mantissa_bits" not in f.header() and sum(low.values()) > len(low) // 2
            assert "prtt_glossy_colour" not in f.header() and "R.o001.i000" in ch
        else:
            assert f.header()["prtt_mantissa_bits"] == 6
            # Auto also stores the glossy rows once for all colours.
            assert f.header()["prtt_glossy_colour"] == "shared" and "S.o001.i000" in ch and "R.o001.i000" not in ch
            assert {n for n, v in low.items() if v} == {"R.dc.i000", "G.dc.i000", "B.dc.i000"}
