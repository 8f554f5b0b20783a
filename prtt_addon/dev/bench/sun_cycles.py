"""``python -m prtt_addon.dev.bench sun``: a Sun lamp's light and shadows in
PRTT's preview against Cycles (issue 48, item 2).

A scene built with bpy: a 4 m floor (two triangles), a 0.5 m box on it and a
1.2 m plank held 0.4 m over the floor, Diffuse BSDF (or, ``glossy``, a
Principled floor of roughness 0.3), under one Sun lamp of
strength 3 W/m² at 50 degrees from the zenith, of angle ``angle`` (0.5 and 5
degrees: Blender's default and a soft sun) and a dim band-limited sky (the
"city" HDRI in 5 bands, exact for the transfer). The add-on unwraps and bakes it
(its sun mask, SUN_RAYS rays a texel); its preview renders the camera's view
offscreen (diffuse mode), Cycles the same view with direct light only (no
bounce, 0.01 px pixel filter, ``samples``, two seeds for its own noise).

Measured over the pixels more than a pixel from a triangle edge: relative
RMSE of the image and of the shadowed floor (Cycles below half the lit
floor's value: the umbra and most of the penumbra). And the penumbrae: an
orthographic view 2 cm over the floor across the plank's shadow, the sky
off, rendered by both (strip_profiles), gives the visible fraction of the
sun along a line; the 10 %-90 % widths of its two edges, in mm, beside the
floor's texel.

``--sky`` (issue 48, item 3): the same scene under Blender's Sky Texture
(single scattering, its sun disc at the same direction, ``angle`` its size)
instead of the lamp and the band-limited sky: PRTT with the disc baked as
the sun (the default, ``scene.prtt.sky_sun``) and with it left in the
World's SH (``sky_sun`` off, as before), both against Cycles. The sky itself
is not band-limited there: what remains is the sky's own SH error. The strip
has the sky in it, so its profiles are normalised lit = 1, umbra = 0.

``--hdri NAME`` (issue 48, item 3): the scene lit by one of Blender's studio
HDRIs as it is (not band-limited, no lamp), with its sun extracted
(``scene.prtt.hdri_sun``: core/light/sun_extract.py) and without (the sun in
the SH), both against Cycles; profiles normalised as for the sky.

``--memory SIZES`` (issue 48: memory measured like time): the demo-class
room (scene_library.room_scene, one atlas of each size, one relightable
bounce) baked in a child process of its own without a sun and with a 0.5°
sun at Sun Shadow Detail 1 and 2: the process's peak RSS (VmHWM) beside
the bake's memory estimate (memory_plan), its seconds and the masks'.
"""
from __future__ import annotations

import argparse
import math
import os
import tempfile
import time

import numpy as np

from . import meshgen as mg

SUN_ELEVATION = 40.0          # degrees above the horizon (50 from the zenith)
SUN_AZIMUTH = 30.0            # degrees from +x towards +y
SUN_STRENGTH = 3.0
#: The floor's base colour: diffuse (False) and glossy (True, a Principled BSDF of roughness 0.3).
FLOOR_ALBEDO = {False: 0.7, True: 0.6}
#: The World: Blender's "city" HDRI band-limited to 5 bands (cycles_compare.band_limited_environment)
#: at this strength, so that the sky lights the shadows at about a fifth of the sun.
SKY_STRENGTH = 0.1
FLOOR = 4.0
PLANK = ((1.2, 0.15, 0.03), (0.0, 0.55, 0.4))        # size, centre
BOX = ((0.5, 0.5, 0.5), (-0.7, -0.3, 0.25))


def sun_direction() -> np.ndarray:
    e, a = math.radians(SUN_ELEVATION), math.radians(SUN_AZIMUTH)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


#: An HDRI's strength in ``--hdri``: city's sun (47.8 degrees up) is then about SUN_STRENGTH W/m².
HDRI_STRENGTH = 1.0
#: The Sky Texture's strength (its Background's) in ``--sky``: its sun at 40 degrees gives about
#: 147 W/m² at strength 1 (Blender's physical sky), so this makes it about SUN_STRENGTH.
SKY_TEXTURE_STRENGTH = 0.02


