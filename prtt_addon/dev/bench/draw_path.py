"""``python -m prtt_addon.dev.bench draw-path --glb FILE``: the page's two ways
to draw a PRTT scene, timed against each other in one run (issue 51).

* ``prtt.render(renderer, scene, camera)``: a depth pre-pass, then each pixel
  shaded once, as Blender's preview (the page with ``prepass=1``);
* ``renderer.render(scene, camera)``: three's own call (the page's default);
  the PRTT meshes' ``onBeforeRender`` relight and set the view.

Two pages are open at once, one per path, in one headless Chromium
(SwiftShader: a software rasteriser, so these are CPU figures); frames are
drawn alternately (``window.prttDraw()``: one frame, waited for with a
1-pixel read-back), the first of each discarded. Prints each path's median
and fastest milliseconds and their ratio.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile

from ...cli_options import parse_size
from .web_bench import BROWSER, BROWSER_ARGS, PAGE_TIMEOUT_MS, Site, page_url

#: Each path's ``prepass`` (page_url asks 1, the web benchmark's path; each page's URL says its own).
PATHS = {"prtt.render (depth pre-pass)": "1", "renderer.render (three's own)": "0"}


def run(glb: str, size, mode: str, frames: int, log=print) -> dict:
    from playwright.sync_api import sync_playwright
    with tempfile.TemporaryDirectory() as work, sync_playwright() as pw:
        site = Site(work)
        b = pw.chromium.launch(executable_path=BROWSER, args=BROWSER_ARGS)
        try:
            src = site.add(glb, "scene.glb")
            pages = {}
            for name, extra in PATHS.items():
                page = b.new_page(viewport={"width": size[0], "height": size[1]})
                url = page_url(site, src, size, mode).replace("&prepass=1", f"&prepass={extra}")
                page.goto(url, timeout=PAGE_TIMEOUT_MS)
                page.wait_for_function("document.title.startsWith('ready') || document.title.startsWith('error')",
                                       timeout=PAGE_TIMEOUT_MS, polling=20)
                if not page.title().startswith("ready"):
                    raise SystemExit(f"{name}: the page says {page.title()!r}")
                pages[name] = page
            ms = {name: [] for name in PATHS}
            for k in range(frames + 1):
                for name, page in pages.items():
                    t = float(page.evaluate("window.prttDraw()"))
                    if k:
                        ms[name].append(t)
        finally:
            b.close()
            site.close()
    out = {name: {"median_ms": statistics.median(v), "min_ms": min(v), "ms": v} for name, v in ms.items()}
    first, second = (out[n] for n in PATHS)
    log(f"{os.path.basename(glb)}, {mode}, {size[0]}x{size[1]}, {frames} frame(s) each after 1 discarded, "
        f"alternating (SwiftShader):")
    for name, row in out.items():
        log(f"  {name:32s} median {row['median_ms']:8.1f} ms   fastest {row['min_ms']:8.1f} ms")
    log(f"  renderer.render / prtt.render: median {second['median_ms'] / first['median_ms']:.3f}, "
        f"fastest {second['min_ms'] / first['min_ms']:.3f}")
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench draw-path", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--glb", required=True, help="a .glb written by prtt export")
    p.add_argument("--size", default="1280x720", type=parse_size, help="page size WxH (default 1280x720)")
    p.add_argument("--mode", default="tpfl", choices=("tpfl", "tp", "diffuse"), help="shading (default tpfl)")
    p.add_argument("--frames", type=int, default=5, help="timed frames per path, after one discarded (default 5)")
    args = p.parse_args(argv)
    if args.frames < 1:
        p.error("--frames must be at least 1")
    if not os.path.isfile(args.glb):
        p.error(f"--glb {args.glb}: no such file")
    run(args.glb, args.size, args.mode, args.frames)
    return 0


if __name__ == "__main__":
    sys.exit(main())
