"""Relightable bounces (--bounce-mode relightable): the stored operator shown
under a light equals the baked bounce texture of that light (same rays and
seeds), sums every level into one texture, is linear in the light, and does
not go stale (nor rebake) when only the light changes."""
import json
import os
import sys

import numpy as np
import pytest

from prtt_addon.core.bake.estimators import relightable
from prtt_addon.core.bake.pipeline import relightable_stage
from prtt_addon.core.bake.pipeline.context import BakeSettings
from prtt_addon.core.bake.pipeline.runner import bake_scene
from prtt_addon.core.io import exr_io
from prtt_addon.core.preview.pack import PreviewSet
from prtt_addon.core.sh.rotation import rotate_zyz
from tests.test_bounce import corner_scene, sky

DIFFUSE_WALL = {"name": "wall", "base_color": [0.9, 0.6, 0.3], "specular": 0.0}
DIFFUSE_FLOOR = {"name": "floor", "base_color": [0.5, 0.45, 0.4], "specular": 0.0}
GLOSSY_WALL = {"name": "glossy", "base_color": [0.2, 0.3, 0.9], "roughness": 0.45, "specular": 1.0}


def _scene(wall, res=24):
    sc = corner_scene(wall, res=res)
    sc.materials[0] = DIFFUSE_FLOOR
    return sc


def _settings(**kw):
    kw.setdefault("bounce_mode", "baked")        # the default is relightable: say which side is which
    return BakeSettings(rays=64, bounce_rays=48, half=False, tuning="fixed", seed=7, **kw)


def _relit(out_dir, set_name, light, K):
    s = PreviewSet(set_name, os.path.join(out_dir, f"{set_name}.transfer.exr"),
                   relight=os.path.join(out_dir, f"{set_name}.relight.exr"))
    return s.load_bounce(K, light)


def _baked(out_dir, set_name, levels):
    return sum(exr_io.read_sh_exr(os.path.join(out_dir, f"{set_name}.bounce{k}.exr"))[0]
               for k in range(1, levels + 1))


@pytest.mark.parametrize("levels", [1, 2])
def test_diffuse_relightable_under_L_equals_baked_under_L(tmp_path, levels):
    sc = _scene(DIFFUSE_WALL)
    light = sky()
    K = light.shape[0]
    bk, rl = tmp_path / "baked", tmp_path / "relight"
    bake_scene(sc, str(bk), _settings(bounces=levels), light=light)
    m = bake_scene(sc, str(rl), _settings(bounces=levels, bounce_mode="relightable"), light=light)
    assert m["bounce"]["mode"] == "relightable" and m["bounce"]["light_hash"] is None
    assert sorted(m["bounce"]["files"]) == ["floor.relight.exr", "wall.relight.exr"]
    assert not any(".bounce" in f for f in os.listdir(rl))     # N levels, one texture per set
    for name in ("floor", "wall"):
        baked = _baked(str(bk), name, levels)
        relit = _relit(str(rl), name, light, K)
        dc = relit[..., 0]
        assert np.abs(dc).max() > 0.01                      # light does bounce here
        # Diffuse receivers read the DC term alone; it is exact (no glossy rows stored).
        np.testing.assert_allclose(dc, baked[..., 0], rtol=0, atol=2e-5 * np.abs(baked[..., 0]).max())
        assert not np.any(relit[..., 1:])