def sky_world(bpy, angle_deg: float):
    """A World of Blender's Sky Texture (single scattering; Nishita before Blender 5) whose sun disc
    is at sun_direction(), of ``angle_deg``; Background strength SKY_TEXTURE_STRENGTH."""
    w = bpy.data.worlds.new("Sky")
    if hasattr(w, "use_nodes") and bpy.app.version < (5, 0, 0):
        w.use_nodes = True
    nt = w.node_tree
    for n in [n for n in nt.nodes if n.bl_idname != "ShaderNodeOutputWorld"]:
        nt.nodes.remove(n)
    out = next(n for n in nt.nodes if n.bl_idname == "ShaderNodeOutputWorld")
    bg = nt.nodes.new("ShaderNodeBackground")
    sky = nt.nodes.new("ShaderNodeTexSky")
    types = [i.identifier for i in sky.bl_rna.properties["sky_type"].enum_items]
    sky.sky_type = "SINGLE_SCATTERING" if "SINGLE_SCATTERING" in types else "NISHITA"
    sky.sun_disc, sky.sun_size = True, math.radians(angle_deg)
    # Blender's sun: (cos e sin r, cos e cos r, sin e) for elevation e and rotation r
    sky.sun_elevation, sky.sun_rotation = math.radians(SUN_ELEVATION), math.radians(90.0 - SUN_AZIMUTH)
    bg.inputs["Strength"].default_value = SKY_TEXTURE_STRENGTH
    nt.links.new(sky.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    return w


def build(bpy, out_dir: str, *, angle_deg: float, resolution: int, rays: int = 256, glossy: bool = False,
          roughness: float = 0.3,
          light: str = "lamp", sky_sun: bool = True, bounces: int = 0, sun_detail: int = 1,
          sun_refine: bool = True, sun_edges: bool = True):
    """The scene in the current (empty) file, unwrapped and baked with the add-on; returns the manifest.
    ``light``: "lamp" (a Sun lamp and a band-limited sky) or "sky" (a Sky Texture, its disc baked as
    the sun where ``sky_sun``)."""
    import mathutils

    from . import scene_build as sb
    from .cycles_compare import band_limited_environment
    grey = sb.principled("grey", base_color=(FLOOR_ALBEDO[False],) * 3, diffuse=True)
    floor_mat = (sb.principled("floor", base_color=(FLOOR_ALBEDO[True],) * 3, roughness=roughness) if glossy
                 else grey)
    sb.mesh_object("floor", mg.plane(FLOOR, FLOOR, subdiv=1), material=floor_mat)
    sb.mesh_object("box", mg.box(*BOX), material=grey)
    sb.mesh_object("plank", mg.box(*PLANK), material=grey)
    scene = bpy.context.scene
    os.makedirs(out_dir, exist_ok=True)
    if light == "sky":
        scene.world = sky_world(bpy, angle_deg)
    elif light.startswith("hdri:"):
        from ...core.light.envmap import builtin_environment_path
        scene.world = sb.environment_world("HDRI", builtin_environment_path(light[5:]), strength=HDRI_STRENGTH)
    else:
        # A band-limited sky (its light exact in 5 bands), dim beside the sun: what lights the shadows.
        env = os.path.join(out_dir, "band_limited_city.exr")
        band_limited_environment(env)
        scene.world = sb.environment_world("BandLimited", env, strength=SKY_STRENGTH)
        lamp = bpy.data.lights.new("Sun", "SUN")
        lamp.energy, lamp.angle = SUN_STRENGTH, math.radians(angle_deg)
        ob = bpy.data.objects.new("Sun", lamp)
        ob.rotation_euler = mathutils.Vector(tuple(sun_direction())).to_track_quat("Z", "Y").to_euler()
        scene.collection.objects.link(ob)
    scene.camera = sb.camera_object("Camera", (1.6, -2.6, 2.2), (-0.1, 0.2, 0.0), fov_y_deg=50.0)
    scene.view_settings.view_transform = "Standard"
    bpy.context.view_layer.update()
    st = scene.prtt
    st.output_dir, st.resolution, st.rays, st.bounces = out_dir, resolution, rays, bounces
    st.bounce_rays = 256
    st.texture_sets, st.unwrap_method, st.light_source = "ATLAS", "SMART", "WORLD"
    st.sky_sun = st.hdri_sun = sky_sun
    st.sun_detail = sun_detail
    for o in bpy.context.view_layer.objects:
        o.select_set(o.type == "MESH")
    if bpy.ops.prtt.unwrap() != {"FINISHED"}:
        raise RuntimeError("unwrap failed")
    from ...blender.bake.run import bake_blocking
    overrides = {k: False for k, on in (("sun_refine", sun_refine), ("sun_edges", sun_edges)) if not on}
    outcome = bake_blocking(bpy.context, force=True, overrides=overrides or None)
    if outcome.status != "done":
        raise RuntimeError(outcome.message)
    return outcome.manifest


def _reference_sun(light: str, manifest: dict):
    """(direction, mean irradiance W/m²) of the sun whose shadows are
    measured: the baked one, else an HDRI's (extracted from its image as the
    bake would: the same sun, left in the SH), else None (sun_direction())."""
    s = manifest.get("sun")
    if s:
        return np.asarray(s["direction"], np.float64), float(s["strength"] * np.mean(s["color"]))
    if light.startswith("hdri:"):
        from ...core.io.image_io import read_hdr_image
        from ...core.light.envmap import builtin_environment_path
        from ...core.light.sun_extract import extract_sun
        found = extract_sun(read_hdr_image(builtin_environment_path(light[5:])))[0]
        if found is not None:
            return np.asarray(found.direction, np.float64), float(np.mean(found.energy)) * HDRI_STRENGTH
    return None


def _normalised(f: np.ndarray) -> np.ndarray:
    """A lit - shadow - lit profile with the sky in it as 0 at its umbra and 1
    on each side's own lit plateau (the median of its outer eighth): the
    skylight differs on the two sides of a plank."""
    n = len(f)
    k = int(np.argmin(f))
    lo = float(f.min())
    left, right = float(np.median(f[:max(1, n // 8)])), float(np.median(f[-max(1, n // 8):]))
    out = np.empty_like(f, dtype=np.float64)
    out[:k] = (f[:k] - lo) / max(left - lo, 1e-12)
    out[k:] = (f[k:] - lo) / max(right - lo, 1e-12)
    return out


def strip_profiles(bpy, d: str, *, samples: int, size=(48, 480), glossy: bool = False, sky: bool = False,
                   towards=None) -> dict:
    """The visible fraction of the sun across the plank's shadow on the floor,
    from above (an orthographic camera 2 cm over the floor, under the plank,
    the World switched off for it): PRTT's preview and Cycles', each divided
    by the unshadowed sun's radiance; rows along y (across the shadow's long
    edges), averaged over the columns. ``sky``: a Sky Texture World holds the
    sun, so it stays on and each profile is normalised (lit 1, umbra 0).
    Returns {"y" (rows,), "prtt", "cycles", "texel_m": the floor's texel in metres}."""
    from ...blender.blendfile import blender_log_muted
    from ...blender.preview.offscreen import render_scene
    from ...blender.shared import UV_MAP
    from .cycles_compare import render_cycles
    scene = bpy.context.scene
    l = sun_direction() if towards is None else np.asarray(towards, np.float64)
    t = (PLANK[1][2] - PLANK[0][2] / 2) / l[2]
    y_mid = PLANK[1][1] - t * l[1]                  # the shadow's centre line on the floor
    x_mid = PLANK[1][0] - t * l[0]
    span = 0.3                                      # metres across (y), 0.03 along (x)
    cam = bpy.data.cameras.new("Strip")
    cam.type, cam.ortho_scale, cam.sensor_fit = "ORTHO", span, "AUTO"
    cam.clip_start, cam.clip_end = 0.001, 1.0
    ob = bpy.data.objects.new("Strip", cam)
    ob.location = (x_mid, y_mid, 0.02)
    scene.collection.objects.link(ob)
    bg = next(n for n in scene.world.node_tree.nodes if n.bl_idname == "ShaderNodeBackground").inputs["Strength"]
    keep_strength, keep_cam = bg.default_value, scene.camera
    if not sky:
        bg.default_value = 0.0
    scene.camera = ob
    bpy.context.view_layer.update()
    w, h = size
    try:
        prtt, _, _, _ = render_scene(bpy.context, mode="diffuse", size=(w, h), bounces=False)
        with blender_log_muted():
            cyc = render_cycles(bpy, os.path.join(d, "strip.exr"), (w, h), samples, 0, 3)
    finally:
        bg.default_value, scene.camera = keep_strength, keep_cam
        bpy.data.objects.remove(ob)
    # The floor's albedo times the unshadowed sun on it (facing up); the strip is drawn in diffuse mode.
    unlit = FLOOR_ALBEDO[bool(glossy)] / math.pi * SUN_STRENGTH * l[2]
    floor = bpy.data.objects["floor"].data
    uv = np.array([d.uv[:] for d in floor.uv_layers[UV_MAP].data])
    res = scene.prtt.resolution
    texel = FLOOR / (np.ptp(uv[:, 0]) * res)
    profiles = {k: v[..., :3].mean(axis=(1, 2)) for k, v in (("prtt", prtt), ("cycles", cyc))}
    for k, f in profiles.items():
        profiles[k] = _normalised(f) if sky else f / unlit
    return {"y": y_mid + (np.arange(h) + 0.5 - h / 2) * span / h, **profiles, "texel_m": float(texel)}


def penumbrae(y: np.ndarray, f: np.ndarray) -> list:
    """The widths (metres) of the 10 %-90 % ramps of a profile ``f`` along
    ``y`` that goes lit - shadow - lit: the first ramp down and the last up,
    by linear interpolation of the crossings."""
    def cross(level, idx):
        i = idx
        return y[i] + (level - f[i]) * (y[i + 1] - y[i]) / (f[i + 1] - f[i])
    down = [i for i in range(len(f) - 1) if f[i] >= 0.9 > f[i + 1]], [i for i in range(len(f) - 1)
                                                                    if f[i] >= 0.1 > f[i + 1]]
    up = [i for i in range(len(f) - 1) if f[i] <= 0.1 < f[i + 1]], [i for i in range(len(f) - 1)
                                                                  if f[i] <= 0.9 < f[i + 1]]
    if not (all(down) and all(up)):
        return [float("nan"), float("nan")]
    return [abs(cross(0.1, down[1][0]) - cross(0.9, down[0][0])), abs(cross(0.9, up[1][-1]) - cross(0.1, up[0][-1]))]


class _without_sun_bounce:
    """``with _without_sun_bounce():`` the preview relights relightable bounces
    with the environment alone (PreviewScene.bounce_light = light): what it
    drew before the sun's bounce, for the comparison."""

    def __enter__(self):
        from ...core.preview import pack
        self.prop = pack.PreviewScene.bounce_light
        pack.PreviewScene.bounce_light = property(lambda ps: ps.light)

    def __exit__(self, *exc):
        from ...core.preview import pack
        pack.PreviewScene.bounce_light = self.prop


def compare(angle_deg: float = 0.5, size=(320, 180), *, samples: int = 256, resolution: int = 512,
            glossy: bool = False, work_dir: str | None = None, light: str = "lamp", sky_sun: bool = True,
            bounces: int = 0, sun_detail: int = 1, sun_refine: bool = True, roughness: float = 0.3,
            sun_edges: bool = True) -> dict:
    import bpy

    from ... import register
    from ...blender.blendfile import blender_log_muted
    from ...blender.preview.drawlist import collect
    from ...blender.preview.offscreen import camera_view, render_scene
    from ...core.preview.reference import trace_pixels
    from .cycles_compare import render_cycles
    tmp = tempfile.TemporaryDirectory(prefix="prtt-sun-") if work_dir is None else None
    d = work_dir or tmp.name
    try:
        bpy.ops.wm.read_factory_settings(use_empty=True)
        if not hasattr(bpy.types.Scene, "prtt"):
            register()
        t = time.perf_counter()
        manifest = build(bpy, os.path.join(d, "textures"), angle_deg=angle_deg, resolution=resolution,
                         glossy=glossy, light=light, sky_sun=sky_sun, bounces=bounces, sun_detail=sun_detail,
                         sun_refine=sun_refine, roughness=roughness, sun_edges=sun_edges)
        t_bake = time.perf_counter() - t
        mode = "tpfl" if glossy else "diffuse"
        prtt, _, status, _ = render_scene(bpy.context, mode=mode, size=size, bounces=bounces > 0)
        no_sun_bounce = None
        if bounces:
            with _without_sun_bounce():
                no_sun_bounce = render_scene(bpy.context, mode=mode, size=size, bounces=True)[0]
        with blender_log_muted():
            cyc = [render_cycles(bpy, os.path.join(d, f"cycles{s}.exr"), size, samples, bounces, s) for s in (1, 2)]
        ps, _ = collect(bpy.context, use_bounces=False)
        vp, _ = camera_view(bpy.context.scene.camera, bpy.context.evaluated_depsgraph_get(), *size,
                            bpy.context.scene)
        hits = trace_pixels(ps, vp, *size)
        ref_sun = _reference_sun(light, manifest)
        strip = strip_profiles(bpy, d, samples=samples, glossy=glossy, sky=light != "lamp",
                               towards=None if ref_sun is None else ref_sun[0])
    finally:
        if tmp is not None:
            tmp.cleanup()
    mask = hits.hit & (hits.edge_px > 1.0) & (prtt[..., 3] > 0.5) & (cyc[0][..., 3] > 0.99)
    ref = 0.5 * (cyc[0] + cyc[1])
    a, b = prtt[..., :3].astype(np.float64), ref[..., :3].astype(np.float64)
    yb = b.mean(axis=2)
    floor_k = [m.name for m in ps.meshes].index("floor")
    on_floor = mask & (hits.mesh == floor_k)
    lit = float(np.quantile(yb[on_floor], 0.9))
    if light.startswith("hdri:") and ref_sun is not None:
        # an HDRI's sky is bright: the shadow is where Cycles has lost half the sun's light on the floor
        albedo = FLOOR_ALBEDO[bool(glossy)]
        shadow = on_floor & (yb < lit - 0.5 * albedo / math.pi * ref_sun[1] * max(ref_sun[0][2], 0.0))
    else:
        shadow = on_floor & (yb < 0.5 * lit)
    noise = float(np.sqrt(np.mean((cyc[0][..., :3][mask] - cyc[1][..., :3][mask]) ** 2) / 2.0) / np.mean(b[mask]))
    pen = {k: penumbrae(strip["y"], strip[k]) for k in ("prtt", "cycles")}

    def rel(m):
        return float(np.sqrt(np.mean((a[m] - b[m]) ** 2)) / np.mean(b[m]))

    without = (float(np.sqrt(np.mean((no_sun_bounce[..., :3][mask] - b[mask]) ** 2)) / np.mean(b[mask]))
               if no_sun_bounce is not None else float("nan"))
    return {"angle_deg": angle_deg, "size": list(size), "samples": samples, "resolution": resolution,
            "bounces": bounces, "rel_rmse_without_sun_bounce": without,
            "glossy": glossy, "light": light, "sky_sun": sky_sun, "sun": manifest.get("sun"), "pixels": int(mask.sum()), "shadow_pixels": int(shadow.sum()),
            "rel_rmse": rel(mask), "rel_rmse_shadow": rel(shadow) if shadow.sum() >= 20 else float("nan"),
            "mean_ratio_minus_1": float(a[mask].mean() / b[mask].mean() - 1.0),
            "cycles_noise": noise / math.sqrt(2.0), "bake_s": t_bake,
            "sun_seconds": sum(s.get("sun_seconds", 0.0) for s in manifest["sets"]),
            "bake_seconds": float(manifest["seconds"]["total"]),
            "notes": [t for _, t in status.messages], "texel_m": strip["texel_m"],
            "penumbra_m": pen, "strip": strip,
            "images": {"prtt": prtt, "cycles": ref, "mask": mask, "shadow": shadow}}


def _cycles_glossy(bpy, path: str, size, samples: int, seed: int) -> np.ndarray:
    """Cycles' glossy light of the scene's lamps alone: Glossy Direct times Glossy
    Color (the World's strength 0, no bounce), (H, W, 3), row 0 at the bottom."""
    import OpenEXR
    layer = bpy.context.view_layer
    layer.use_pass_glossy_direct = layer.use_pass_glossy_color = True
    r = bpy.context.scene.render
    fmt = r.image_settings
    if hasattr(fmt, "media_type"):
        fmt.media_type = "MULTI_LAYER_IMAGE"                  # Blender 5: its one format, OPEN_EXR_MULTILAYER
    else:
        fmt.file_format = "OPEN_EXR_MULTILAYER"               # Blender 4
    try:
        from .cycles_compare import cycles_still
        cycles_still(bpy, path, size, samples, 0, seed)
        with OpenEXR.File(path) as f:
            # one part per pass in Blender 5 ("Glossy Direct"), one list of channels in Blender 4 ("GlossDir")
            ch = {k: v for part in f.parts for k, v in part.channels.items()}

            def plane(*names):
                key = next((k for k in ch if any(k.endswith(f".{n}") or f".{n}." in k for n in names)), None)
                if key is None:
                    raise RuntimeError(f"{path}: no {names[0]} pass among {sorted(ch)}")
                px = np.array(ch[key].pixels, np.float32)
                return px[..., :3] if px.ndim == 3 else px
            out = plane("Glossy Direct", "GlossDir") * plane("Glossy Color", "GlossCol")
    finally:
        if hasattr(fmt, "media_type"):
            fmt.media_type = "IMAGE"
        fmt.file_format = "OPEN_EXR"
        layer.use_pass_glossy_direct = layer.use_pass_glossy_color = False
    return out[::-1].copy()


def glossy_highlight(size=(320, 180), *, samples: int = 256, resolution: int = 512, angle_deg: float = 0.5,
                     roughness: float = 0.3,
                     work_dir: str | None = None) -> dict:
    """The sun's highlight on the glossy floor (Principled, ``roughness``) seen
    from where it mirrors the sun: PRTT's lobe alone ((TPFL - diffuse) with the
    sun less without it) against Cycles' Glossy Direct x Glossy Color with the
    World off. Returns the energy ratio and relative RMSE over the floor where
    Cycles' highlight is above a tenth of its peak, and the peaks."""
    import bpy

    from ... import register
    from ...blender.blendfile import blender_log_muted
    from ...blender.preview.offscreen import render_scene
    from . import scene_build as sb
    tmp = tempfile.TemporaryDirectory(prefix="prtt-gloss-") if work_dir is None else None
    d = work_dir or tmp.name
    try:
        bpy.ops.wm.read_factory_settings(use_empty=True)
        if not hasattr(bpy.types.Scene, "prtt"):
            register()
        build(bpy, os.path.join(d, "textures"), angle_deg=angle_deg, resolution=resolution, glossy=True,
              roughness=roughness)
        scene = bpy.context.scene
        l = sun_direction()
        target = np.array([0.3, -0.3, 0.0])
        eye = target + 3.5 * np.array([-l[0], -l[1], l[2]])       # the floor mirrors the sun at the target
        scene.camera = sb.camera_object("Mirror", tuple(eye), tuple(target), fov_y_deg=40.0)
        bpy.context.view_layer.update()
        lamp = bpy.data.objects["Sun"]
        img = {}
        for on in (True, False):
            lamp.hide_render = not on
            bpy.context.view_layer.update()
            for mode in ("tpfl", "diffuse"):
                img[mode, on] = render_scene(bpy.context, mode=mode, size=size, bounces=False)[0][..., :3]
        lamp.hide_render = False
        bpy.context.view_layer.update()
        prtt = (img["tpfl", True] - img["tpfl", False]) - (img["diffuse", True] - img["diffuse", False])
        bg = next(n for n in scene.world.node_tree.nodes if n.bl_idname == "ShaderNodeBackground")
        bg.inputs["Strength"].default_value = 0.0
        with blender_log_muted():
            cyc = [_cycles_glossy(bpy, os.path.join(d, f"gloss{s}.exr"), size, samples, s) for s in (1, 2)]
    finally:
        if tmp is not None:
            tmp.cleanup()
    ref = 0.5 * (cyc[0] + cyc[1])
    yr = ref.mean(axis=2)
    hi = yr > 0.1 * float(yr.max())
    a, b = prtt[hi].astype(np.float64), ref[hi].astype(np.float64)
    return {"angle_deg": angle_deg, "pixels": int(hi.sum()), "energy_ratio": float(a.sum() / b.sum()),
            "rel_rmse": float(np.sqrt(np.mean((a - b) ** 2)) / b.mean()),
            "peak_prtt": float(prtt.mean(axis=2).max()), "peak_cycles": float(yr.max()),
            "cycles_noise": float(np.sqrt(np.mean((cyc[0][hi] - cyc[1][hi]) ** 2) / 2) / b.mean() / math.sqrt(2)),
            "images": {"prtt": prtt, "cycles": ref}}


_MEMORY_CHILD = r"""
import json, math, sys, tempfile
from prtt_addon.core.bake.pipeline.context import BakeSettings
from prtt_addon.core.bake.pipeline.runner import bake_scene
from prtt_addon.core.light.envmap import environment_light
from prtt_addon.core.light.sun import Sun
from prtt_addon.dev.bench import scene_library
size, detail = int(sys.argv[1]), int(sys.argv[2])
sc = scene_library.room_scene(size, atlas=True, materials=True)
sun = Sun(direction=(0.45, -0.3, 0.84), angle=math.radians(0.5), strength=3.0) if detail else None
with tempfile.TemporaryDirectory(prefix="prtt-sun-memory-") as d:
    m = bake_scene(sc, d, BakeSettings(bounces=1, sun_detail=max(detail, 1)),
                   light=environment_light("forest", 5, 1.0, 0.0), sun=sun)
hwm = next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM:"))
print(json.dumps({"peak_rss_mb": hwm / 1024.0, "estimate_mb": m.get("memory", {}).get("estimate_mb"),
                  "seconds": m["seconds"]["total"], "texels": m["totals"]["texels"],
                  "sun_s": sum(s.get("sun_seconds", 0.0) for s in m["sets"])}))
"""


def memory_rows(sizes, details=(0, 1, 2)):
    """One child process a (size, detail) bake (detail 0: no sun), yielded as
    each ends: its peak RSS, the bake's estimate, seconds (module docstring,
    ``--memory``)."""
    import json
    import subprocess
    import sys

    from . import scene_library
    for size in sizes:
        for f in details:
            r = subprocess.run([sys.executable, "-c", _MEMORY_CHILD, str(size), str(f)], capture_output=True,
                               text=True, env=dict(os.environ, PYTHONPATH=scene_library.ROOT), timeout=3600)
            if r.returncode != 0:
                raise RuntimeError(f"the {size}² bake with detail {f} failed: {r.stderr[-1500:]}")
            yield dict(size=size, detail=f, **json.loads(r.stdout.strip().splitlines()[-1]))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench sun", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--angles", default="0.5,5", help="the Sun's angles, degrees, comma-separated")
    p.add_argument("--size", default="320x180")
    p.add_argument("--samples", type=int, default=256, help="Cycles' samples a pixel")
    p.add_argument("--resolution", type=int, default=512, help="the atlas")
    p.add_argument("--glossy", action="store_true", help="a glossy floor (Principled, --roughness), TPFL")
    p.add_argument("--roughness", type=float, default=0.3, help="the glossy floor's roughness")
    p.add_argument("--sun-detail", default="1", help="the sun masks' detail (Sun Shadow Detail), "
                   "comma-separated: a row each")
    p.add_argument("--memory", metavar="SIZES", help="peak RSS of the room's bake in a process of its own at "
                   "each atlas size (comma-separated), without a sun and with one at Sun Shadow Detail 1 and 2, "
                   "beside the bake's estimate (no Cycles)")
    p.add_argument("--no-sun-refine", action="store_true", help="fine masks trace every texel's 64 rays "
                   "(sun_refine off: the masks before refinement)")
    p.add_argument("--edges", default="on", help="the sub-texel shadow edges (sun_edges): on, off or on,off "
                   "(a row each)")
    p.add_argument("--glossy-pass", action="store_true",
                   help="the sun's highlight on the glossy floor, seen where it mirrors the sun: PRTT's lobe "
                        "against Cycles' Glossy Direct x Glossy Color")
    p.add_argument("--bounces", type=int, default=0, help="PRTT's relightable bounce and Cycles' diffuse "
                   "bounces (with 1: also the preview without the sun's bounce)")
    p.add_argument("--hdri", metavar="NAME", help="a studio HDRI as the World (not band-limited): its sun "
                   "extracted (hdri_sun) and left in the SH, both against Cycles; --angles is then ignored")
    p.add_argument("--sky", action="store_true",
                   help="a Sky Texture World with its sun disc instead of the lamp: the disc baked as the sun "
                        "(sky_sun) and left in the World's SH (sky_sun off), both against Cycles")
    a = p.parse_args(argv)
    if a.memory:
        print("the room's bake (one relightable bounce) in a process of its own: peak RSS and the bake's estimate:")
        print(f"  {'atlas':>6}  {'sun':>14}  {'texels':>9}  {'peak MiB':>8}  {'estimate':>8}  {'est/peak':>8}  "
              f"{'bake s':>6}  {'mask s':>6}")
        for r in memory_rows([int(x) for x in a.memory.split(",")]):
            sun = "none" if r["detail"] == 0 else f"0.5 deg x{r['detail']}"
            print(f"  {r['size']:>5}²  {sun:>14}  {r['texels']:>9}  {r['peak_rss_mb']:8.0f}  {r['estimate_mb']:8.0f}  "
                  f"{r['estimate_mb'] / r['peak_rss_mb']:8.2f}  {r['seconds']:6.2f}  {r['sun_s']:6.2f}", flush=True)
        return 0
    w, h = (int(v) for v in a.size.split("x"))
    if a.glossy_pass:
        print(f"the sun's highlight on a glossy floor (roughness {a.roughness:g}), {w}x{h}, Cycles {a.samples} samples "
              f"(Glossy Direct x Color, World off), atlas {a.resolution}²:")
        print(f"  {'angle':>6}  {'energy PRTT/Cycles':>18}  {'RMSE':>7}  {'peak PRTT':>9}  {'peak Cycles':>11}  "
              f"{'Cycles noise':>12}  pixels")
        for ang in (float(x) for x in a.angles.split(",")):
            r = glossy_highlight((w, h), samples=a.samples, resolution=a.resolution, angle_deg=ang,
                                 roughness=a.roughness)
            print(f"  {ang:6.2f}  {r['energy_ratio']:18.3f}  {r['rel_rmse']:7.2%}  {r['peak_prtt']:9.3f}  "
                  f"{r['peak_cycles']:11.3f}  {r['cycles_noise']:12.2%}  {r['pixels']}", flush=True)
        return 0
    what = f"the {a.hdri} HDRI's sun" if a.hdri else "a Sky Texture's sun" if a.sky else "Sun lamp"
    print(f"{what} over a box and a plank, {w}x{h}, Cycles {a.samples} samples, {a.bounces} bounce(s), "
          f"atlas {a.resolution}², "
          f"{f'glossy floor (roughness {a.roughness:g}), TPFL' if a.glossy else 'diffuse, diffuse mode'}:")
    print(f"  {'angle':>6}  {'disc':>10}  {'image RMSE':>10}  {'shadow RMSE':>11}  {'mean':>7}  {'Cycles noise':>12}  "
          f"{'sun mask s':>10}  {'bake s':>6}  penumbrae PRTT / Cycles (mm; texel)")
    variants = ([(f"hdri:{a.hdri}", True), (f"hdri:{a.hdri}", False)] if a.hdri else
                [("sky", True), ("sky", False)] if a.sky else [("lamp", True)])
    details = [int(x) for x in a.sun_detail.split(",")]
    edges = [{"on": True, "off": False}[x.strip()] for x in a.edges.split(",")]
    if False in edges:
        print("  (-e: without the sub-texel shadow edges, --no-sun-edges: the mask alone)")
    runs = [(ang, light, sky_sun, f, e) for ang in ([0.0] if a.hdri else [float(x) for x in a.angles.split(",")])
            for light, sky_sun in variants for f in details for e in edges]
    for ang, light, sky_sun, f, e in runs:
        if True:
            r = compare(ang, (w, h), samples=a.samples, resolution=a.resolution, glossy=a.glossy, light=light,
                        sky_sun=sky_sun, bounces=a.bounces, sun_detail=f, sun_refine=not a.no_sun_refine,
                        roughness=a.roughness, sun_edges=e)
            disc = ("lamp" if light == "lamp" else "as sun" if r["sun"] else "in SH") + (f" x{f}" if f > 1 else "") + ("" if e else " -e")
            if a.hdri and r["sun"]:
                print(f"          extracted: a {math.degrees(r['sun']['angle']):.2f} degree disc of "
                      f"{r['sun']['strength']:.3g} W/m²", flush=True)
            print(f"  {ang:6.2f}  {disc:>10}  {r['rel_rmse']:10.2%}  {r['rel_rmse_shadow']:11.2%}  "
                  f"{r['mean_ratio_minus_1']:+7.2%}  {r['cycles_noise']:12.2%}  {r['sun_seconds']:10.2f}  {r['bake_seconds']:6.2f}  "
                  + " ".join(f"{1e3 * p:.1f}/{1e3 * c:.1f}" for p, c in zip(*r["penumbra_m"].values()))
                  + f" ({1e3 * r['texel_m']:.1f})", flush=True)
            if a.bounces:
                print(f"          {a.bounces} bounce(s): without the sun's bounce the image is "
                      f"{r['rel_rmse_without_sun_bounce']:.2%} from Cycles", flush=True)
            if r["sun"] and a.sky:
                print(f"          the sun measured from the sky: {r['sun']['strength']:.3g} W/m², colour "
                      f"{', '.join(f'{c:.3f}' for c in r['sun']['color'])}, "
                      f"{math.degrees(math.acos(min(1.0, float(np.dot(r['sun']['direction'], sun_direction()))))):.3f}"
                      f" degrees from the node's direction", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
