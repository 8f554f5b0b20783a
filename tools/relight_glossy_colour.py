"""One-off measurement for #21: what sharing the relightable glossy rows
between the colours would cost in image error, before building it.

The relightable texture stores per colour c the glossy rows R_c,o,i (out
coefficient 1 <= o < 9, light coefficient i < 9): 216 of its 291 channels.
Light propagates per colour, and colour enters the rows only through the
albedos and specular colours of the surfaces the light bounced off, so a
texel's rows are close to one shared map times a colour tint. This script
bakes the room (the bench relight scene, 1024², tuning auto) as relightable,
replaces the glossy rows by the rank-1 form

    R_c,o,i ~= kappa_c * S_o,i,   S = mean over c of R_c,   kappa_c = R_c,0,0 / mean_c R_c,0,0

(the tint from the DC response, which is stored anyway, so the shared form
would store 75 + 72 = 147 channels), and renders relit frames of both
against a full rebake at the World turned 0, 120 and 240 degrees, as
``bench relight`` does. Run: ./prtt.sh py tools/relight_glossy_colour.py
"""
from __future__ import annotations

import os
import sys
import tempfile

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from prtt_addon.cli import env_light  # noqa: E402
from prtt_addon.core.bake.pipeline import relightable_stage as relight_stage  # noqa: E402
from prtt_addon.core.bake.pipeline.context import BakeSettings
from prtt_addon.core.bake.pipeline.runner import bake_scene  # noqa: E402
from prtt_addon.core.io.exr_io import expand_shared_glossy, read_relight_exr, relight_channel_names, write_sh_planes
from prtt_addon.dev.bench import scene_library  # noqa: E402
from prtt_addon.dev.bench.relight_bench import turned  # noqa: E402
from prtt_addon.dev.bench.sweep import Previewer  # noqa: E402
from prtt_addon.dev.bench.texture_error import image_error  # noqa: E402


def main() -> int:
    # The baseline keeps one set of glossy rows per colour (what tuning auto
    # wrote before it shared them); the shared form is made from it below.
    relight_stage.relight_shared_colour = lambda st: False
    light = env_light("forest", 5)
    sc = scene_library.room_scene(1024, atlas=True, materials=True)
    name = sc.set_names[0]
    with tempfile.TemporaryDirectory(prefix="prtt-glossy-colour-") as tmp:
        rl, sh, dco, bk = (os.path.join(tmp, d) for d in ("relight", "shared", "dc-only", "baked"))
        for d in (rl, bk):
            bake_scene(sc, d, BakeSettings(bounces=0), light=light)
        bake_scene(sc, rl, BakeSettings(bounces=1, bounce_mode="relightable"), light=light)
        for d in (sh, dco):
            os.makedirs(d)
            for f in os.listdir(rl):
                if not f.endswith(".relight.exr"):
                    os.link(os.path.join(rl, f), os.path.join(d, f))
        path = os.path.join(rl, f"{name}.relight.exr")
        dc, glossy, attrs = read_relight_exr(path)
        H, W, _, K = dc.shape
        kg = glossy.shape[-1]
        g2 = expand_shared_glossy(dc, glossy.mean(axis=2))     # what a reader makes of shared rows
        rel = np.sqrt(((g2 - glossy) ** 2).sum() / (glossy.astype(np.float64) ** 2).sum())
        print(f"glossy rows: shared-colour form differs from the stored rows by {100 * rel:.1f} % (relative RMSE)")
        planes = np.concatenate([dc.reshape(H, W, -1), g2.reshape(H, W, -1)], axis=-1).transpose(2, 0, 1)
        own = ("kind", "bands", "format_version", "convention", "resolution", "storage", "mantissa_bits",
               "glossy_colour")
        keep = {k: v for k, v in attrs.items() if k not in own}
        write_sh_planes(os.path.join(sh, f"{name}.relight.exr"), np.ascontiguousarray(planes), kind="relight",
                        half=False, attrs=keep, names=relight_channel_names(K, kg), bands=int(round(K ** 0.5)))
        # No glossy rows at all: glossy receivers read the DC row (irradiance) alone.
        dc_planes = np.ascontiguousarray(dc.reshape(H, W, -1).transpose(2, 0, 1))
        write_sh_planes(os.path.join(dco, f"{name}.relight.exr"), dc_planes, kind="relight", half=False,
                        attrs=dict(keep, glossy_bands=0), names=relight_channel_names(K, 0), bands=int(round(K ** 0.5)))
        view = Previewer(sc, light, (640, 360), bounces=True)
        for deg in (0.0, 120.0, 240.0):
            L = turned(light, deg)
            view.light = L
            bake_scene(sc, bk, BakeSettings(bounces=1), light=L)
            ref = view.render(bk)
            e_full, e_shared = image_error(view.render(rl), ref), image_error(view.render(sh), ref)
            e_dc = image_error(view.render(dco), ref)
            print(f"{deg:5.0f} deg: relit vs rebaked {100 * e_full:.3f} % (per-colour glossy rows), "
                  f"{100 * e_shared:.3f} % (shared-colour rows), {100 * e_dc:.3f} % (no glossy rows)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
