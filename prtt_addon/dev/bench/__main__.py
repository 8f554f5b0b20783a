"""``python -m prtt_addon.dev.bench <benchmark> [options]``."""
import sys

BENCHMARKS = {
    "memory": ("prtt_addon.dev.bench.memory_bench", "peak memory and seconds against texels and triangles, per stage and "
               "process (bake worker, Blender side, render), the estimate against the measured peak"),
    "bake": ("prtt_addon.dev.bench.bake_bench", "transfer bake vs raw Embree on the room-class scene"),
    "bounce": ("prtt_addon.dev.bench.bounce_bench", "inter-reflection bake on the room-class scene"),
    "auto": ("prtt_addon.dev.bench.auto_bench", "per-set tuning vs the fixed bake: time, bytes, preview image error"),
    "relight": ("prtt_addon.dev.bench.relight_bench", "relightable bounces vs a rebake at every World rotation: "
                "error, bake and frame time, bytes"),
    "render": ("prtt_addon.dev.bench.render_bench", "preview frame time per mode vs triangles and resolution"),
    "sweep": ("prtt_addon.dev.bench.sweep", "run time against error: rays, strategies, resolution, bands, storage, scenes"),
    "cycles": ("prtt_addon.dev.bench.cycles_compare", "diffuse PRTT against Cycles under a band-limited environment"),
    "contact": ("prtt_addon.dev.bench.contact", "the paper's contact-shadow figure, measured against ray tracing"),
    "contact-profile": ("prtt_addon.dev.bench.contact_profile", "the floor's baked light beside a box against the "
                        "traced light, in quarter-texel bins (dark creases at contacts; --leak: a shed of "
                        "single-plane walls)"),
    "contact-cycles": ("prtt_addon.dev.bench.contact_cycles", "the contact-profile's bins against a Cycles render "
                       "of the floor (--leak: across the shed's single-plane wall), the traced light beside it"),
    "sun": ("prtt_addon.dev.bench.sun_cycles", "a Sun lamp's light and shadows in the preview against Cycles "
            "(0.5 and 5 degree discs over a box and a plank)"),
    "lamps": ("prtt_addon.dev.bench.lamp_cycles", "point and spot lamps' light and shadows in the preview against "
              "Cycles (over a box and a plank, direct light)"),
    "quality": ("prtt_addon.dev.bench.quality", "issue 53's lightmap artefacts (contact creases, leaks under "
                "single-plane walls, a window-lit room's noise and time, seams) before their fixes and now"),
    "window-room": ("prtt_addon.dev.bench.window_room", "a room lit only through a window: the transfer's "
                    "noise against its converged value, raw and denoised"),
    "web": ("prtt_addon.dev.bench.web_bench", "glTF export vs bake (time, bytes) and the web viewer's page load and "
            "frame time (headless Chromium, SwiftShader)"),
    "draw-path": ("prtt_addon.dev.bench.draw_path", "the page's prtt.render (depth pre-pass) against three's own "
                  "renderer.render, frame times in one run"),
    "figures": ("prtt_addon.dev.bench.figures", "write the docs' figures blocks from the benchmarks' records (--check)"),
    "stress": ("prtt_addon.dev.bench.stress", "numerical stress cases (scale, normals, thin shells, degenerate, bands, overflow)"),
}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] not in BENCHMARKS:
        print("usage: python -m prtt_addon.dev.bench <benchmark> [--help]\n\nbenchmarks:")
        for k, (_, doc) in BENCHMARKS.items():
            print(f"  {k:15s} {doc}")
        return 2 if argv and argv[0] not in ("-h", "--help") else 0
    import importlib
    return importlib.import_module(BENCHMARKS[argv[0]][0]).main(argv[1:])


if __name__ == "__main__":
    sys.exit(main())
