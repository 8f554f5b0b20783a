"""``python -m prtt_addon.dev.bench contact``: the paper's central picture, measured.

A minimally tessellated floor (2 triangles, 4 vertices) under the 69K-triangle
bunny and a box, lit by Blender's "city" HDRI, glossy floor. Rendered with
the preview's shaders (offscreen, blender/preview/renderer.py) three ways:

* fragment TPFL with transfer textures (PRTT, the paper's method);
* vertex TPFL with per-vertex transfer on the same 2-triangle floor (the
  traditional baseline: the floor's 4 vertices never see the contact shadow);
* vertex TPFL on a floor subdivided to 32 x 32 quads (2048 triangles): the
  baseline's only remedy, more vertices.

Against a ground truth that needs neither textures nor vertices: at every
pixel's surface point the transfer is ray traced with ``--ref-rays`` rays and
shaded with the same model (core/preview/reference.traced_reference). Errors
are relative RMSE (RMSE / mean of the reference) over the floor's pixels and
over all pixels. Images go to docs/images/contact_*.png.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np

from . import meshgen as mg
from . import scene_library

ROOT = scene_library.ROOT
DOCS_IMAGES = os.path.join(ROOT, "docs", "images")

FLOOR_MATERIAL = {"base_color": [0.75, 0.72, 0.68], "roughness": 0.4}
BUNNY_MATERIAL = {"base_color": [0.8, 0.55, 0.35], "roughness": 0.5}
BOX_MATERIAL = {"base_color": [0.3, 0.45, 0.7], "roughness": 0.3}


def _objects(floor_subdiv: int):
    bunny, uv = scene_library.bunny_unwrapped(256)
    bunny = mg.Mesh(bunny.vertices * 1.6, bunny.faces, bunny.normals)         # 0.8 m tall
    bunny.uvs = uv
    box = mg.box((0.5, 0.5, 0.5), (0.75, 0.45, 0.25)).transformed(rotate_z=0.4)
    return [("floor", mg.plane(4.0, 4.0, subdiv=floor_subdiv)), ("bunny", bunny), ("box", box)]


def build(floor_subdiv: int, resolution: int):
    from ...core.model.scene import validate
    objs = _objects(floor_subdiv)
    sc = mg.assemble(objs, resolution=resolution, keep_uvs=True,
                     resolutions={"bunny": 256, "box": 128})
    sc.materials = [dict(name="floor", **FLOOR_MATERIAL), dict(name="bunny", **BUNNY_MATERIAL),
                    dict(name="box", **BOX_MATERIAL)]
    sc.material_id = sc.object_id.copy()
    validate(sc)
    return sc


def camera(width: int, height: int):
    from ...core.preview.reference import look_at, perspective
    eye = np.array([1.35, -1.65, 0.95])
    vp = perspective(42.0, width / height) @ look_at(eye, (0.2, 0.15, 0.22))
    return vp, np.array([*eye, 1.0])


def experiment(width: int = 480, height: int = 320, *, resolution: int = 512, rays: int = 256,
               ref_rays: int = 1024, dense: int = 32, env: str = "city", work_dir: str | None = None) -> dict:
    """Render the three pictures and the ground truth; returns images and errors."""
    from ...blender.preview.offscreen import ensure_gpu
    from ...blender.preview.renderer import Renderer, render_offscreen
    from ...core.bake.pipeline.context import BakeSettings
    from ...core.bake.pipeline.runner import bake_scene
    from ...core.light.envmap import environment_light
    from ...core.preview.pack import from_core_scene
    from ...core.preview.reference import trace_pixels, traced_reference
    ensure_gpu()
    light = environment_light(env, 5)
    vp, cam = camera(width, height)
    out = {"seconds": {}}
    tmp = tempfile.TemporaryDirectory(prefix="prtt-contact-") if work_dir is None else None
    base = work_dir or tmp.name
    try:
        previews = {}
        for key, subdiv in (("coarse", 1), ("dense", dense)):
            sc = build(subdiv, resolution)
            d = os.path.join(base, key)
            t = time.perf_counter()
            bake_scene(sc, d, BakeSettings(rays=rays, vertex_mode=True, bounces=0))
            out["seconds"][f"bake_{key}"] = time.perf_counter() - t
            previews[key] = from_core_scene(sc, d, light, 5)
        r = Renderer()
        shots = {"fragment": (previews["coarse"], "tpfl"), "vertex": (previews["coarse"], "vertex-tpfl"),
                 "vertex_dense": (previews["dense"], "vertex-tpfl")}
        images = {}
        for name, (ps, mode) in shots.items():
            images[name], _ = render_offscreen(r, ps, mode, vp, cam, width, height)
        r.free()
        ps = previews["coarse"]
        hits = trace_pixels(ps, vp, width, height)
        t = time.perf_counter()
        images["reference"], _ = traced_reference(ps, vp, cam, width, height, rays=ref_rays, hits=hits)
        out["seconds"]["reference"] = time.perf_counter() - t
    finally:
        if tmp is not None:
            tmp.cleanup()
    floor_k = [m.name for m in ps.meshes].index("floor")
    interior = hits.hit & (hits.edge_px > 0.5)
    masks = {"floor": interior & (hits.mesh == floor_k), "all": interior}
    ref = images["reference"][..., :3]
    errors = {}
    for name in ("fragment", "vertex", "vertex_dense"):
        img = images[name][..., :3]
        errors[name] = {k: float(np.sqrt(np.mean((img[m] - ref[m]) ** 2)) / ref[m].mean())
                        for k, m in masks.items()}
    out.update(images=images, errors=errors, masks=masks,
               triangles={k: sum(m.triangles for m in p.meshes) for k, p in previews.items()},
               floor_triangles={k: next(m.triangles for m in p.meshes if m.name == "floor")
                                for k, p in previews.items()})
    return out


#: The city HDRI is bright (floor radiance ~2.5): pictures are exposed down.
EXPOSURE = 0.35


def save_figure(res: dict, folder: str) -> list:
    """PNG per picture and one labelled side-by-side figure."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ...core.io.image_write import srgb_encode, write_image
    os.makedirs(folder, exist_ok=True)
    paths = []
    for name, img in res["images"].items():
        paths.append(write_image(os.path.join(folder, f"contact_{name}.png"), img, exposure=EXPOSURE))
    ft = res["floor_triangles"]
    titles = {"vertex": f"vertex TPFL, floor {ft['coarse']} triangles",
              "fragment": f"PRTT: fragment TPFL, floor {ft['coarse']} triangles",
              "vertex_dense": f"vertex TPFL, floor {ft['dense']} triangles",
              "reference": "ray-traced transfer per pixel"}
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.6))
    for ax, name in zip(axes, ("vertex", "fragment", "vertex_dense", "reference")):
        img = res["images"][name]
        rgb = srgb_encode(EXPOSURE * img[::-1, :, :3]) * img[::-1, :, 3:] + (1 - img[::-1, :, 3:])
        ax.imshow(np.clip(rgb, 0, 1))
        ax.set_axis_off()
        e = res["errors"].get(name)
        sub = f"\nfloor error {100 * e['floor']:.1f}%, image {100 * e['all']:.1f}%" if e else "\n(ground truth)"
        ax.set_title(titles[name] + sub, fontsize=9)
    fig.tight_layout()
    path = os.path.join(folder, "contact_shadow.png")
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return paths + [path]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench contact", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", default="480x320")
    p.add_argument("--resolution", type=int, default=512, help="floor texture resolution")
    p.add_argument("--rays", type=int, default=256, help="bake rays per texel / vertex")
    p.add_argument("--ref-rays", type=int, default=1024, help="ground-truth rays per pixel")
    p.add_argument("--env", default="city")
    p.add_argument("--out", default=DOCS_IMAGES, help="folder for the PNGs")
    args = p.parse_args(argv)
    import bpy  # noqa: F401  (Blender as a module provides gpu)
    w, h = (int(v) for v in args.size.split("x"))
    res = experiment(w, h, resolution=args.resolution, rays=args.rays, ref_rays=args.ref_rays, env=args.env)
    print(f"floor: {res['floor_triangles']['coarse']} triangles (dense: {res['floor_triangles']['dense']}); "
          f"scene {res['triangles']['coarse']} triangles; {w}x{h} px; light '{args.env}'")
    print(f"{'picture':14s} {'floor rel. RMSE':>16s} {'image rel. RMSE':>16s}")
    for name, e in res["errors"].items():
        print(f"{name:14s} {100 * e['floor']:15.2f}% {100 * e['all']:15.2f}%")
    print("seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in res["seconds"].items()))
    for path in save_figure(res, args.out):
        print(f"wrote {os.path.relpath(path, ROOT)}")
    return 0
