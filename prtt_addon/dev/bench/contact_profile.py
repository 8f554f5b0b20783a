"""Dark creases at contacts (issue 53, item 2), measured: the floor's baked
light next to a box resting on it, against the light traced at the same
points, in quarter-texel bins of distance from the box.

A 2 m floor (two triangles, its own ``resolution``² set: 2 / resolution m
texels) and a 0.5 m box standing on it (its bottom face on the floor, its
sides off the texel grid). Along the middle 60 % of the box's -x side,
``samples`` floor points at each bin centre (0.125, 0.375, ... texels out)
are shaded two ways with the same light (SH, ``env``): the floor's transfer
texture sampled as the preview samples it (texsample.bilinear, the baked
texels as written), and the transfer traced at the point itself
(``ref_rays`` rays: core.bake.estimators.transfer, as the traced reference
of bench contact). The profile is the ratio of their irradiance (the light's
dot product with the transfer, mean over RGB) per bin: 1 is exact, below 1
a dark crease (texels whose centres lie under the box are baked black and
blend into the visible floor).
"""
from __future__ import annotations

import argparse
import os
import tempfile

import numpy as np

from . import meshgen as mg

#: The box: size, centre (its bottom face on the floor, z = 0) and turn about
#: z: 0.05 rad, so that along the measured side the edge crosses the texel
#: grid at every phase (the profile is an average over where texel centres fall).
BOX_SIZE = 0.5
BOX_CENTRE = (0.1234, 0.0567)
BOX_TURN = 0.05


def _on_floor(name: str, mesh, resolution: int):
    """The core scene: the 2 m floor (own UVs over [0, 1], ``resolution``²)
    and ``mesh`` (xatlas, 128²) standing on it, one grey material."""
    from ...core.model.scene import validate
    floor = mg.plane(2.0, 2.0, subdiv=1)
    floor.uvs = ((floor.vertices[:, :2] + 1.0) / 2.0)[floor.faces]
    sc = mg.assemble([("floor", floor), (name, mesh)], resolution=resolution, keep_uvs=True,
                     resolutions={name: 128})
    sc.materials = [dict(name="grey", base_color=[0.7, 0.7, 0.7], roughness=0.6)]
    sc.material_id = np.zeros_like(sc.object_id)
    validate(sc)
    return sc


def build(resolution: int):
    """The core scene: floor (own UVs over [0, 1]) and box (xatlas, 128²)."""
    box = mg.box((BOX_SIZE,) * 3).transformed(rotate_z=BOX_TURN, translate=(*BOX_CENTRE, BOX_SIZE / 2))
    return _on_floor("box", box, resolution)


def baked_floor(sc, settings, rays: int):
    """The floor's transfer texture (H, W, K) as the bake writes it, with
    ``settings`` (default: ``rays`` rays, no bounce)."""
    from ...core.bake.pipeline.context import BakeSettings
    from ...core.bake.pipeline.runner import bake_scene
    from ...core.io.exr_io import read_sh_exr
    with tempfile.TemporaryDirectory(prefix="prtt-contact-profile-") as d:
        bake_scene(sc, os.path.join(d, "b"), settings or BakeSettings(rays=rays, bounces=0))
        tex, _ = read_sh_exr(os.path.join(d, "b", "floor.transfer.exr"))
    return tex


def _ratio(rs, tex, x: np.ndarray, along: np.ndarray, light, ref_rays: int) -> np.ndarray:
    """(bins,) the mean baked / traced irradiance of floor points per bin:
    ``x`` (bins, samples) and ``along`` (samples,) coordinates in the box's
    frame (turned by BOX_TURN about BOX_CENTRE); the baked value sampled
    from ``tex`` as the preview samples it (texsample.bilinear), the traced
    one from ``ref_rays`` rays at the point itself (``rs`` the RayScene)."""
    from ...core.bake.estimators.transfer import Points, TransferSettings, bake_points
    from ...core.texels.texsample import bilinear
    bins = x.shape[0]
    local = np.stack([x.ravel(), np.repeat(along[None, :], bins, 0).ravel()], axis=1)
    c, s_ = np.cos(BOX_TURN), np.sin(BOX_TURN)
    xy = local @ np.array([[c, s_], [-s_, c]]) + np.asarray(BOX_CENTRE)
    P = np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)
    up = np.tile([0.0, 0.0, 1.0], (len(P), 1))
    H, W, K = tex.shape
    baked = bilinear(np.ascontiguousarray(tex.reshape(H * W, K), np.float32), W, H,
                     (P[:, :2] + 1.0) / 2.0).astype(np.float64)
    pts = Points(P, up, up, np.arange(len(P), dtype=np.int64), np.zeros(len(P), bool))
    traced, _ = bake_points(rs, pts, TransferSettings(bands=5, rays=ref_rays, seed=11))
    e_baked = (baked @ light).mean(axis=1).reshape(bins, -1)
    e_traced = (traced.astype(np.float64) @ light).mean(axis=1).reshape(bins, -1)
    return e_baked.mean(axis=1) / e_traced.mean(axis=1)


def profile(resolution: int = 112, *, rays: int = 256, ref_rays: int = 4096, samples: int = 300,
            env: str = "forest", bins: int = 8, settings=None) -> dict:
    """{"bins": bin centres in texels, "ratio": baked / traced irradiance per
    bin, "texel_m": the floor's texel in metres}."""
    from ...core.bake.estimators.raytrace import RayScene
    from ...core.light.envmap import environment_light

    sc = build(resolution)
    light = environment_light(env, 5)
    texel = 2.0 / resolution
    centres = (np.arange(bins) + 0.5) / 4.0
    # In the box's frame: x out of its -x side by the bin's distance, y along the side.
    along = np.linspace(-0.3, 0.3, samples) * BOX_SIZE
    out = -(BOX_SIZE / 2 + centres[:, None] * texel) * np.ones_like(along)[None, :]
    tex = baked_floor(sc, settings, rays)
    ratio = _ratio(RayScene(np.asarray(sc.positions, np.float64)), tex, out, along, light, ref_rays)
    return {"bins": centres, "ratio": ratio, "texel_m": texel, "resolution": resolution}


