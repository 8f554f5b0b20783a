"""The sun's mask (issue 48): the visible fraction of the sun's disc per texel
(core/bake/estimators/sun_mask.py, pipeline/sun_stage.py), against the
analytic penumbra of a straight edge, and as the bake writes, reuses and
drops it."""
import math
import os

import numpy as np
import pytest

from prtt_addon.core.bake.estimators.raytrace import RayScene
from prtt_addon.core.bake.estimators.sun_mask import disc_directions, disc_pattern, sun_mask
from prtt_addon.core.light.sun import SUN_RAYS, Sun, SunError


def _segment_visible(offset, radius):
    """Visible fraction of a disc of angular radius ``radius`` whose part beyond
    ``offset`` (signed, along one axis, small angles) is hidden."""
    d = np.clip(offset / radius, -1.0, 1.0)
    hidden = (np.arccos(d) - d * np.sqrt(1.0 - d * d)) / math.pi     # the segment beyond d
    return 1.0 - hidden


def _roof(h=0.5, size=50.0):
    """A horizontal plane at height h over x < 0 (two triangles)."""
    return np.array([[[-size, -size, h], [0.0, -size, h], [0.0, size, h]],
                     [[-size, -size, h], [0.0, size, h], [-size, size, h]]], np.float64)


def test_disc_directions_fill_the_cone_uniformly():
    sun = Sun(direction=(0.3, -0.2, 0.9), angle=math.radians(8.0))
    d = disc_directions(sun.direction, sun.angle, disc_pattern(4096, 3), np.zeros((1, 2)))[0]
    cos = d @ np.asarray(sun.direction)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert cos.min() >= sun.cos_half_angle - 1e-12
    # Uniform in solid angle: cos theta uniform on [cos(a/2), 1].
    u = (1.0 - cos) / (1.0 - sun.cos_half_angle)
    assert abs(u.mean() - 0.5) < 0.01 and abs(np.median(u) - 0.5) < 0.02


@pytest.mark.parametrize("angle_deg", [0.5, 5.0])
def test_penumbra_of_a_straight_edge_is_the_discs_segment(angle_deg):
    """Sun at the zenith, a roof's edge 0.5 m above a floor: the visible
    fraction across the penumbra is the circular segment's (small angles)."""
    h, alpha = 0.5, math.radians(angle_deg) / 2
    x = np.linspace(-1.5, 1.5, 61) * h * math.tan(alpha)
    P = np.stack([x, np.zeros_like(x), np.zeros_like(x)], 1)
    up = np.tile([0.0, 0.0, 1.0], (len(P), 1))
    rs = RayScene(_roof(h))
    got = sun_mask(rs, P, up, np.arange(len(P)), (0.0, 0.0, 1.0), 2 * alpha, rays=4096, seed=1)
    # The edge is seen at angle atan(x / h) from the zenith: the part of the disc beyond it is hidden.
    want = _segment_visible(np.arctan(x / h), alpha)
    assert np.abs(got - want).max() < 0.01, np.abs(got - want).max()
    assert got[0] == 0.0 and got[-1] == 1.0


