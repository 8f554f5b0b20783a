"""Pictures of issue 53's artefacts, before their fixes and at the defaults
(``bench quality --figures``), drawn by the preview's numpy twin
(core/preview/reference.reference_image: the GPU's bilinear lookups and
shading, on the CPU) in diffuse mode, so they need neither a GPU nor bpy:

* docs/images/quality_window.png: the room lit only through a window
  (bench/window_room.py, 512² atlas, 256 rays, no bounce) from inside,
  before (cosine rays, no filter, no validity) and now, beside the same bake
  at 8192 cosine rays (what the bench's traced reference converges to);
* docs/images/quality_contact.png: the floor from above beside the box
  resting on it, and the foot of the shed's single-plane back wall from
  inside and from outside (bench/contact_profile.py, 1.8 cm texels, 256
  rays), before (no texel validity) and now, beside the transfer traced at
  every pixel (traced_reference, 1024 rays: no texture at all).

Each row shares one exposure (its reference's mean), so brightness compares
across a row.
"""
from __future__ import annotations

import os
import tempfile

import numpy as np

from . import contact_profile as cp
from . import scene_library
from . import window_room as wr

DOCS_IMAGES = os.path.join(scene_library.ROOT, "docs", "images")
BEFORE_WINDOW = dict(guiding=False, guided_filter=False, texel_validity=False)


def _baked(sc, settings, light, d, name):
    from ...core.bake.pipeline.runner import bake_scene
    from ...core.preview.pack import from_core_scene
    out = os.path.join(d, name)
    bake_scene(sc, out, settings)
    return from_core_scene(sc, out, light, 5, use_bounces=False)


def window_images(size=(360, 240), resolution: int = 512, rays: int = 256, ref_rays: int = 8192) -> dict:
    """{"before", "now", "reference"}: (H, W, 4) images from inside the room."""
    from ...core.bake.pipeline.context import BakeSettings
    from ...core.light.envmap import environment_light
    from ...core.preview.reference import look_at, perspective, reference_image, trace_pixels
    sc = wr.build(resolution)
    light = environment_light("forest", 5)
    eye = np.array([-1.5, -1.8, 1.5])
    vp = perspective(70.0, size[0] / size[1]) @ look_at(eye, (0.6, 2.0, 0.7))
    cam = np.array([*eye, 1.0])
    base = dict(bounces=0, vertex_mode=False)
    runs = {"before": BakeSettings(rays=rays, **BEFORE_WINDOW, **base), "now": BakeSettings(rays=rays, **base),
            "reference": BakeSettings(rays=ref_rays, guiding=False, guided_filter=False, **base)}
    out, hits = {}, None
    with tempfile.TemporaryDirectory(prefix="prtt-quality-fig-") as d:
        for k, st in runs.items():
            ps = _baked(sc, st, light, d, k)
            hits = hits or trace_pixels(ps, vp, *size)
            out[k], _ = reference_image(ps, "diffuse", vp, cam, *size, hits=hits)
    return out


#: The contact figure's views: (name, scene, eye, target, vertical field of view in degrees), points in
#: the object's frame (turned by BOX_TURN about BOX_CENTRE, z up): the box's -x side from above, the
#: shed's back wall (x = -0.5) at its foot from inside and from outside.
CONTACT_VIEWS = (
    ("box", "box", (-0.25, 0.0, 0.6), (-0.25, 0.0, 0.0), 23.0),
    ("shed, inside", "shed", (-0.2, 0.05, 0.3), (-0.5, 0.0, 0.0), 45.0),
    ("shed, outside", "shed", (-0.8, 0.05, 0.3), (-0.5, 0.0, 0.0), 45.0),
)


def contact_images(size=(240, 200), resolution: int = 112, rays: int = 256, ref_rays: int = 1024) -> dict:
    """{view name: {"before", "now", "reference"}} for CONTACT_VIEWS."""
    from ...core.bake.pipeline.context import BakeSettings
    from ...core.light.envmap import environment_light
    from ...core.preview.reference import look_at, perspective, reference_image, trace_pixels, traced_reference
    light = environment_light("forest", 5)
    c, s = np.cos(cp.BOX_TURN), np.sin(cp.BOX_TURN)

    def world(p):
        x, y, z = p
        return np.array([cp.BOX_CENTRE[0] + c * x - s * y, cp.BOX_CENTRE[1] + s * x + c * y, z])

    out = {}
    with tempfile.TemporaryDirectory(prefix="prtt-quality-fig-") as d:
        scenes = {"box": cp.build(resolution), "shed": cp.build_shed(resolution)}
        baked = {(kind, k): _baked(sc, BakeSettings(rays=rays, bounces=0, texel_validity=k == "now"), light, d,
                                   f"{kind}-{k}")
                 for kind, sc in scenes.items() for k in ("before", "now")}
        for name, kind, eye, target, fov in CONTACT_VIEWS:
            eye = world(eye)
            up = (-s, c, 0.0) if kind == "box" else (0.0, 0.0, 1.0)
            vp = perspective(fov, size[0] / size[1]) @ look_at(eye, world(target), up=up)
            cam = np.array([*eye, 1.0])
            hits = trace_pixels(baked[(kind, "now")], vp, *size)
            imgs = {k: reference_image(baked[(kind, k)], "diffuse", vp, cam, *size, hits=hits)[0]
                    for k in ("before", "now")}
            imgs["reference"], _ = traced_reference(baked[(kind, "now")], vp, cam, *size, rays=ref_rays, hits=hits)
            out[name] = imgs
    return out


def _panel(ax, img, exposure, title):
    from ...core.io.image_write import srgb_encode
    rgb = srgb_encode(exposure * img[::-1, :, :3]) * img[::-1, :, 3:] + (1 - img[::-1, :, 3:])
    ax.imshow(np.clip(rgb, 0, 1))
    ax.set_axis_off()
    ax.set_title(title, fontsize=9)


def save(window: dict, contact: dict, folder: str = DOCS_IMAGES) -> list:
    """The two PNGs; returns their paths."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    os.makedirs(folder, exist_ok=True)
    paths = []
    fig, axes = plt.subplots(1, 3, figsize=(13.5, 3.4))
    exp = 0.45 / window["reference"][..., :3][window["reference"][..., 3] > 0].mean()
    for ax, (k, title) in zip(axes, (("before", "before: 256 cosine rays"),
                                     ("now", "now (defaults): 256 rays, guided, filtered"),
                                     ("reference", "8192 cosine rays"))):
        _panel(ax, window[k], exp, title)
    fig.tight_layout()
    paths.append(os.path.join(folder, "quality_window.png"))
    fig.savefig(paths[-1], dpi=80)
    plt.close(fig)
    fig, axes = plt.subplots(len(contact), 3, figsize=(9.5, 2.9 * len(contact)))
    for row, (label, imgs) in zip(axes, contact.items()):
        exp = 0.45 / imgs["reference"][..., :3][imgs["reference"][..., 3] > 0].mean()
        for ax, (k, title) in zip(row, (("before", "before (no texel validity)"), ("now", "now (defaults)"),
                                        ("reference", "traced at every pixel"))):
            _panel(ax, imgs[k], exp, f"{label}: {title}")
    fig.tight_layout()
    paths.append(os.path.join(folder, "quality_contact.png"))
    fig.savefig(paths[-1], dpi=80)
    plt.close(fig)
    return paths
