"""``python -m prtt_addon.dev.bench lamps``: point and spot lamps' light and
shadows in PRTT's preview against Cycles (issue 49, item 1).

The sun bench's scene (sun_cycles: a 4 m floor, a 0.5 m box, a 1.2 m plank
0.4 m over the floor, Diffuse BSDF 0.7, the dim band-limited "city" sky that
lights the shadows) without its sun, lit instead by ``--lamps``: a point
lamp of radius 10 cm over the plank ("point"), a spot on the box and the
floor ("spot", cone 60 degrees, blend 0.3), or both. The add-on unwraps and
bakes it (the lamps' masks, LAMP_RAYS a texel); its preview renders the
camera's view offscreen (diffuse mode), Cycles the same view with direct
light only (no bounce, ``samples``, two seeds for its own noise).

Measured over the pixels more than a pixel from a triangle edge and from
another object (a silhouette's pixel is each renderer's own coverage): relative
RMSE of the image and of the shadowed floor (Cycles below half the floor's
lit value at the same distance from the lamps: the pixels where a shadow
took half the lamps' light or more), and the mean.
"""
from __future__ import annotations

import argparse
import math
import os
import tempfile
import time

import numpy as np

#: The lamps of each variant: Blender's Point and Spot settings.
LAMPS = {
    "point": [dict(name="Bulb", kind="POINT", energy=120.0, radius=0.1, color=(1.0, 0.9, 0.8),
                   location=(0.3, 0.9, 1.6))],
    "spot": [dict(name="Spot", kind="SPOT", energy=400.0, radius=0.05, color=(0.8, 0.9, 1.0),
                  location=(-2.0, -1.6, 2.2), target=(-0.5, -0.2, 0.0), spot_size=60.0, spot_blend=0.3)],
}


def add_lamps(bpy, variant: str) -> list:
    """The variant's lamps (LAMPS; "both": point and spot) linked into the scene."""
    import mathutils
    specs = LAMPS["point"] + LAMPS["spot"] if variant == "both" else LAMPS[variant]
    obs = []
    for s in specs:
        ob = bpy.data.objects.new(s["name"], bpy.data.lights.new(s["name"], s["kind"]))
        ob.data.energy, ob.data.shadow_soft_size, ob.data.color = s["energy"], s["radius"], s["color"]
        ob.location = s["location"]
        if s["kind"] == "SPOT":
            ob.data.spot_size, ob.data.spot_blend = math.radians(s["spot_size"]), s["spot_blend"]
            d = mathutils.Vector(s["target"]) - mathutils.Vector(s["location"])
            ob.rotation_euler = d.to_track_quat("-Z", "Y").to_euler()
        bpy.context.scene.collection.objects.link(ob)
        obs.append(ob)
    return obs


