"""The contact and leak profiles (bench/contact_profile.py) confirmed with
Cycles, an independent renderer (issue 53, proof).

The same core scene (the floor and the box, or the shed of single planes) is
built in Blender (scene_build.mesh_object: the same vertices), its floor and
walls a Diffuse BSDF of albedo ALBEDO, lit by a band-limited World (Blender's
"city" HDRI projected to 5 SH bands and Hann-windowed, written as an EXR:
cycles_compare.band_limited_environment). Under a band-limited light the
diffuse transfer's irradiance T . L is exact, so the baked floor, the transfer
traced at the points and Cycles must agree up to ray noise and the texture's
sampling.

An orthographic camera 2 cm above the floor, looking down, turned with the
box, sees a strip of floor across the measured side (the box's -x side, or the
shed's back wall: both sides of it): STRIP_ALONG of the side's length along it,
pixels of 1/PIXELS_PER_BIN of a quarter texel across it. Cycles renders it
with no bounce (direct light only: the shed's walls reflect nothing, as the
transfer bake with no bounce) and a 0.01 px pixel filter, so a pixel is the
light at its centre: irradiance = pi * radiance / ALBEDO. Each pixel centre is
shaded by the floor's baked transfer texture (texsample.bilinear, as the
preview samples it) and a subset by the transfer traced at the point; per
quarter-texel bin of distance from the side the ratios baked / Cycles and
traced / Cycles are the mean over the bin's pixels.
"""
from __future__ import annotations

import argparse
import math
import os
import tempfile

import numpy as np

from . import contact_profile as cp

ALBEDO = 0.7
#: The strip along the side: its middle 60 %, as contact_profile's profiles.
STRIP_ALONG = 0.6
PIXELS_PER_BIN = 4
CAMERA_HEIGHT = 0.02


def _strip(kind: str, texel: float, bins: int):
    """(side, sign, x0, x1): the side's x in the object's frame, the sign of
    "out" (distance grows with sign * (side - x) for the box, both ways for
    the shed), and the strip's x range in that frame."""
    reach = (bins + 2) / 4.0 * texel
    if kind == "box":
        side = -cp.BOX_SIZE / 2
        return side, side - reach, side + 0.5 / 4.0 * texel
    side = -cp.SHED_SIZE / 2
    return side, side - reach, side + reach


def render_strip(bpy, sc, kind: str, env_path: str, out_path: str, *, texel: float, bins: int,
                 samples: int, seed: int = 1):
    """Cycles' irradiance over the strip: (E (ny, nx, 3), x (nx,), y (ny,)) in
    the object's frame (turned by BOX_TURN about BOX_CENTRE), E from pixel
    centres, row 0 at the smallest y."""
    from . import scene_build as sb
    from .cycles_compare import render_cycles
    bpy.ops.wm.read_factory_settings(use_empty=True)
    mat = sb.principled("grey_diffuse", base_color=(ALBEDO,) * 3, diffuse=True)
    from . import meshgen as mg
    for k, name in enumerate(sc.object_names):
        tri = np.flatnonzero(sc.object_id == k)
        verts = np.asarray(sc.positions, np.float64)[tri].reshape(-1, 3)
        sb.mesh_object(name, mg.Mesh(verts, np.arange(len(verts)).reshape(-1, 3), None), material=mat)
    scene = bpy.context.scene
    scene.world = sb.environment_world("BandLimited", env_path)
    scene.view_settings.view_transform = "Standard"
    _, x0, x1 = _strip(kind, texel, bins)
    length = (cp.BOX_SIZE if kind == "box" else cp.SHED_SIZE) * STRIP_ALONG
    px = texel / 4.0 / PIXELS_PER_BIN
    nx, ny = int(round((x1 - x0) / px)), int(round(length / px))
    if nx > ny:
        raise ValueError("the strip must be longer along the side than across it")
    cam = bpy.data.cameras.new("Strip")
    cam.type, cam.ortho_scale, cam.sensor_fit = "ORTHO", ny * px, "AUTO"
    cam.clip_start, cam.clip_end = 0.001, 1.0
    ob = bpy.data.objects.new("Strip", cam)
    c, s = math.cos(cp.BOX_TURN), math.sin(cp.BOX_TURN)
    xc = 0.5 * (x0 + x1)
    ob.location = (cp.BOX_CENTRE[0] + c * xc, cp.BOX_CENTRE[1] + s * xc, CAMERA_HEIGHT)
    ob.rotation_euler = (0.0, 0.0, cp.BOX_TURN)          # looking down -Z, its x the object's x
    scene.collection.objects.link(ob)
    scene.camera = ob
    bpy.context.view_layer.update()
    from ...blender.blendfile import blender_log_muted
    with blender_log_muted():                           # Blender's "Fra:" lines on stdout
        img = render_cycles(bpy, out_path, (nx, ny), samples, 0, seed)  # row 0 at the bottom
    x = xc + (np.arange(nx) + 0.5 - nx / 2) * px
    y = (np.arange(ny) + 0.5 - ny / 2) * px
    return img[..., :3].astype(np.float64) * (math.pi / ALBEDO), x, y


