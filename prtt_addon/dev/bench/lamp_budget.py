"""``python -m prtt_addon.dev.bench lamps --budget``: what each point or spot
lamp costs (issue 49, item 3): the room-class scene (scene_library.room_scene,
its materials, one atlas) baked with 0, 1, 2 and 4 of BUDGET_LAMPS (no
bounce: the lamps' masks are what changes), each bake's seconds and its
masks' seconds and bytes, and the preview's frame time in TPFL and diffuse
(renderer.draw into an offscreen buffer, render_bench.time_frames: the
median of ``frames``) with those lamps drawn.

A set's masks are one RGBA texture whatever the count (4 lamps at most,
core.light.lamp.MAX_LAMPS): 8 bytes a texel on the GPU (RGBA16F) and 4 on
the page (RGBA8); the file holds a half channel a lamp.
"""
from __future__ import annotations

import os
import time

#: The room's lamps, brightest first (core.light.lamp.Lamp fields): a ceiling
#: bulb, a spot on the table, a reading lamp, a spot on the back wall.
BUDGET_LAMPS = (
    dict(kind="POINT", name="Ceiling", position=(0.0, 0.5, 2.6), radius=0.08, power=300.0),
    dict(kind="SPOT", name="Table", position=(0.8, -1.0, 2.5), radius=0.04, power=250.0, axis=(-0.3, 0.5, -0.8),
         spot_size=0.8, spot_blend=0.3),
    dict(kind="POINT", name="Reading", position=(-1.2, 1.0, 1.4), radius=0.05, power=120.0, color=(1.0, 0.8, 0.6)),
    dict(kind="SPOT", name="Wall", position=(0.0, -1.5, 1.8), radius=0.02, power=100.0, axis=(0.0, 0.9, 0.2),
         spot_size=0.6, spot_blend=0.2),
)


def budget(resolution: int = 1024, counts=(0, 1, 2, 4), size=(1280, 720), frames: int = 5):
    """Rows {lamps, bake_s, mask_s, mask_bytes, frame_ms per mode}."""
    import bpy  # noqa: F401  (Blender as a module provides gpu)

    from ...blender.preview.offscreen import ensure_gpu
    from ...blender.preview.renderer import Renderer
    from ...core.bake.pipeline.context import BakeSettings
    from ...core.bake.pipeline.runner import bake_scene
    from ...core.light.envmap import environment_light
    from ...core.light.lamp import Lamp
    from ...core.preview.pack import from_core_scene
    from . import scene_library
    from .render_bench import time_frames
    ensure_gpu()
    light = environment_light("forest", 5)
    sc = scene_library.room_scene(resolution, materials=True)
    rows = []
    for n in counts:
        lamps = tuple(Lamp(**d) for d in BUDGET_LAMPS[:n])
        out = os.path.join(scene_library.CACHE, f"lamp-budget-{resolution}-{n}")
        t = time.perf_counter()
        m = bake_scene(sc, out, BakeSettings(bounces=0, vertex_mode=False), light=light, lamps=lamps,
                       skip_if_unchanged=False)
        bake_s = time.perf_counter() - t
        files = (m.get("lamps") or {}).get("files", [])
        ps = from_core_scene(sc, out, light, 5, lamps=lamps)
        renderer = Renderer()
        row = {"lamps": n, "bake_s": bake_s, "mask_s": sum(s.get("lamp_seconds", 0.0) for s in m["sets"]),
               "mask_bytes": sum(os.path.getsize(os.path.join(out, f)) for f in files)}
        for mode in ("tpfl", "diffuse"):
            row[f"{mode}_ms"] = 1000 * time_frames(renderer, ps, mode, *size, frames)[1]
        renderer.free()
        rows.append(row)
        yield row