def compare(variant: str = "both", size=(320, 180), *, samples: int = 256, resolution: int = 512,
            work_dir: str | None = None, detail: int = 1) -> dict:
    import bpy

    from ... import register
    from ...blender.bake.run import bake_blocking
    from ...blender.blendfile import blender_log_muted
    from ...blender.preview.drawlist import collect
    from ...blender.preview.offscreen import camera_view, render_scene
    from ...core.preview.reference import trace_pixels
    from . import meshgen as mg
    from . import scene_build as sb
    from .cycles_compare import band_limited_environment, render_cycles
    from .sun_cycles import BOX, FLOOR, FLOOR_ALBEDO, PLANK, SKY_STRENGTH
    tmp = tempfile.TemporaryDirectory(prefix="prtt-lamps-") if work_dir is None else None
    d = work_dir or tmp.name
    try:
        bpy.ops.wm.read_factory_settings(use_empty=True)
        if not hasattr(bpy.types.Scene, "prtt"):
            register()
        grey = sb.principled("grey", base_color=(FLOOR_ALBEDO[False],) * 3, diffuse=True)
        sb.mesh_object("floor", mg.plane(FLOOR, FLOOR, subdiv=1), material=grey)
        sb.mesh_object("box", mg.box(*BOX), material=grey)
        sb.mesh_object("plank", mg.box(*PLANK), material=grey)
        scene = bpy.context.scene
        out = os.path.join(d, "textures")
        os.makedirs(out, exist_ok=True)
        env = os.path.join(out, "band_limited_city.exr")
        band_limited_environment(env)
        scene.world = sb.environment_world("BandLimited", env, strength=SKY_STRENGTH)
        add_lamps(bpy, variant)
        scene.camera = sb.camera_object("Camera", (1.6, -2.6, 2.2), (-0.1, 0.2, 0.0), fov_y_deg=50.0)
        scene.view_settings.view_transform = "Standard"
        bpy.context.view_layer.update()
        st = scene.prtt
        st.output_dir, st.resolution, st.rays, st.bounces = out, resolution, 256, 0
        st.texture_sets, st.unwrap_method, st.light_source = "ATLAS", "SMART", "WORLD"
        st.sun_detail = detail          # Shadow Detail: the lamps' masks too
        for o in bpy.context.view_layer.objects:
            o.select_set(o.type == "MESH")
        if bpy.ops.prtt.unwrap() != {"FINISHED"}:
            raise RuntimeError("unwrap failed")
        t = time.perf_counter()
        outcome = bake_blocking(bpy.context, force=True)
        if outcome.status != "done":
            raise RuntimeError(outcome.message)
        t_bake = time.perf_counter() - t
        manifest = outcome.manifest
        prtt, _, status, _ = render_scene(bpy.context, mode="diffuse", size=size, bounces=False)
        with blender_log_muted():
            cyc = [render_cycles(bpy, os.path.join(d, f"cycles{s}.exr"), size, samples, 0, s) for s in (1, 2)]
        # The lamps' light alone, unshadowed: what the floor would receive without the box and plank.
        ps, _ = collect(bpy.context, use_bounces=False)
        vp, _ = camera_view(scene.camera, bpy.context.evaluated_depsgraph_get(), *size, scene)
        hits = trace_pixels(ps, vp, *size)
        unshadowed = _unshadowed_floor(ps, hits, vp, size)
    finally:
        if tmp is not None:
            tmp.cleanup()
    # Pixels whose 3 x 3 neighbourhood is one mesh: a silhouette's pixel is the
    # rasteriser's and Cycles' own coverage there, not the light.
    mesh = np.pad(hits.mesh, 1, mode="edge")
    inner = np.ones(hits.mesh.shape, bool)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            inner &= mesh[dy:dy + hits.mesh.shape[0], dx:dx + hits.mesh.shape[1]] == hits.mesh
    mask = hits.hit & inner & (hits.edge_px > 1.0) & (prtt[..., 3] > 0.5) & (cyc[0][..., 3] > 0.99)
    ref = 0.5 * (cyc[0] + cyc[1])
    a, b = prtt[..., :3].astype(np.float64), ref[..., :3].astype(np.float64)
    floor_k = [m.name for m in ps.meshes].index("floor")
    on_floor = mask & (hits.mesh == floor_k)
    # Shadowed: Cycles has lost half the lamps' unshadowed light on the floor or more.
    sky = np.quantile(b.mean(axis=2)[on_floor], 0.02)
    shadow = on_floor & (b.mean(axis=2) < sky + 0.5 * unshadowed)
    noise = float(np.sqrt(np.mean((cyc[0][..., :3][mask] - cyc[1][..., :3][mask]) ** 2) / 2.0) / np.mean(b[mask]))

    def rel(m):
        return float(np.sqrt(np.mean((a[m] - b[m]) ** 2)) / np.mean(b[m]))

    return {"variant": variant, "size": list(size), "samples": samples, "resolution": resolution,
            "pixels": int(mask.sum()), "shadow_pixels": int(shadow.sum()),
            "rel_rmse": rel(mask), "rel_rmse_shadow": rel(shadow) if shadow.sum() >= 20 else float("nan"),
            "mean_ratio_minus_1": float(a[mask].mean() / b[mask].mean() - 1.0),
            "cycles_noise": noise / math.sqrt(2.0), "bake_seconds": float(manifest["seconds"]["total"]),
            "bake_s": t_bake, "lamp_seconds": sum(s.get("lamp_seconds", 0.0) for s in manifest["sets"]),
            "lamps": [lp["name"] for lp in (manifest.get("lamps") or {}).get("lamps", [])],
            "notes": [t for _, t in status.messages],
            "images": {"prtt": prtt, "cycles": ref, "mask": mask, "shadow": shadow}}