def cycles_profile(kind: str = "box", resolution: int = 112, *, ref_rays: int = 2048, samples: int = 256,
                   bins: int = 8, variants: dict, traced_every: int = 4, work_dir: str | None = None) -> dict:
    """The profiles against one Cycles render of the strip: {"bins": centres
    in texels, "baked": {variant: {side: ratio to Cycles per bin}}, "traced":
    {side: ...}, "texel_m", "resolution", "samples"}; sides "out" for the
    box, "inside" and "outside" for the shed; ``variants`` names the bakes'
    BakeSettings; the traced transfer at every ``traced_every``-th column of
    pixels with ``ref_rays`` rays."""
    import bpy

    from ...core.bake.estimators.raytrace import RayScene
    from ...core.bake.estimators.transfer import Points, TransferSettings, bake_points
    from ...core.texels.texsample import bilinear
    from .cycles_compare import band_limited_environment
    sc = cp.build(resolution) if kind == "box" else cp.build_shed(resolution)
    texel = 2.0 / resolution
    tmp = tempfile.TemporaryDirectory(prefix="prtt-contact-cycles-") if work_dir is None else None
    d = work_dir or tmp.name
    try:
        env = os.path.join(d, "band_limited_city.exr")
        light = band_limited_environment(env)
        texs = {k: cp.baked_floor(sc, st, 0) for k, st in variants.items()}
        E, x, y = render_strip(bpy, sc, kind, env, os.path.join(d, f"{kind}.exr"), texel=texel, bins=bins,
                               samples=samples)
    finally:
        if tmp is not None:
            tmp.cleanup()
    X, Y = np.meshgrid(x, y)
    c, s = math.cos(cp.BOX_TURN), math.sin(cp.BOX_TURN)
    wx = cp.BOX_CENTRE[0] + c * X - s * Y
    wy = cp.BOX_CENTRE[1] + s * X + c * Y
    uv = (np.stack([wx.ravel(), wy.ravel()], 1) + 1.0) / 2.0
    e_baked = {}
    for k, tex in texs.items():
        H, W, K = tex.shape
        baked = bilinear(np.ascontiguousarray(tex.reshape(H * W, K), np.float32), W, H, uv).astype(np.float64)
        e_baked[k] = (baked @ light).reshape(*X.shape, 3)
    sub = np.zeros(X.shape, bool)
    sub[:, ::traced_every] = True
    P = np.stack([wx[sub], wy[sub], np.zeros(sub.sum())], 1)
    up = np.tile([0.0, 0.0, 1.0], (len(P), 1))
    traced, _ = bake_points(RayScene(np.asarray(sc.positions, np.float64)),
                            Points(P, up, up, np.arange(len(P), dtype=np.int64), np.zeros(len(P), bool)),
                            TransferSettings(bands=5, rays=ref_rays, seed=11))
    e_traced = np.full(X.shape + (3,), np.nan)
    e_traced[sub] = traced.astype(np.float64) @ light
    side, _, _ = _strip(kind, texel, bins)
    sides = {"out": -1.0} if kind == "box" else {"inside": 1.0, "outside": -1.0}
    out = {"bins": (np.arange(bins) + 0.5) / 4.0, "texel_m": texel, "resolution": resolution, "samples": samples,
           "baked": {k: {} for k in variants}, "traced": {}}

    def ratio(e, m):
        return float(np.nanmean(e[m].mean(axis=1)) / E[m].mean(axis=1).mean())

    for name, sign in sides.items():
        dist = sign * (X - side) / texel                      # texels from the side, on this side
        in_bin = [(dist >= b / 4.0) & (dist < (b + 1) / 4.0) for b in range(bins)]
        for k in variants:
            out["baked"][k][name] = np.array([ratio(e_baked[k], m) for m in in_bin])
        out["traced"][name] = np.array([ratio(e_traced, m & sub) for m in in_bin])
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench contact-cycles", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=112, help="the floor's texels a side (112: 1.8 cm texels)")
    p.add_argument("--rays", type=int, default=256)
    p.add_argument("--ref-rays", type=int, default=2048, help="the traced transfer's rays a point")
    p.add_argument("--samples", type=int, default=256, help="Cycles' samples a pixel")
    p.add_argument("--leak", action="store_true", help="the shed of single-plane walls instead of the box")
    p.add_argument("--texel-validity", action=argparse.BooleanOptionalAction, default=True,
                   help="bake with texel validity (the default) or without")
    a = p.parse_args(argv)
    from ...core.bake.pipeline.context import BakeSettings
    st = BakeSettings(rays=a.rays, bounces=0, texel_validity=a.texel_validity)
    r = cycles_profile("shed" if a.leak else "box", a.resolution, ref_rays=a.ref_rays, samples=a.samples,
                       variants={"baked": st})
    print(f"floor texel {r['texel_m'] * 100:.2f} cm ({r['resolution']}² over 2 m), texel validity "
          f"{'on' if a.texel_validity else 'off'}; irradiance / Cycles' ({a.samples} samples a pixel) by "
          f"distance from the {'shed' if a.leak else 'box'}, in texels:")
    sides = list(r["traced"])
    print("  texels" + "".join(f"  {s + ' baked':>14}  {s + ' traced':>14}" for s in sides))
    for b, c in enumerate(r["bins"]):
        print(f"  {c:5.3f} " + "".join(f"  {r['baked']['baked'][s][b]:14.3f}  {r['traced'][s][b]:14.3f}"
                                      for s in sides))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