#: The shed of zero-thickness walls (leak_profile): a 1 m cube of single
#: planes (four walls and a roof) standing on the floor, which runs on under
#: its walls; light gets in only through a door, a slot SHED_DOOR wide and as
#: tall as the front (+x) wall. Turned and placed as the box.
SHED_SIZE = 1.0
SHED_DOOR = 0.2


def build_shed(resolution: int, walls: str = "in"):
    """The core scene: floor (own UVs over [0, 1]) and the shed (xatlas, 128²),
    its walls facing ``walls``: "in" (into the shed) or "out" (as Blender's
    cube with its bottom face deleted); the roof faces up either way."""
    from .scene_library import wall
    h = SHED_SIZE / 2
    f = {"in": 1.0, "out": -1.0}[walls]
    parts = [wall((-h, 0.0, h), (SHED_SIZE, SHED_SIZE), facing=(f, 0, 0)),
             wall((0.0, -h, h), (SHED_SIZE, SHED_SIZE), facing=(0, f, 0)),
             wall((0.0, h, h), (SHED_SIZE, SHED_SIZE), facing=(0, -f, 0)),
             mg.plane(SHED_SIZE).transformed(translate=(0.0, 0.0, SHED_SIZE))]
    side = (SHED_SIZE - SHED_DOOR) / 2
    for sy in (-1.0, 1.0):
        parts.append(wall((h, sy * (SHED_DOOR / 2 + side / 2), h), (side, SHED_SIZE), facing=(-f, 0, 0)))
    shed = mg.merge(parts).transformed(rotate_z=BOX_TURN, translate=(*BOX_CENTRE, 0.0))
    return _on_floor("shed", shed, resolution)


def leak_profile(resolution: int = 112, *, rays: int = 256, ref_rays: int = 4096, samples: int = 300,
                 env: str = "forest", bins: int = 8, settings=None, walls: str = "in") -> dict:
    """Light leaking under a zero-thickness wall (issue 53, item 2): the
    floor's baked / traced irradiance in quarter-texel bins from the shed's
    back wall, inside (dark: lit only through the door) and outside
    (in the open), along its middle 60 %; ``walls`` as build_shed. {"bins",
    "inside", "outside" (the ratios per bin), "texel_m", "resolution"}."""
    from ...core.bake.estimators.raytrace import RayScene
    from ...core.light.envmap import environment_light

    sc = build_shed(resolution, walls)
    light = environment_light(env, 5)
    texel = 2.0 / resolution
    centres = (np.arange(bins) + 0.5) / 4.0
    along = np.linspace(-0.3, 0.3, samples) * SHED_SIZE
    tex = baked_floor(sc, settings, rays)
    rs = RayScene(np.asarray(sc.positions, np.float64))
    out = {"bins": centres, "texel_m": texel, "resolution": resolution}
    for side, sign in (("inside", 1.0), ("outside", -1.0)):
        x = -SHED_SIZE / 2 + sign * centres[:, None] * texel * np.ones_like(along)[None, :]
        out[side] = _ratio(rs, tex, x, along, light, ref_rays)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench contact-profile", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=112, help="the floor's texels a side (112: 1.8 cm texels)")
    p.add_argument("--rays", type=int, default=256)
    p.add_argument("--ref-rays", type=int, default=4096)
    p.add_argument("--texel-validity", action=argparse.BooleanOptionalAction, default=True,
                   help="bake with texel validity (the default) or without (the crease it removes)")
    p.add_argument("--leak", action="store_true",
                   help="the shed of zero-thickness walls instead of the box: the floor inside and outside its "
                        "back wall (leak_profile)")
    p.add_argument("--walls", choices=("in", "out"), default="in",
                   help="with --leak: the shed's walls face into it (the default) or out (Blender's cube with its "
                        "bottom deleted)")
    args = p.parse_args(argv)
    from ...core.bake.pipeline.context import BakeSettings
    settings = BakeSettings(rays=args.rays, bounces=0, texel_validity=args.texel_validity)
    if args.leak:
        r = leak_profile(args.resolution, rays=args.rays, ref_rays=args.ref_rays, settings=settings, walls=args.walls)
        print(f"floor texel {r['texel_m'] * 100:.2f} cm ({r['resolution']}² over 2 m), texel validity "
              f"{'on' if args.texel_validity else 'off'}; baked / traced irradiance by distance from the shed's "
              f"back wall (single planes facing {args.walls}), in texels:")
        print("  texels  inside  outside")
        for c, a, b in zip(r["bins"], r["inside"], r["outside"]):
            print(f"  {c:5.3f}  {a:6.3f}  {b:7.3f}")
        return 0
    r = profile(args.resolution, rays=args.rays, ref_rays=args.ref_rays, settings=settings)
    print(f"floor texel {r['texel_m'] * 100:.2f} cm ({r['resolution']}² over 2 m), texel validity "
          f"{'on' if args.texel_validity else 'off'}; baked / traced irradiance by distance from the box, in texels:")
    for c, v in zip(r["bins"], r["ratio"]):
        print(f"  {c:5.3f}  {v:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
