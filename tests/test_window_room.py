"""The window-lit room's measurement (bench/window_room.py, issue 53 item 1):
the scene is closed (light reaches the inside only through the window), the
reference is converged far below the bake's noise, and the measure sees the
noise fall with rays and with a denoiser."""
import numpy as np


def test_only_the_window_lets_light_in():
    """Rays from the room's centre escape exactly through the window's solid
    angle: every escaping ray leaves through the window's rectangle."""
    from prtt_addon.core.bake.estimators.raytrace import RayScene
    from prtt_addon.dev.bench import window_room as wr
    sc = wr.build(128)
    rs = RayScene(np.asarray(sc.positions, np.float64))
    rng = np.random.default_rng(0)
    d = rng.normal(size=(20000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.tile([0.0, 0.0, 1.3], (len(d), 1))
    escape = ~rs.occluded(rs.to_local(o), d.astype(np.float32))     # origins in Embree's normalised frame
    # Where an escaping ray crosses the +y wall's plane (y = 2).
    t = (wr.ROOM[1] / 2 - o[escape, 1]) / d[escape, 1]
    x, z = o[escape, 0] + t * d[escape, 0], o[escape, 2] + t * d[escape, 2]
    ww, wh, sill = wr.WINDOW
    assert escape.sum() > 50
    assert np.all(d[escape, 1] > 0)
    assert np.all((np.abs(x) <= ww / 2 + 1e-6) & (z >= sill - 1e-6) & (z <= sill + wh + 1e-6))


def test_the_error_falls_with_rays_and_with_a_denoiser():
    from prtt_addon.dev.bench import window_room as wr
    # The guided texels as traced (--no-guided-filter), so that the denoiser has their noise to remove.
    r = wr.measure(256, rays=(64, 1024), ref_rays=16384, ref_texels=600, denoisers=("none", "edge-aware:2"),
                   settings=dict(guided_filter=False, texel_validity=False))
    by = {(x["rays"], x["denoiser"]): x for x in r["rows"]}
    raw64, raw1024 = by[(64, "none")]["mean"], by[(1024, "none")]["mean"]
    assert raw1024 < 0.5 * raw64, (raw64, raw1024)
    assert by[(64, "edge-aware:2")]["mean"] < 0.7 * raw64, r["rows"]
    assert by[(1024, "none")]["texels"] > 200


def test_the_default_bake_smooths_the_guided_texels():
    """The defaults (texel validity and the guided texels' filter,
    guided_filter.py) against the same bake without either: the error falls
    by more than a third (512², 256 rays, 2,000 texels: 6.26 % -> 2.98 %;
    here 256², 600 texels), and the p99 with it."""
    from prtt_addon.dev.bench import window_room as wr
    on = wr.measure(256, rays=(256,), ref_rays=16384, ref_texels=600)["rows"][0]
    off = wr.measure(256, rays=(256,), ref_rays=16384, ref_texels=600,
                     settings=dict(guided_filter=False, texel_validity=False))["rows"][0]
    assert on["mean"] < 0.65 * off["mean"], (on, off)
    assert on["p99"] < off["p99"], (on, off)