def test_glossy_relightable_with_all_bands_equals_baked(tmp_path, monkeypatch):
    """With the glossy part at the bake's bands (no band limit) every
    coefficient of the glossy wall's and the floor's bounce light matches."""
    monkeypatch.setattr(relightable_stage, "GLOSSY_BANDS", 5)
    sc = _scene(GLOSSY_WALL, res=16)
    light = sky()
    K = light.shape[0]
    bake_scene(sc, str(tmp_path / "b"), _settings(bounces=2), light=light)
    bake_scene(sc, str(tmp_path / "r"), _settings(bounces=2, bounce_mode="relightable"), light=light)
    _, _, attrs = exr_io.read_relight_exr(str(tmp_path / "r" / "wall.relight.exr"))
    assert attrs["glossy_bands"] == 5
    for name in ("floor", "wall"):
        baked = _baked(str(tmp_path / "b"), name, 2)
        relit = _relit(str(tmp_path / "r"), name, light, K)
        scale = np.abs(baked).max()
        if name == "wall":
            np.testing.assert_allclose(relit, baked, rtol=0, atol=5e-5 * scale)
        else:                                                # a diffuse set keeps the DC row
            np.testing.assert_allclose(relit[..., 0], baked[..., 0], rtol=0, atol=5e-5 * scale)


def test_band_limited_glossy_rows_hold_bands_0_to_2(tmp_path):
    sc = _scene(GLOSSY_WALL, res=16)
    light = sky()
    bake_scene(sc, str(tmp_path), _settings(bounces=1, bounce_mode="relightable"), light=light)
    dc, gl, attrs = exr_io.read_relight_exr(str(tmp_path / "wall.relight.exr"))
    assert attrs["kind"] == "relight" and attrs["glossy_bands"] == relightable.GLOSSY_BANDS == 3
    assert dc.shape[2:] == (3, 25) and gl.shape[2:] == (3, 8, 9)
    _, gl_floor, _ = exr_io.read_relight_exr(str(tmp_path / "floor.relight.exr"))
    assert gl_floor is None                                   # diffuse: no glossy rows


def test_relight_texture_records_the_rays_it_traced(tmp_path):
    """Under tuning auto a coarse bounce grid traces 1.5x the bounce rays per
    texel: the header says what was traced, as the baked levels' do."""
    sc = _scene(GLOSSY_WALL, res=32)
    m = bake_scene(sc, str(tmp_path), BakeSettings(rays=64, bounce_rays=48, half=False, seed=7, bounces=1,
                                                   tuning="auto", bounce_mode="relightable"), light=sky())
    for r in m["bounce"]["sets"]:
        _, _, attrs = exr_io.read_relight_exr(str(tmp_path / f"{r['name']}.relight.exr"))
        assert attrs["rays"] == r["rays"] == r.get("grid", {}).get("rays", 48)
    assert any(r["rays"] == 72 for r in m["bounce"]["sets"])


def test_relit_bounce_is_linear_in_the_light(tmp_path):
    sc = _scene(GLOSSY_WALL, res=16)
    bake_scene(sc, str(tmp_path), _settings(bounces=2, bounce_mode="relightable"), light=None)
    L1 = sky()
    K = L1.shape[0]
    # A second, different light: the sky turned 90 degrees about Z and tinted.
    L2 = rotate_zyz(L1.T, np.full(3, np.pi / 2), np.zeros(3), np.zeros(3)).T * np.array([0.3, 1.0, 2.0])
    for name in ("floor", "wall"):
        a = _relit(str(tmp_path), name, L1, K)
        b = _relit(str(tmp_path), name, L2, K)
        ab = _relit(str(tmp_path), name, 0.7 * L1 - 1.9 * L2, K)
        np.testing.assert_allclose(ab, 0.7 * a - 1.9 * b, rtol=0, atol=1e-5 * np.abs(ab).max())
        assert np.abs(a - b).max() > 0.05 * np.abs(a).max()   # the light matters