def test_points_facing_away_see_no_sun_and_threads_do_not_change_the_mask():
    rs = RayScene(_roof())
    rng = np.random.default_rng(2)
    P = rng.uniform(-1, 1, (3000, 3)) * [1, 1, 0]
    n = rng.normal(size=(3000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    args = (rs, P, n, np.arange(3000), (0.0, 0.6, 0.8), math.radians(2.0))
    one = sun_mask(*args, rays=64, seed=5, threads=1, chunk_rays=4096)
    two = sun_mask(*args, rays=64, seed=5, threads=2, chunk_rays=1 << 14)
    assert np.array_equal(one, two)
    assert (one[n @ np.array([0.0, 0.6, 0.8]) < -0.02] == 0).all()
    assert set(np.unique(np.round(one * 64) / 64)) == set(np.unique(one))   # steps of 1 / 64


def test_sun_from_untrusted_json_is_checked():
    ok = Sun.from_dict({"direction": [0, 0, 2], "angle": 0.01, "color": [1, 0.9, 0.8], "strength": 3})
    assert ok.direction == (0.0, 0.0, 1.0)
    for bad, word in [({"angle": 0.01}, "direction"), ({"direction": [0, 0, 0], "angle": 0.01}, "length"),
                      ({"direction": [0, 0, 1], "angle": 1.0}, "angle"),
                      ({"direction": [0, 0, 1], "angle": 0.01, "strength": -1}, "strength"),
                      ({"direction": [0, 0, 1], "angle": 0.01, "color": [1, 1]}, "colour"),
                      ({"direction": [0, 0, 1], "angle": 0.01, "power": 1}, "unknown"), ([1, 2], "object")]:
        with pytest.raises(SunError, match=word):
            Sun.from_dict(bad)
    assert ok.moved_from(ok) is None
    turned = Sun(direction=(0.0, 0.05, 1.0), angle=0.01)
    assert "turned 2.86 degrees" in turned.moved_from(ok)


def test_the_bake_writes_reuses_and_drops_the_masks(tmp_path):
    """With a sun each set gets <set>.sun.exr and the manifest a "sun"; the same
    sun again is skipped, a turned sun bakes again; without a sun the transfer
    is byte-identical to the bake with one, and the masks are gone."""
    from prtt_addon.core.bake.pipeline.context import BakeSettings
    from prtt_addon.core.bake.pipeline.runner import bake_scene
    from prtt_addon.core.io.exr_io import read_mask_exr, read_sh_exr
    from prtt_addon.dev.bench import contact_profile as cp
    sc = cp.build(48)
    st = BakeSettings(rays=32, bounces=0, vertex_mode=False)
    sun = Sun(direction=(0.5, 0.1, 0.8), angle=math.radians(3.0))
    out = str(tmp_path / "b")
    m = bake_scene(sc, out, st, sun=sun)
    assert m["sun"]["files"] == ["floor.sun.exr", "box.sun.exr"] and m["sun"]["rays"] == SUN_RAYS == 256
    mask, attrs = read_mask_exr(os.path.join(out, "floor.sun.exr"))
    assert mask.shape == (48, 48) and 0.0 < mask.mean() < 1.0 and attrs["sun_key"] == m["sun"]["key"]
    t_sun, _ = read_sh_exr(os.path.join(out, "floor.transfer.exr"))
    assert bake_scene(sc, out, st, sun=sun)["skipped"]
    m2 = bake_scene(sc, out, st, sun=Sun(direction=(0.4, 0.1, 0.8), angle=math.radians(3.0)))
    assert not m2["skipped"] and m2["sun"]["key"] != m["sun"]["key"]
    m3 = bake_scene(sc, out, st)
    assert "sun" not in m3 and not any(f.endswith(".sun.exr") for f in m3["files"])
    assert not os.path.exists(os.path.join(out, "floor.sun.exr"))
    t_plain, _ = read_sh_exr(os.path.join(out, "floor.transfer.exr"))
    assert t_plain.tobytes() == t_sun.tobytes()


def test_the_mask_pass_stays_within_its_memory_bound():
    """tracemalloc's peak of a mask pass (numpy's arrays) within
    sun_mask.mask_bytes less its plane (the stage's), at two chunk sizes."""
    import tracemalloc

    from prtt_addon.core.bake.estimators.sun_mask import mask_bytes
    rs = RayScene(_roof())
    rng = np.random.default_rng(3)
    n = 20000
    P = rng.uniform(-1, 1, (n, 3)) * [1, 1, 0]
    up = np.tile([0.0, 0.0, 1.0], (n, 1))
    for chunk in (1 << 14, 1 << 17):
        tracemalloc.start()
        sun_mask(rs, P, up, np.arange(n), (0.3, 0.2, 0.9), math.radians(1.0), rays=64, seed=1, threads=2,
                 chunk_rays=chunk)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        bound = mask_bytes(1, 1, n, 2, chunk, 64)
        assert 0.3 * bound < peak <= bound, (peak, bound)


def test_a_sun_without_shadow_has_a_mask_of_one_and_its_own_key(tmp_path):
    """Blender's Shadow off: the mask is 1 on every texel (nothing traced), the
    key differs from the shadowing sun's, and a shadowing sun's key, JSON and
    mask are what they were before the field existed."""
    from prtt_addon.core.bake.pipeline.context import BakeSettings
    from prtt_addon.core.bake.pipeline.runner import bake_scene
    from prtt_addon.core.io.exr_io import read_mask_exr
    from prtt_addon.dev.bench import contact_profile as cp
    lit = Sun(direction=(0.5, 0.1, 0.8), angle=math.radians(3.0))
    free = Sun(direction=(0.5, 0.1, 0.8), angle=math.radians(3.0), shadow=False)
    assert "shadow" not in lit.as_dict() and "shadow" not in lit.mask_key()
    assert lit.mask_key() == {"direction": [round(v, 12) for v in lit.direction], "angle": round(lit.angle, 12)}
    assert free.as_dict()["shadow"] is False and free.mask_hash() != lit.mask_hash()
    assert Sun.from_dict(free.as_dict()) == free
    assert "Shadow is on, baked off" in lit.moved_from(free)
    with pytest.raises(SunError, match="shadow must be true or false"):
        Sun.from_dict({"direction": [0, 0, 1], "angle": 0.01, "shadow": "no"})
    sc = cp.build(32)
    st = BakeSettings(rays=16, bounces=0, vertex_mode=False)
    m = bake_scene(sc, str(tmp_path / "a"), st, sun=free)
    assert m["sun"]["shadow"] is False
    mask, attrs = read_mask_exr(os.path.join(str(tmp_path / "a"), "floor.sun.exr"))
    assert attrs["sun_shadow"] == 0 and mask.max() == 1.0
    shadowed = read_mask_exr(os.path.join(str(bake_scene(sc, str(tmp_path / "b"), st, sun=lit) and tmp_path / "b"),
                                          "floor.sun.exr"))[0]
    assert shadowed.min() < 0.5                         # the box's shadow: what the unshadowed sun has not
    # every texel the floor covers is 1 (the dilated ring too)
    assert np.all(mask[shadowed > 0] == 1.0)


@pytest.mark.parametrize("bounce_mode", [None, "relightable", "baked"])
def test_a_turned_sun_bakes_its_masks_alone_over_the_transfer(tmp_path, bounce_mode):
    """Only the sun changed: the transfer on disk is reused (not traced again),
    the masks are the very bytes a bake from scratch writes for the new sun;
    a relightable bounce (which holds no sun) is kept as it is, a baked one
    (which holds the sun's bounce) is baked again; a sun that comes or goes
    likewise bakes or removes the masks alone."""
    from prtt_addon.core.bake.pipeline.context import BakeSettings
    from prtt_addon.core.bake.pipeline.runner import bake_scene
    from prtt_addon.core.io.exr_io import read_mask_exr
    from prtt_addon.core.light.envmap import builtin_environment_path, environment_light
    from prtt_addon.dev.bench import contact_profile as cp
    sc = cp.build(32)
    kw = dict(bounces=1, bounce_rays=8, bounce_mode=bounce_mode) if bounce_mode else dict(bounces=0)
    st = BakeSettings(rays=16, vertex_mode=False, **kw)
    light = environment_light(builtin_environment_path("forest"), 5)
    a = Sun(direction=(0.5, 0.1, 0.8), angle=math.radians(3.0))
    b = Sun(direction=(0.2, -0.4, 0.9), angle=math.radians(1.0))
    work, fresh = str(tmp_path / "work"), str(tmp_path / "fresh")
    m1 = bake_scene(sc, work, st, light=light, sun=a)
    m2 = bake_scene(sc, work, st, light=light, sun=b)
    assert m2["transfer_reused"] and not m2["skipped"] and m2["seconds"]["trace"] < m1["seconds"]["trace"]
    for f in m1["transfer_files"]:
        if f.endswith(".transfer.exr"):
            assert m2["file_info"][f] == m1["file_info"][f], f
    m3 = bake_scene(sc, fresh, st, light=light, sun=b)
    for name in ("floor", "box"):
        got = read_mask_exr(os.path.join(work, f"{name}.sun.exr"))[0]
        want = read_mask_exr(os.path.join(fresh, f"{name}.sun.exr"))[0]
        assert got.tobytes() == want.tobytes(), name
    assert [r.get("sun_lit_fraction") for r in m2["sets"]] == [r.get("sun_lit_fraction") for r in m3["sets"]]
    if bounce_mode == "relightable":
        assert m2["bounce"]["files"] == m1["bounce"]["files"]
        assert all(m2["file_info"][f] == m1["file_info"][f] for f in m1["bounce"]["files"])
    elif bounce_mode == "baked":
        assert m2["bounce"]["key"] != m1["bounce"]["key"]
        assert m2["bounce"]["files"] == m3["bounce"]["files"]
    m4 = bake_scene(sc, work, st, light=light)                       # the sun gone
    assert m4["transfer_reused"] and "sun" not in m4 and not any(f.endswith(".sun.exr") for f in m4["files"])
    assert not os.path.exists(os.path.join(work, "floor.sun.exr"))
    assert not any(k.startswith("sun_") for r in m4["sets"] for k in r)
    m5 = bake_scene(sc, work, st, light=light, sun=b)                # and back
    assert m5["transfer_reused"] and m5["sun"]["files"] == m3["sun"]["files"]
    assert bake_scene(sc, work, st, light=light, sun=b)["skipped"]


def test_a_finer_sun_mask_resolves_a_narrow_penumbra_and_bakes_alone(tmp_path):
    """sun_detail f: the mask is f times the set's texels per side over the
    same layout (f² as many), its penumbra across the box's shadow edge f
    times narrower in the set's texels; changing f bakes the masks alone
    (the transfer reused); a mask wider than a texture may be is refused
    before anything is baked."""
    from prtt_addon.core.bake.pipeline.context import BakeSettings
    from prtt_addon.core.bake.pipeline.runner import bake_scene
    from prtt_addon.core.base.errors import BakeError
    from prtt_addon.core.io.exr_io import read_mask_exr
    from prtt_addon.dev.bench import contact_profile as cp
    sc = cp.build(32)
    sun = Sun(direction=(0.5, 0.1, 0.8), angle=math.radians(0.5))
    out = str(tmp_path / "b")
    widths = {}
    for f in (1, 2, 4):
        m = bake_scene(sc, out, BakeSettings(rays=16, bounces=0, vertex_mode=False, sun_detail=f), sun=sun)
        assert m["transfer_reused"] == (f > 1)
        mask, _ = read_mask_exr(os.path.join(out, "floor.sun.exr"))
        assert mask.shape == (32 * f, 32 * f)
        rep = next(r for r in m["sets"] if r["name"] == "floor")
        assert rep.get("sun_detail", 1) == f
        # texels (in the set's texel units) that are neither lit nor shadowed
        widths[f] = float(((mask > 0.05) & (mask < 0.95)).sum()) / f ** 2
    assert widths[2] < 0.7 * widths[1] and widths[4] < 0.7 * widths[2], widths
    big = cp.build(8192)
    with pytest.raises(BakeError, match="over the 16384 a texture may have a side"):
        bake_scene(big, str(tmp_path / "c"), BakeSettings(rays=16, bounces=0, vertex_mode=False, sun_detail=4),
                   sun=sun)
    assert not os.path.exists(os.path.join(str(tmp_path / "c"), "manifest.json"))


def test_the_memory_plan_counts_a_finer_masks_gbuffer():
    """With sun_detail f the trace stage's estimate holds the mask's own
    G-buffer, f² as many texels at GBUFFER_BUILD bytes while it is built."""
    from prtt_addon.core.bake.pipeline.memory_plan import GBUFFER_BUILD, stage_bytes
    sets = [(2048, 2048, 3_000_000)]
    kw = dict(bands=5, dilate=3, n_triangles=100_000, validity=True, sun=True)
    plain = stage_bytes(sets, **kw)["trace"]
    for f in (2, 4):
        fine = stage_bytes(sets, sun_detail=f, **kw)["trace"]
        assert fine >= GBUFFER_BUILD * f * f * 3_000_000 > plain / 2, (f, fine, plain)


class _Counting(RayScene):
    """A RayScene that counts the rays it traces (those with a non-negative tfar)."""
    traced = 0

    def occluded(self, origins, dirs, tfar=None):
        self.traced += int(origins.shape[0] if tfar is None else np.count_nonzero(tfar >= 0))
        return super().occluded(origins, dirs, tfar)


@pytest.mark.parametrize("angle_deg", [0.5, 3.0])
def test_refined_mask_is_the_full_trace_in_penumbrae_for_a_fraction_of_the_rays(angle_deg):
    """sun_mask(grid=...) against every texel tracing all 64 rays, on a floor
    grid under a roof's edge and a pole 3 mm thick (a thin shadow): the
    refined texels are the full trace's bit for bit, the others 0 or 1;
    where the two differ (a penumbra's tails, the pole's shadow where the
    first rays miss it) by at most a quarter of the disc, in under 1 % of
    the texels, at under a third of the rays."""
    W = H = 160
    step = 0.004                                                    # 4 mm texels
    x, y = np.meshgrid((np.arange(W) - W / 2) * step, (np.arange(H) - H / 2) * step)
    P = np.stack([x.ravel(), y.ravel(), np.zeros(W * H)], 1)
    up = np.tile([0.0, 0.0, 1.0], (W * H, 1))
    t = 0.0015                                                      # the pole's half-thickness
    pole = [[[-t, 0.1, 0.0], [t, 0.1, 0.0], [t, 0.1, 0.6]], [[-t, 0.1, 0.0], [t, 0.1, 0.6], [-t, 0.1, 0.6]]]
    tris = np.concatenate([_roof(0.5) + [0.1, 0.0, 0.0], np.array(pole, np.float64)])
    sun = ((0.2, -0.35, 0.9) / np.linalg.norm((0.2, -0.35, 0.9)), math.radians(angle_deg))
    full_rs, refined_rs = _Counting(tris), _Counting(tris)
    ids = np.arange(W * H)
    full = sun_mask(full_rs, P, up, ids, *sun, rays=64, seed=3, threads=2, chunk_rays=1 << 14)
    fine = sun_mask(refined_rs, P, up, ids, *sun, rays=64, seed=3, threads=2, chunk_rays=1 << 14, grid=(W, H))
    penumbra = (full > 0) & (full < 1)
    assert penumbra.sum() > 100                                     # the test has penumbrae to find
    differ = fine != full
    assert np.isin(fine[differ], (0.0, 1.0)).all()                  # a decided texel's value
    assert np.abs(fine - full).max() <= 0.25, np.abs(fine - full).max()
    assert differ.mean() < 0.01, (differ.sum(), penumbra.sum())
    assert refined_rs.traced < full_rs.traced / 3, (refined_rs.traced, full_rs.traced)
    # Threads and chunks do not change it.
    again = sun_mask(RayScene(tris), P, up, ids, *sun, rays=64, seed=3, threads=1, chunk_rays=1 << 12, grid=(W, H))
    assert np.array_equal(again, fine)
