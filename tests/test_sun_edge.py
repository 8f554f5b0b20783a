"""Sub-texel shadow edges of a sharp sun (issue 48;
core/bake/estimators/sun_edge.py): drawn through the preview's lookup
(bilinear (mask, d, valid, h), then sun_edge.visible, the twin of
prtt_shade.glsl sun_visible) against the analytic penumbra of a straight
roof edge at sub-texel points; what the bake writes, reuses and drops; and
the bake without them, byte for byte the one before them."""
import math
import os

import numpy as np

from prtt_addon.core.bake.estimators.raytrace import RayScene
from prtt_addon.core.bake.estimators.sun_edge import WIDE, profile, sun_edges, visible
from prtt_addon.core.bake.estimators.sun_mask import sun_mask
from prtt_addon.core.light.sun import Sun
from prtt_addon.core.texels.texsample import bilinear

W = H = 48
SIZE, HEIGHT = 1.0, 0.5                                # floor side and roof height (m)
THETA = math.radians(20.0)                             # the roof's edge, turned off the texel grid
TOWARDS = np.array([0.3, -0.2, 0.93]) / np.linalg.norm([0.3, -0.2, 0.93])


def _roof():
    """A plane at HEIGHT over the half-plane x.e < 0 (e at THETA): (tris, e, u)."""
    e = np.array([math.cos(THETA), math.sin(THETA), 0.0])
    u = np.array([-e[1], e[0], 0.0])
    c = [p + [0.0, 0.0, HEIGHT] for p in (-50 * e - 50 * u, -50 * u, 50 * u, -50 * e + 50 * u)]
    return np.array([[c[0], c[1], c[2]], [c[0], c[2], c[3]]]), e, u


def _analytic(P, alpha, e, u):
    """Visible fraction of a uniform disc of angular radius alpha around
    TOWARDS at floor points P behind the roof's edge line {t u + HEIGHT z}:
    the circular segment beyond the plane through P and that line."""
    a = np.array([0.0, 0.0, HEIGHT]) - P
    nrm = np.cross(a, np.broadcast_to(u, a.shape))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm *= np.sign(nrm @ e)[:, None]                   # towards the open side
    s = np.clip(np.arcsin(np.clip(nrm @ TOWARDS, -1, 1)) / alpha, -1, 1)
    return 1.0 - (np.arccos(s) - s * np.sqrt(1 - s * s)) / math.pi


def _floor():
    """Texel centres of a W x H floor under the roof's shadow edge (row 0 at the bottom)."""
    shift = HEIGHT * TOWARDS[:2] / TOWARDS[2]
    xs = (np.arange(W) + 0.5) / W * SIZE - SIZE / 2
    X, Y = np.meshgrid(xs, xs)
    P = np.stack([X.ravel() + shift[0], Y.ravel() + shift[1], np.zeros(W * H)], 1)
    return P, np.tile([0.0, 0.0, 1.0], (W * H, 1)), shift


def _drawn(angle):
    """(with edges, the mask alone, analytic) at 20000 sub-texel points, and the edges."""
    tris, e, u = _roof()
    rs = RayScene(tris)
    P, N, shift = _floor()
    texel = np.arange(W * H)
    mask = sun_mask(rs, P, N, texel, TOWARDS, angle, rays=64, seed=1)
    edges, counts = sun_edges(rs, P, N, texel, W, H, mask, TOWARDS, angle)
    uv = np.random.default_rng(3).uniform(1.0 / W, 1 - 1.0 / W, (20000, 2))
    Q = np.stack([uv[:, 0] * SIZE - SIZE / 2 + shift[0], uv[:, 1] * SIZE - SIZE / 2 + shift[1],
                  np.zeros(len(uv))], 1)
    # the halves the preview uploads, in its channel order
    tex = np.stack([mask, edges[:, 0], edges[:, 2], edges[:, 1]], 1).astype(np.float16).astype(np.float32)
    f = bilinear(np.ascontiguousarray(tex), W, H, uv)
    return visible(f), f[:, 0], _analytic(Q, angle / 2, e, u), edges, counts


def test_profile_is_the_discs_segment():
    """profile(s) against the segment's area by quadrature (scipy-free:
    a fine midpoint sum over the disc's chords)."""
    y = (np.arange(200000) + 0.5) / 200000 * 2 - 1
    chord = 2 * np.sqrt(1 - y * y)
    for s in (-1.0, -0.6, -0.1, 0.0, 0.3, 0.9, 1.0):
        lit = (chord * (y < s)).sum() * (2 / y.size) / math.pi    # the disc's part below the line y = s
        assert abs(profile(s) - lit) < 1e-6, s
    assert profile(-5.0) == 0.0 and profile(5.0) == 1.0