def test_light_change_keeps_relightable_bounces_and_rebakes_baked_ones(tmp_path):
    sc = _scene(DIFFUSE_WALL, res=16)
    L1 = sky()
    L2 = 2.0 * L1
    rl, bk = str(tmp_path / "r"), str(tmp_path / "b")
    m1 = bake_scene(sc, rl, _settings(bounces=1, bounce_mode="relightable"), light=L1)
    m2 = bake_scene(sc, rl, _settings(bounces=1, bounce_mode="relightable"), light=L2)
    assert m2.get("skipped") and m2["bounce"]["key"] == m1["bounce"]["key"]
    b1 = bake_scene(sc, bk, _settings(bounces=1), light=L1)
    b2 = bake_scene(sc, bk, _settings(bounces=1), light=L2)
    assert not b2.get("skipped") and b2["bounce"]["key"] != b1["bounce"]["key"]
    # Switching mode replaces the levels by the relightable texture (and back).
    m3 = bake_scene(sc, bk, _settings(bounces=1, bounce_mode="relightable"), light=L2)
    assert m3["transfer_reused"] and not any(".bounce" in f for f in os.listdir(bk))
    bake_scene(sc, bk, _settings(bounces=1), light=L2)
    assert not any(f.endswith(".relight.exr") for f in os.listdir(bk))
    with open(os.path.join(bk, "manifest.json"), encoding="utf-8") as f:
        assert "mode" not in json.load(f)["bounce"]          # baked manifests as before


def test_relightable_bakes_without_a_light_and_refuses_denoising(tmp_path):
    sc = _scene(DIFFUSE_WALL, res=16)
    m = bake_scene(sc, str(tmp_path / "a"), _settings(bounces=1, bounce_mode="relightable"), light=None)
    assert m["bounce"]["files"] and not m.get("warnings")
    from prtt_addon.core.base.errors import BakeError
    with pytest.raises(BakeError, match="relightable"):
        bake_scene(sc, str(tmp_path / "b"), _settings(bounces=1, bounce_mode="relightable",
                                                      bounce_denoise="edge-aware"), light=None)


@pytest.mark.parametrize("header", [{"glossy_bands": 100000}, {"bands": 10**6}, {"bands": "five"}])
def test_forged_band_counts_are_refused_before_listing_channels(tmp_path, header):
    """A texture's header is untrusted: a band count beyond the bake's limit is
    a clear error, not a list of 10^10 channel names."""
    import OpenEXR
    path = str(tmp_path / "forged.relight.exr")
    attrs = {"kind": "relight", "bands": 5, "glossy_bands": 0, **header}
    exr_io.write_sh_planes(path, np.zeros((75, 4, 4), np.float32), kind="relight", rgb=False,
                           names=exr_io.relight_channel_names(25), bands=5)
    with OpenEXR.File(path) as f:
        h = dict(f.header())
        chans = {n: np.array(c.pixels) for n, c in f.channels().items()}
    h.update({f"prtt_{k}": v for k, v in attrs.items()})
    with OpenEXR.File(h, chans) as f:
        f.write(path)
    with pytest.raises(exr_io.TextureError, match="is not a band count"):
        exr_io.read_relight_exr(path)
    if "bands" in header:
        with pytest.raises(exr_io.TextureError, match="is not a band count"):
            exr_io.read_sh_exr(path)


@pytest.mark.parametrize("scene,shared", [("corner", False), ("ball", False), ("ball", True)])
def test_compiled_relight_projection_equals_the_numpy_path(tmp_path, monkeypatch, scene, shared):
    """The relightable operator from the compiled loop that shades and
    projects each hit (numba, hit_jit.relight_project) equals the numpy
    path's to float32 rounding, for two levels (level 1: one form for all
    colours; level 2: one per colour) of glossy and diffuse sets, flat ones
    (one frame per chunk) and a ball (a frame per texel), with glossy rows per
    colour and shared; the manifest says which path ran."""
    from prtt_addon.core.base import jit
    from prtt_addon.dev.bench.relight_bench import ball_scene
    assert jit.available(), "numba is pinned in requirements.txt"
    monkeypatch.setattr(relightable_stage, "relight_shared_colour", lambda st: shared)
    sc = _scene(GLOSSY_WALL, res=16) if scene == "corner" else ball_scene(32)[0]
    paths = {}
    for path, off in (("compiled", "0"), ("numpy", "1")):
        monkeypatch.setenv("PRTT_NO_NUMBA", off)
        m = bake_scene(sc, str(tmp_path / path), _settings(bounces=2, bounce_mode="relightable"), light=sky())
        assert {r["hit_shading"] for r in m["bounce"]["sets"]} == {path}
        paths[path] = tmp_path / path
    for name in (("floor", "wall") if scene == "corner" else ("floor", "ball", "box")):
        a = exr_io.read_relight_exr(str(paths["compiled"] / f"{name}.relight.exr"))
        b = exr_io.read_relight_exr(str(paths["numpy"] / f"{name}.relight.exr"))
        for x, y in zip(a[:2], b[:2]):
            if y is None:
                assert x is None
                continue
            scale = np.abs(y).max()
            assert scale > 0
            np.testing.assert_allclose(x, y, rtol=0, atol=2e-6 * scale)