def _unshadowed_floor(ps, hits, vp, size) -> np.ndarray:
    """(H, W) the lamps' diffuse light on the floor at each pixel without any
    shadow (masks 1): the scale the shadowed region is judged by."""
    from .sun_cycles import FLOOR_ALBEDO
    W, H = size
    out = np.zeros(H * W)
    k = [m.name for m in ps.meshes].index("floor")
    m = ps.meshes[k]
    sel = np.flatnonzero((hits.mesh == k).ravel())
    P = np.einsum("nk,nkc->nc", hits.bary.reshape(-1, 3)[sel], m.world_corners("positions")[hits.tri.ravel()[sel]])
    for lp in ps.lamps:
        l, E = lp.irradiance(P)
        out[sel] += FLOOR_ALBEDO[False] / math.pi * np.maximum(l[:, 2], 0.0) * E.mean(axis=1)
    return out.reshape(H, W)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench lamps", description=__doc__.split("\n\n")[0])
    p.add_argument("--lamps", default="point,spot,both", help="variants, comma-separated: point, spot, both")
    p.add_argument("--size", default="320x180")
    p.add_argument("--samples", type=int, default=256, help="Cycles' samples a pixel")
    p.add_argument("--resolution", type=int, default=512, help="the atlas")
    p.add_argument("--budget", action="store_true", help="what each lamp costs: the room baked with 0, 1, 2 and 4 "
                   "lamps, the masks' seconds and bytes and the preview's frame time (bench/lamp_budget.py; no Cycles)")
    p.add_argument("--detail", default="1", help="Shadow Detail (sun_detail: the masks' texels per set texel a "
                   "side), comma-separated: a row each")
    a = p.parse_args(argv)
    if a.budget:
        from .lamp_budget import budget
        res = 1024 if a.resolution == 512 else a.resolution
        print(f"the room ({res}² atlas, no bounce) with point and spot lamps, preview frames at 1280x720:")
        print(f"  {'lamps':>5}  {'bake s':>6}  {'masks s':>7}  {'mask bytes':>10}  {'TPFL ms':>7}  {'diffuse ms':>10}")
        for r in budget(res):
            print(f"  {r['lamps']:5d}  {r['bake_s']:6.2f}  {r['mask_s']:7.2f}  {r['mask_bytes']:10d}  "
                  f"{r['tpfl_ms']:7.1f}  {r['diffuse_ms']:10.1f}", flush=True)
        return 0
    w, h = (int(v) for v in a.size.split("x"))
    print(f"point and spot lamps over a box and a plank, {w}x{h}, Cycles {a.samples} samples, direct light, "
          f"atlas {a.resolution}², diffuse mode:")
    print(f"  {'lamps':>6}  {'detail':>6}  {'image RMSE':>10}  {'shadow RMSE':>11}  {'mean':>7}  {'Cycles noise':>12}  "
          f"{'masks s':>7}  {'bake s':>6}")
    runs = [(v.strip(), int(f)) for v in a.lamps.split(",") for f in a.detail.split(",")]
    for v, f in runs:
        r = compare(v, (w, h), samples=a.samples, resolution=a.resolution, detail=f)
        print(f"  {v:>6}  {f:>6}  {r['rel_rmse']:10.2%}  {r['rel_rmse_shadow']:11.2%}  {r['mean_ratio_minus_1']:+7.2%}  "
              f"{r['cycles_noise']:12.2%}  {r['lamp_seconds']:7.2f}  {r['bake_seconds']:6.2f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