def test_a_sharp_suns_edge_is_drawn_where_it_is():
    """0.5 degree sun, 48 texels a metre: its penumbra is 5 mm, a tenth of a
    texel. The mask alone draws the edge a texel wide; with the edges the
    drawn fraction is the analytic one to a few thousandths."""
    got, plain, want, edges, counts = _drawn(math.radians(0.5))
    rmse = float(np.sqrt(((got - want) ** 2).mean()))
    before = float(np.sqrt(((plain - want) ** 2).mean()))
    print(f"0.5 deg: RMSE with edges {rmse:.4f}, mask alone {before:.4f}, {counts}")
    assert counts["crossings"] > 40 and counts["edge_texels"] > 200
    assert rmse < 0.003 and rmse < before / 10, (rmse, before)
    assert (edges[:, 1] < WIDE).all()


def test_a_wide_penumbra_is_left_to_the_mask():
    """5 degrees: the penumbra is wider than a texel; no texel near the edge
    takes the line (valid 0 there) and the drawing is the mask's."""
    got, plain, want, edges, counts = _drawn(math.radians(5.0))
    partial = (edges[:, 2] < 1.0)
    P, _, _ = _floor()
    tris, e, u = _roof()
    pen = np.abs(_analytic(P, math.radians(2.5), e, u) - 0.5) < 0.45       # texels inside the penumbra
    assert partial[pen].all() and counts["edge_texels"] == 0
    assert np.array_equal(got, plain)


def test_the_edges_are_a_function_of_the_mask_and_the_scene():
    """Twice, and with the other core busy tracing: the same bytes."""
    import threading
    tris, _, _ = _roof()
    P, N, _ = _floor()
    texel = np.arange(W * H)
    angle = math.radians(0.5)
    mask = sun_mask(RayScene(tris), P, N, texel, TOWARDS, angle, rays=64, seed=1)
    first = sun_edges(RayScene(tris), P, N, texel, W, H, mask, TOWARDS, angle)[0]
    busy = threading.Thread(target=lambda: sun_mask(RayScene(tris), P, N, texel, TOWARDS, angle, rays=1024, seed=2))
    busy.start()
    again = sun_edges(RayScene(tris), P, N, texel, W, H, mask, TOWARDS, angle)[0]
    busy.join()
    assert first.tobytes() == again.tobytes()


def _bake(sc, out, sun, **kw):
    from prtt_addon.core.bake.pipeline.context import BakeSettings
    from prtt_addon.core.bake.pipeline.runner import bake_scene
    return bake_scene(sc, str(out), BakeSettings(rays=16, bounces=0, vertex_mode=False, **kw), sun=sun)


def test_the_bake_writes_the_edges_and_without_them_the_files_before_them(tmp_path):
    """Default: <set>.sun_edge.exr beside each mask, named in the manifest's
    sun entry and the report; the same sun again is skipped. --no-sun-edges:
    no edge file, no "edge_files", a different key, and the masks and
    transfer byte-identical to the bake with edges (the edges read the mask,
    never change it)."""
    from prtt_addon.core.io.exr_io import read_edge_exr, read_mask_exr
    from prtt_addon.dev.bench import contact_profile as cp
    sc = cp.build(48)
    sun = Sun(direction=(0.5, 0.1, 0.8), angle=math.radians(0.5))
    m = _bake(sc, tmp_path / "e", sun)
    assert m["sun"]["edge_files"] == ["floor.sun_edge.exr", "box.sun_edge.exr"], m["sun"]
    edge, attrs = read_edge_exr(os.path.join(tmp_path / "e", "floor.sun_edge.exr"))
    mask = read_mask_exr(os.path.join(tmp_path / "e", "floor.sun.exr"))[0]
    assert edge.shape == (48, 48, 3) and (edge[..., 2] >= 1).any() and attrs["sun_key"] == m["sun"]["key"]
    assert _bake(sc, tmp_path / "e", sun)["skipped"]
    plain = _bake(sc, tmp_path / "p", sun, sun_edges=False)
    assert "edge_files" not in plain["sun"] and plain["sun"]["key"] != m["sun"]["key"]
    assert not any(f.endswith(".sun_edge.exr") for f in os.listdir(tmp_path / "p"))
    for f in ("floor.sun.exr", "box.sun.exr", "floor.transfer.exr"):
        a, b = (open(os.path.join(tmp_path / d, f), "rb").read() for d in ("e", "p"))
        if f.endswith(".sun.exr"):
            # the key (in the header) differs; the texels do not
            assert np.array_equal(read_mask_exr(os.path.join(tmp_path / "e", f))[0],
                                  read_mask_exr(os.path.join(tmp_path / "p", f))[0]), f
        else:
            assert a == b, f
    assert mask.shape == (48, 48)
    # the edges off over a bake with them: the edge files go
    m3 = _bake(sc, tmp_path / "e", sun, sun_edges=False)
    assert not m3["skipped"] and not any(f.endswith(".sun_edge.exr") for f in os.listdir(tmp_path / "e"))


def test_a_sun_without_shadow_has_no_edges(tmp_path):
    """Blender's Shadow off: the mask is 1 everywhere, there is no edge to draw."""
    from prtt_addon.dev.bench import contact_profile as cp
    m = _bake(cp.build(32), tmp_path / "a", Sun(direction=(0.5, 0.1, 0.8), angle=0.01, shadow=False))
    assert "edge_files" not in m["sun"]
    assert not any(f.endswith(".sun_edge.exr") for f in os.listdir(tmp_path / "a"))
