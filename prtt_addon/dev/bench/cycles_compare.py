"""``python -m prtt_addon.dev.bench cycles``: PRTT against Cycles, an independent renderer.

The room-class scene with diffuse materials (Diffuse BSDF, the room's
colours) under a *band-limited* environment: Blender's "city" HDRI projected
to 5 SH bands and Hann-windowed (so its reconstruction is positive), written
out as an equirect EXR and used as the World. For a band-limited light the
diffuse PRT integral is exact: sum_k T_k L_k = integral V max(0, n.w) L(w) dw
(the light has no higher bands for the transfer's to meet), so PRTT's diffuse
preview and a Cycles path-traced image with direct light only must agree up
to Monte Carlo noise (both sides) and texture sampling. With ``--bounces 1``
Cycles gets one diffuse bounce and PRTT its bounce texture. For diffuse
surfaces that is exact too: the light leaving q is albedo/pi times q's
irradiance (exact under the band-limited light), and a diffuse receiver needs
only the cosine-weighted integral of the bounced light, which the bounce
texture's projection keeps exactly; what remains is ray noise and the bilinear
texture lookup at q.

Both images come from the same .blend and camera: PRTT's through the
add-on's bake and offscreen preview, Cycles' through ``bpy.ops.render``
(pixel filter 0.01 px, so a pixel is its centre like the preview's). Pixels
within 1 px of a triangle edge are left out. Cycles' own noise is measured
from two renders with different seeds.
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time

import numpy as np

from . import scene_library

DOCS_BENCH = os.path.join(scene_library.ROOT, "docs", "bench")


def band_limited_environment(path: str, bands: int = 5, source: str = "city", height: int = 256) -> np.ndarray:
    """Write the band-limited, Hann-windowed environment as an equirect EXR; returns its SH."""
    import OpenEXR

    from ...core.base.atomic import atomic_write
    from ...core.light.envmap import project_equirect, reconstruct_equirect
    from ...core.sh.zonal import convolve, window_factors
    L = convolve(project_equirect(source, bands), window_factors(bands, "hanning"))
    img = reconstruct_equirect(L, height).astype(np.float32)          # (H, 2H, 3), row 0 = top
    if img.min() < 0:
        raise ValueError(f"the windowed {source!r} environment still goes negative ({img.min():.3g})")
    channels = {c: np.ascontiguousarray(img[..., i]) for i, c in enumerate("RGB")}
    with atomic_write(path) as tmp, OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION,
                                                  "type": OpenEXR.scanlineimage}, channels) as f:
        f.write(tmp)
    return L


def build(bpy, env_path: str, out_dir: str, *, resolution: int, rays: int, bounces: int,
          bounce_mode: str = "baked"):
    """The diffuse room in the current (empty) file, unwrapped and baked with the add-on."""
    from . import scene_build as sb
    for name, mesh in scene_library.room_objects():
        colour = tuple(scene_library.ROOM_MATERIALS.get(name, {"base_color": [0.6, 0.6, 0.6]})["base_color"])
        sb.mesh_object(name, mesh, material=sb.principled(f"{name}_diffuse", base_color=colour, diffuse=True))
    scene = bpy.context.scene
    scene.world = sb.environment_world("BandLimited", env_path, strength=1.0)
    scene.camera = sb.camera_object("Camera", (0.0, -5.6, 2.3), (0.0, 0.6, 0.7), fov_y_deg=62.0)
    scene.view_settings.view_transform = "Standard"
    bpy.context.view_layer.update()
    st = scene.prtt
    st.output_dir, st.resolution, st.rays = out_dir, resolution, rays
    st.texture_sets, st.unwrap_method, st.bounces, st.bounce_rays = "ATLAS", "SMART", bounces, max(16, rays // 4)
    st.bounce_mode = bounce_mode.upper()
    for ob in bpy.context.view_layer.objects:
        ob.select_set(ob.type == "MESH")
    if bpy.ops.prtt.unwrap() != {"FINISHED"}:
        raise RuntimeError("unwrap failed")
    from ...blender.bake.run import bake_blocking
    outcome = bake_blocking(bpy.context, force=True)
    if outcome.status != "done":
        raise RuntimeError(outcome.message)
    return outcome.manifest


def render_cycles(bpy, path: str, size, samples: int, bounces: int, seed: int) -> np.ndarray:
    from ...core.io.image_write import read_exr_rgba
    bpy.context.scene.render.image_settings.file_format = "OPEN_EXR"
    cycles_still(bpy, path, size, samples, bounces, seed)
    return read_exr_rgba(path)


def cycles_still(bpy, path: str, size, samples: int, bounces: int, seed: int) -> None:
    """Render the scene with Cycles to ``path`` in the scene's image format, as
    the comparisons do: CPU, ``samples`` a pixel without adaptive sampling or
    denoising, ``seed``, a 0.01-pixel filter, ``bounces`` diffuse bounces and no
    other, no clamping, a transparent film, 32-bit floats."""
    scene = bpy.context.scene
    r = scene.render
    r.engine = "CYCLES"
    r.resolution_x, r.resolution_y, r.resolution_percentage = size[0], size[1], 100
    r.film_transparent = True
    r.image_settings.color_depth = "32"
    r.filepath = path
    c = scene.cycles
    c.device = "CPU"
    c.samples = samples
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.seed = seed
    c.filter_width = 0.01
    c.max_bounces = bounces
    c.diffuse_bounces = bounces
    c.glossy_bounces = c.transmission_bounces = c.volume_bounces = c.transparent_max_bounces = 0
    c.sample_clamp_direct = c.sample_clamp_indirect = 0.0
    bpy.ops.render.render(write_still=True)


def turn_world(bpy, degrees: float) -> None:
    """Turn the World's environment about Z (its Mapping node), as a user would."""
    import math
    nodes = bpy.context.scene.world.node_tree.nodes
    next(n for n in nodes if n.bl_idname == "ShaderNodeMapping").inputs["Rotation"].default_value[2] = \
        math.radians(degrees)
    bpy.context.view_layer.update()