def test_local_to_world_shared_frame_equals_per_texel_frames():
    """ChunkHits.local_to_world of a shared-frame chunk (one rotation matrix)
    equals the per-texel rotation of the same frame, and to_world(rows) equals
    local_to_world(rows @ table), both ways."""
    from prtt_addon.core.bake.estimators.bounce import ChunkHits
    from prtt_addon.core.bake.estimators.transfer import ChunkFrames
    rng = np.random.default_rng(3)
    n, per, S, kg = 5, 4, 16, 9
    a, b, g = rng.uniform(0, 2 * np.pi), rng.uniform(0, np.pi), rng.uniform(0, 2 * np.pi)
    z3, zb = np.zeros((n, 3), np.float32), np.zeros(n, bool)

    def hits(shared):
        fr = ChunkFrames(np.full(n, a), np.full(n, b), np.full(n, g), np.zeros((n, 3, 3), np.float32), z3, z3, zb,
                         shared=shared)
        return ChunkHits(np.arange(n), S, np.zeros((n * S, 3), np.float32), np.zeros(0, np.int64),
                         np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros(0, np.float32),
                         rng.standard_normal((S, 25)).astype(np.float32), fr)

    sh, pt = hits(True), hits(False)
    pt.table = sh.table
    local = rng.standard_normal((n * per, kg)).astype(np.float32)
    np.testing.assert_allclose(sh.local_to_world(local, kg, per), pt.local_to_world(local, kg, per), atol=2e-5)
    rows = rng.standard_normal((n * per, S)).astype(np.float32)
    for h in (sh, pt):
        np.testing.assert_allclose(h.to_world(rows, kg, per), h.local_to_world(rows @ h.table[:, :kg], kg, per),
                                   rtol=1e-4, atol=1e-4)
    # A real rotation: the per-texel path moves coefficients of band 1 and 2.
    assert not np.allclose(pt.local_to_world(local, kg, per)[:, 1:], local[:, 1:], atol=1e-2)
    # Distinct frames per texel: each texel's rows turned by its own rotation.
    pt.fr.alpha, pt.fr.beta, pt.fr.gamma = (rng.uniform(0, 3, n) for _ in range(3))
    rep = lambda v: np.repeat(v, per)  # noqa: E731
    from prtt_addon.core.sh.rotation import rotate_zyz
    want = rotate_zyz(local.astype(np.float64), rep(pt.fr.alpha), rep(pt.fr.beta), rep(pt.fr.gamma))
    np.testing.assert_allclose(pt.local_to_world(local, kg, per), want, atol=2e-5)
    np.testing.assert_allclose(pt.to_world(rows, kg, per), pt.local_to_world(rows @ pt.table[:, :kg], kg, per),
                               rtol=1e-4, atol=1e-4)


GREY_FLOOR = {"name": "floor", "base_color": [0.5, 0.5, 0.5], "specular": 0.0}
GREY_GLOSSY = {"name": "glossy", "base_color": [0.6, 0.6, 0.6], "roughness": 0.45, "specular": 1.0}
# With GLOSSY_WALL, each set sees a diffuse and a specular colour, so its glossy rows differ per colour.
GLOSSY_FLOOR = {"name": "floor", "base_color": [0.8, 0.5, 0.2], "roughness": 0.4, "specular": 0.8}


def _bake_both(tmp_path, monkeypatch, sc, levels):
    """(per-colour folder, shared folder) of the same relightable bake."""
    out = {}
    for shared in (False, True):
        monkeypatch.setattr(relightable_stage, "relight_shared_colour", lambda st, v=shared: v)
        out[shared] = tmp_path / ("shared" if shared else "per-colour")
        bake_scene(sc, str(out[shared]), _settings(bounces=levels, bounce_mode="relightable"), light=sky())
    return out[False], out[True]


def test_shared_colour_glossy_rows_are_exact_off_grey_surfaces(tmp_path, monkeypatch):
    """Light that bounced off grey surfaces only has the same glossy rows in
    every colour, so the shared rows (one set, tinted back by the DC
    response) equal the per-colour ones and, at full bands, the baked bounce
    texture, for two levels (level 2 reads the shared rows of level 1)."""
    monkeypatch.setattr(relightable_stage, "GLOSSY_BANDS", 5)
    sc = _scene(GREY_GLOSSY, res=16)
    sc.materials[0] = GREY_FLOOR
    light = sky()
    per, shared = _bake_both(tmp_path, monkeypatch, sc, 2)
    bake_scene(sc, str(tmp_path / "b"), _settings(bounces=2), light=light)
    import OpenEXR
    with OpenEXR.File(str(shared / "wall.relight.exr")) as f:
        names, header = set(f.channels()), dict(f.header())
    assert header["prtt_glossy_colour"] == "shared"
    assert header["compression"] == OpenEXR.PIZ_COMPRESSION      # exr_io.compression_of
    assert "S.o001.i000" in names and not any(n.startswith("R.o") for n in names)
    assert len(names) == 3 * 25 + 24 * 25
    with OpenEXR.File(str(per / "wall.relight.exr")) as f:
        assert "prtt_glossy_colour" not in f.header()
    a, b = exr_io.read_relight_exr(str(per / "wall.relight.exr")), exr_io.read_relight_exr(str(shared / "wall.relight.exr"))
    assert b[1].shape == a[1].shape
    np.testing.assert_allclose(b[1], a[1], rtol=0, atol=1e-5 * np.abs(a[1]).max())
    baked = _baked(str(tmp_path / "b"), "wall", 2)
    np.testing.assert_allclose(_relit(str(shared), "wall", light, 25), baked, rtol=0,
                               atol=5e-5 * np.abs(baked).max())


def test_shared_colour_glossy_rows_keep_the_colour_mean_and_the_dc_rows(tmp_path, monkeypatch):
    """Off coloured surfaces the shared rows are an approximation, but the DC
    rows are the per-colour bake's bit for bit (one level), and the colours'
    mean of the tinted rows is the per-colour rows' mean (the tints average
    to one)."""
    sc = _scene(GLOSSY_WALL, res=16)
    # A glossy floor too: each set sees a diffuse and a specular colour, so its rows differ per colour.
    sc.materials[0] = GLOSSY_FLOOR
    per, shared = _bake_both(tmp_path, monkeypatch, sc, 1)
    for name in ("floor", "wall"):
        a = exr_io.read_relight_exr(str(per / f"{name}.relight.exr"))
        b = exr_io.read_relight_exr(str(shared / f"{name}.relight.exr"))
        np.testing.assert_array_equal(b[0], a[0])
        scale = np.abs(a[1]).max()
        np.testing.assert_allclose(b[1].mean(axis=2), a[1].mean(axis=2), rtol=0, atol=1e-5 * scale)
        assert np.abs(b[1] - a[1]).max() > 1e-2 * scale          # the colours do differ here