def compare(size=(320, 180), *, samples: int = 1024, resolution: int = 1024, rays: int = 1024,
            bounces: int = 0, work_dir: str | None = None, bounce_mode: str = "baked", turn: float = 0.0) -> dict:
    import bpy

    from ... import register
    from ...blender.preview.drawlist import collect
    from ...blender.preview.offscreen import camera_view, render_scene
    from ...core.preview.reference import trace_pixels
    tmp = tempfile.TemporaryDirectory(prefix="prtt-cycles-") if work_dir is None else None
    d = work_dir or tmp.name
    try:
        bpy.ops.wm.read_factory_settings(use_empty=True)
        if not hasattr(bpy.types.Scene, "prtt"):
            register()
        env = os.path.join(d, "band_limited_city.exr")
        L = band_limited_environment(env)
        t = time.perf_counter()
        manifest = build(bpy, env, os.path.join(d, "textures"), resolution=resolution, rays=rays, bounces=bounces,
                         bounce_mode=bounce_mode)
        t_bake = time.perf_counter() - t
        if turn:
            # After the bake: relightable bounces follow the World, baked ones would be stale.
            turn_world(bpy, turn)
        t = time.perf_counter()
        prtt, _, _, _ = render_scene(bpy.context, mode="diffuse", size=size, bounces=bounces > 0)
        t_prtt = time.perf_counter() - t
        t = time.perf_counter()
        cyc = [render_cycles(bpy, os.path.join(d, f"cycles{s}.exr"), size, samples, bounces, s) for s in (1, 2)]
        t_cycles = (time.perf_counter() - t) / 2
        ps, _ = collect(bpy.context, use_bounces=bounces > 0)
        vp, _ = camera_view(bpy.context.scene.camera, bpy.context.evaluated_depsgraph_get(), *size,
                            bpy.context.scene)
        hits = trace_pixels(ps, vp, *size)
    finally:
        if tmp is not None:
            tmp.cleanup()
    mask = hits.hit & (hits.edge_px > 1.0) & (prtt[..., 3] > 0.5) & (cyc[0][..., 3] > 0.99)
    ref = 0.5 * (cyc[0] + cyc[1])
    a, b = prtt[..., :3][mask].astype(np.float64), ref[..., :3][mask].astype(np.float64)
    noise = np.sqrt(np.mean((cyc[0][..., :3][mask] - cyc[1][..., :3][mask]) ** 2) / 2.0) / np.mean(b)
    rel = np.abs(a - b) / np.maximum(b, 1e-3 * b.mean())
    per_object = {}
    names = [m.name for m in ps.meshes]
    for k, name in enumerate(names):
        mk = mask & (hits.mesh == k)
        if mk.sum() >= 50:
            per_object[name] = float(np.mean(prtt[..., :3][mk]) / np.mean(ref[..., :3][mk]) - 1.0)
    return {
        "size": list(size), "samples": samples, "resolution": resolution, "rays": rays, "bounces": bounces,
        "bounce_mode": bounce_mode, "world_turned_after_bake_degrees": turn,
        "pixels_compared": int(mask.sum()),
        "mean_ratio_minus_1": float(a.mean() / b.mean() - 1.0),
        "rel_rmse": float(np.sqrt(np.mean((a - b) ** 2)) / b.mean()),
        "cycles_noise_rel_rmse_of_mean": float(noise / np.sqrt(2.0)),
        "median_rel_error": float(np.median(rel)), "p95_rel_error": float(np.quantile(rel, 0.95)),
        "per_object_mean_ratio_minus_1": per_object,
        "seconds": {"bake": t_bake, "prtt_render": t_prtt, "cycles_render": t_cycles},
        "texels": manifest["totals"]["texels"], "light_dc": L[0].tolist(),
        "images": {"prtt": prtt, "cycles": ref, "mask": mask},
    }