def test_expand_shared_glossy_tints_by_the_dc_response():
    dc = np.zeros((3, 3, 25), np.float32)
    dc[0, :, 0] = (0.3, 0.6, 0.9)                            # tints 0.5, 1, 1.5
    dc[2, :, 0] = (1.0, -1.0, 1e-6)                          # signs that cancel: no tint, not 1e6
    S = np.arange(3 * 8 * 9, dtype=np.float32).reshape(3, 8, 9)
    out = exr_io.expand_shared_glossy(dc, S)
    assert out.dtype == np.float32 and out.shape == (3, 3, 8, 9)
    np.testing.assert_allclose(out[0], np.array([0.5, 1.0, 1.5])[:, None, None] * S[0], rtol=1e-6)
    np.testing.assert_array_equal(out[1], np.broadcast_to(S[1], (3, 8, 9)))   # no DC response: untinted
    np.testing.assert_array_equal(out[2], np.broadcast_to(S[2], (3, 8, 9)))


def test_the_next_level_reads_the_tinted_shared_rows(tmp_path, monkeypatch):
    """Level 2's glossy exit gets level 1's shared rows tinted per colour by
    level 1's own DC response (coloured surfaces, so the tint is not 1)."""
    sc = _scene(GLOSSY_WALL, res=16)
    sc.materials[0] = GLOSSY_FLOOR
    seen = []
    real = relightable_stage.later_exit

    def spy(surf, rows, glossy_bands):
        seen.append(rows)
        return real(surf, rows, glossy_bands)

    monkeypatch.setattr(relightable_stage, "relight_shared_colour", lambda st: True)
    monkeypatch.setattr(relightable_stage, "later_exit", spy)
    bake_scene(sc, str(tmp_path), _settings(bounces=2, bounce_mode="relightable"), light=sky())
    glossy = [r for r in seen if r.glossy is not None]
    assert glossy
    for rows in glossy:
        S = rows.glossy.mean(axis=1)                        # the shared rows (the tints average to one)
        np.testing.assert_allclose(rows.glossy, exr_io.expand_shared_glossy(rows.dc, S), rtol=1e-5,
                                   atol=1e-6 * np.abs(rows.glossy).max())
        d0 = rows.dc[:, :, 0]
        assert np.abs(d0 / d0.mean(axis=1, keepdims=True) - 1).max() > 0.05    # really tinted


def test_an_unknown_glossy_colour_layout_is_refused(tmp_path):
    path = str(tmp_path / "x.relight.exr")
    names = exr_io.relight_channel_names(4, 4, shared=True)
    exr_io.write_sh_planes(path, np.zeros((len(names), 2, 2), np.float32), kind="relight", half=False, names=names,
                           bands=2, attrs={"glossy_bands": 2, "glossy_colour": "shared"})
    dc, gl, _ = exr_io.read_relight_exr(path)
    assert dc.shape == (2, 2, 3, 4) and gl.shape == (2, 2, 3, 3, 4)
    exr_io.write_sh_planes(path, np.zeros((len(names), 2, 2), np.float32), kind="relight", half=False, names=names,
                           bands=2, attrs={"glossy_bands": 2, "glossy_colour": "mono"})
    with pytest.raises(exr_io.TextureError, match="glossy_colour 'mono'"):
        exr_io.read_relight_exr(path)