def save_figure(res: dict, path: str) -> str:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ...core.io.image_write import srgb_encode
    im = res["images"]
    exposure = 0.5
    fig, axes = plt.subplots(1, 3, figsize=(15, 3.4))
    for ax, key, title in ((axes[0], "cycles", f"Cycles, {res['samples']} spp x 2, direct light"
                            if not res["bounces"] else f"Cycles, {res['samples']} spp x 2, 1 bounce"),
                           (axes[1], "prtt", "PRTT diffuse preview (transfer textures)")):
        img = im[key][::-1]
        ax.imshow(np.clip(srgb_encode(exposure * img[..., :3]) * img[..., 3:] + (1 - img[..., 3:]), 0, 1))
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
    diff = np.zeros(im["mask"].shape)
    m = im["mask"]
    diff[m] = (im["prtt"][..., :3][m].mean(-1) / np.maximum(im["cycles"][..., :3][m].mean(-1), 1e-6)) - 1.0
    h = axes[2].imshow(diff[::-1], cmap="RdBu_r", vmin=-0.1, vmax=0.1)
    axes[2].set_title(f"PRTT / Cycles - 1 (compared pixels); mean {100 * res['mean_ratio_minus_1']:+.2f} %, "
                      f"rel. RMSE {100 * res['rel_rmse']:.1f} %", fontsize=9)
    axes[2].set_axis_off()
    fig.colorbar(h, ax=axes[2], fraction=0.03)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench cycles", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", default="320x180")
    p.add_argument("--samples", type=int, default=1024)
    p.add_argument("--resolution", type=int, default=1024)
    p.add_argument("--rays", type=int, default=1024)
    p.add_argument("--bounces", type=int, default=0, choices=[0, 1])
    p.add_argument("--bounce-mode", default="baked", choices=("baked", "relightable"))
    p.add_argument("--turn", type=float, default=0.0, metavar="DEG",
                   help="turn the World about Z by DEG after the bake, before both renders (relightable bounces)")
    p.add_argument("--out", default=DOCS_BENCH)
    args = p.parse_args(argv)
    if args.turn and args.bounces and args.bounce_mode != "relightable":
        p.error("--turn with baked bounces compares stale bounce light; use --bounce-mode relightable")
    w, h = (int(v) for v in args.size.split("x"))
    res = compare((w, h), samples=args.samples, resolution=args.resolution, rays=args.rays, bounces=args.bounces,
                  bounce_mode=args.bounce_mode, turn=args.turn)
    os.makedirs(args.out, exist_ok=True)
    tag = f"cycles_b{args.bounces}" + ("_relight" if args.bounce_mode == "relightable" else "") + \
        (f"_turn{args.turn:g}" if args.turn else "")
    fig = save_figure(res, os.path.join(args.out, f"{tag}.png"))
    res.pop("images")
    with open(os.path.join(args.out, f"{tag}.json"), "w", encoding="utf-8") as f:
        json.dump(res, f, indent=1)
    print(f"room, diffuse, band-limited 'city' (5 bands, Hann), {w}x{h}, bounces {args.bounces} "
          f"({args.bounce_mode}, World turned {args.turn:g} deg after the bake): "
          f"{res['pixels_compared']} pixels compared")
    print(f"  PRTT mean / Cycles mean - 1:  {100 * res['mean_ratio_minus_1']:+.2f} %")
    print(f"  relative RMSE per pixel:       {100 * res['rel_rmse']:.2f} % (median |rel| "
          f"{100 * res['median_rel_error']:.2f} %, 95th percentile {100 * res['p95_rel_error']:.2f} %)")
    print(f"  Cycles' own noise (2 x {args.samples} spp averaged): {100 * res['cycles_noise_rel_rmse_of_mean']:.2f} % RMSE")
    print("  per object (mean ratio - 1): " + ", ".join(f"{k} {100 * v:+.1f} %"
                                                        for k, v in res["per_object_mean_ratio_minus_1"].items()))
    print("  seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in res["seconds"].items()))
    print(f"wrote {os.path.relpath(fig, scene_library.ROOT)} and {tag}.json")
    return 0