def test_vector_intrinsics_equal_numpy():
    """hit_jit's LLVM vector operations (axpy, rows_combine, outer_acc) against
    numpy in float64, at offsets inside longer arrays and for the lengths the
    relightable loops use (9, 16, 25, 36), neighbours untouched."""
    from prtt_addon.core.base import jit
    assert jit.available(), "numba is pinned in requirements.txt"
    import numba

    from prtt_addon.core.bake.estimators.hit_jit import axpy, outer_acc, rows_combine

    @numba.njit
    def run(dst, src, y, x, tile, big, a):
        axpy(dst, 3, src, 5, a, 25)
        axpy(dst, 40, src, 1, a, 9)
        axpy(dst, 60, src, 2, a, 16)
        axpy(dst, 80, src, 0, a, 36)
        rows_combine(x, big, 7, y, 9, 9)
        outer_acc(dst, 120, x, tile, 4, 9)

    rng = np.random.default_rng(3)
    dst, src = rng.standard_normal(220).astype(np.float32), rng.standard_normal(60).astype(np.float32)
    y, x = rng.standard_normal(9).astype(np.float32), np.zeros(9, np.float32)
    tile, big = rng.standard_normal(90).astype(np.float32), rng.standard_normal(100).astype(np.float32)
    a = np.float32(0.7)
    want = dst.astype(np.float64)
    for off, soff, n in ((3, 5, 25), (40, 1, 9), (60, 2, 16), (80, 0, 36)):
        want[off:off + n] += float(a) * src[soff:soff + n].astype(np.float64)
    xw = y.astype(np.float64) @ big[7:88].astype(np.float64).reshape(9, 9)
    want[120:201] += (xw[:, None] * tile[4:85].astype(np.float64).reshape(9, 9)).ravel()
    run(dst, src, y, x, tile, big, a)
    np.testing.assert_allclose(x, xw, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(dst, want, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("bands", [3, 4, 6])
def test_band_specialised_relight_loops_equal_the_numpy_path(tmp_path, monkeypatch, bands):
    """Level 1's vector loop is compiled once per transfer band count
    (hit_jit.LEVEL1_BY_BANDS); each equals the numpy path to float32
    rounding (the default 5 bands: test_compiled_relight_projection_equals_the_numpy_path)."""
    from prtt_addon.core.bake.estimators import hit_jit
    assert hit_jit.relight_for(bands, 3, True) is hit_jit.LEVEL1_BY_BANDS[bands]
    sc = _scene(GLOSSY_WALL, res=12)
    out = {}
    for path, off in (("compiled", "0"), ("numpy", "1")):
        monkeypatch.setenv("PRTT_NO_NUMBA", off)
        m = bake_scene(sc, str(tmp_path / path), _settings(bands=bands, bounces=1, bounce_mode="relightable"),
                       light=sky(bands))
        assert {r["hit_shading"] for r in m["bounce"]["sets"]} == {path}
        out[path] = exr_io.read_relight_exr(str(tmp_path / path / "wall.relight.exr"))
    for x, y in zip(out["compiled"][:2], out["numpy"][:2]):
        scale = np.abs(y).max()
        assert scale > 0
        np.testing.assert_allclose(x, y, rtol=0, atol=2e-6 * scale)


@pytest.mark.parametrize("rows", [5, 1000, 1001, 1063, 1064, 4100])
def test_the_glossy_table_made_in_blocks_is_the_one_product_and_consumes_its_input(monkeypatch, rows):
    """transfer_product_rows in blocks of rows (a short last block joined to the
    one before: numpy multiplies a single row by another BLAS routine) gives
    the one whole product's bits; ``consume`` gives the input's pages back as
    it goes (#35: the block means and the table are not both whole)."""
    monkeypatch.setattr(relightable, "EXIT_BLOCK", 1000)
    rng = np.random.default_rng(rows)
    T = (rng.standard_normal((rows, 25)) * np.geomspace(1.0, 1e-3, 25)).astype(np.float32)
    whole = relightable.transfer_product_rows(T, 9)
    assert relightable.row_blocks(rows, 1000)[-1][1] == rows
    assert all(b - a >= min(rows, relightable.MIN_TAIL_ROWS) for a, b in relightable.row_blocks(rows, 1000))
    out = np.empty((rows, 9, 9), np.float32)
    relightable.transfer_product_rows(T, 9, out=out)
    assert out.tobytes() == whole.tobytes()
    # Blocks of 1 MB: at most a page at each block's ends stays behind.
    monkeypatch.setattr(relightable, "EXIT_BLOCK", 10000)
    big = np.ascontiguousarray(np.tile(T, (-(-40000 // rows), 1)))
    want = relightable.transfer_product_rows(big, 9)
    out = np.empty((big.shape[0], 9, 9), np.float32)
    relightable.transfer_product_rows(big, 9, out=out, consume=True)
    assert out.tobytes() == want.tobytes()
    if sys.platform.startswith("linux"):          # madvise zeroes given-back pages there
        assert np.count_nonzero(big) < 0.05 * big.size
