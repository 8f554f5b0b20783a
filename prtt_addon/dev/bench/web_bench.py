"""``python -m prtt_addon.dev.bench web``: the glTF export and the web viewer,
measured on the demo room (issue 34's goals).

1. **Export against bake.** The demo room (``scene_build.demo_scene`` in a fresh
   file) is baked by the command line as a user bakes it
   (``prtt bake room.blend --out textures --unwrap SMART --atlas``) at the
   demo's settings: a 1024² atlas, 256 rays, one relightable bounce of 64
   rays (``--resolution/--rays/--bounce-rays`` shrink it; no per-vertex
   transfer: the .glb does not carry it). The bake's time is the manifest's
   ``seconds.total`` (the bake's own stages, in its worker); the wall time of
   the command (Blender's start, the Smart UV unwrap, the save) is printed
   beside it. The export is timed twice: the wall time of ``prtt export``
   (Python, Blender, opening the .blend, exporting), and ``export_glb``
   alone, called in a Blender process that has the .blend open (first call:
   what the command pays, the glTF exporter's first use included; then a
   second call). Goal: export <= 10 % of the bake. Each of ``--encodings``
   (``prtt export --encoding``: half, the EXRs' values as RGBA16F, the
   default; u8, RGBA8 with a scale and offset per plane) is exported and
   measured in items 1-3; item 4 draws the first.
2. **Bytes.** The .glb, the PRTT payloads in it (the extension's ``bytes``
   fields: transfer, relightable-bounce DC and glossy rows, and the World's
   image), against the bake's EXR files that those payloads come from
   (transfer, relight). PRTT writes them half float with lossless
   compression (ZIP, PIZ: core/io/exr_io.py); the benchmark checks each
   file's channels and compression and, where a file is not half + lossless,
   measures a half ZIP copy instead. Goal: the .glb no larger.
3. **Page load to first frame**: ``page.goto`` until the page's title says
   ``ready`` (the first frame drawn and read back), in a freshly launched
   browser each time, median of ``--loads``.
4. **Frame time per mode** (tpfl, tp, diffuse; bounces on) at
   ``--size``: ``window.prttDraw()`` (one frame, waited for with a 1-pixel
   readPixels) ``--frames`` + 1 times, the first discarded; median and
   spread. Drawn by ``prtt.render`` with its depth pre-pass (``prepass=1``,
   as recorded); the page's default, three's own ``renderer.render``, took
   0.955-0.995 of it (``bench draw-path``).
5. **Frame time against triangles**, as the paper's table: the room alone
   (21K triangles) and with 4 (~300K) or 18 (~1.27M, ``--scenes
   21K,300K,1.3M``) copies of the 69K-triangle bunny (bench/scene_library.py),
   a texture set per object, baked small and with few rays (the rays do not
   change a frame's work; the sets are not item 4's 1024² atlas, so these
   rows compare with each other), exported and drawn in tpfl mode at
   ``--size`` and at ``--small-size`` (pixel cost against triangle cost).

The browser is Debian's chromium-headless-shell driven by Playwright, with
WebGL2 on **SwiftShader**: on the CPU. Its frame times measure a software
rasteriser, not a graphics card (the same caveat as ``bench render`` on
llvmpipe, whose numbers are Blender's preview on another software
rasteriser).

Settings, figures, the browser and the machine's load average go to
``docs/bench/web.json`` (``--json``); ``python -m prtt_addon.dev.bench figures``
writes docs/benchmarks.md's table from it.
"""
from __future__ import annotations

import argparse
import functools
import http.server
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time

from ...core.io.gltf_prtt import read_glb_json
from . import figures, scene_library

#: Debian's headless Chromium and its flags, as tests/test_web_viewer.py launches it:
#: WebGL2 on SwiftShader, and no calls out of a closed network.
BROWSER = "/usr/bin/chromium-headless-shell"
BROWSER_ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                "--disable-background-networking", "--disable-component-update", "--no-first-run"]
MODES = ("tpfl", "tp", "diffuse")
#: Scaling scenes: name -> copies of the bunny beside the room.
BUNNIES = {"21K": 0, "300K": 4, "1.3M": 18}
#: The extension's payloads of a texture set, as docs/gltf.md names them.
PAYLOADS = ("transfer", "relightDC", "relightGlossy", "bounce")
#: OpenEXR compressions that keep every bit of half data (PXR24 rounds float32 only).
LOSSLESS = {"NO_COMPRESSION", "RLE_COMPRESSION", "ZIPS_COMPRESSION", "ZIP_COMPRESSION", "PIZ_COMPRESSION",
            "PXR24_COMPRESSION"}
#: Page timeouts, ms: a 1920 x 1080 tp frame on SwiftShader takes minutes on 2 cores.
PAGE_TIMEOUT_MS = 3_600_000
EXPORT_TIMES = "prtt-bench-export-seconds "


def _size(text: str) -> tuple[int, int]:
    w, h = (int(v) for v in text.lower().split("x"))
    return w, h


def code_version() -> dict | None:
    """The commit this checkout is at and the code files (prtt_addon/, viewer/,
    shaders/) that differ from it; None outside a git checkout."""
    def git(*a):
        return subprocess.run(["git", "-C", figures.ROOT, *a], capture_output=True, text=True, check=True).stdout
    try:
        commit = git("rev-parse", "--short", "HEAD").strip()
        changed = [ln[3:] for ln in git("status", "--porcelain").splitlines()]
    except (OSError, subprocess.CalledProcessError):
        return None
    return {"commit": commit, "changed": sorted(p for p in changed if p.startswith(("prtt_addon/", "viewer/",
                                                                                     "shaders/")))}


def _mark(record: dict, phase: str) -> None:
    """The 1-minute load average as ``phase`` ends (this benchmark alone keeps
    about 2 busy: the bake's threads, SwiftShader's; more is someone else)."""
    record["loadavg"]["after"][phase] = (_loadavg() or [None])[0]


def _loadavg() -> list:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return []


# --- scenes, bake and export (Blender) ----------------------------------------------------

def build_blend(path: str, bunnies: int = 0) -> dict:
    """The demo room (scene_build.demo_scene) in a fresh file, plus ``bunnies``
    copies of the bunny with its cached xatlas unwrap as their PRTT map (no
    unwrap of 69K triangles at bake time); saved at ``path``. Returns the
    objects and triangles."""
    import bpy
    import numpy as np

    from ... import register
    from ...blender.blendfile import blender_log_muted
    from ...blender.shared import UV_MAP
    from . import scene_build as sb
    from .scene_build import demo_scene  # needs bpy
    bpy.ops.wm.read_factory_settings(use_empty=True)
    if not hasattr(bpy.types.Scene, "prtt"):
        register()
    objects = list(demo_scene().values())
    if bunnies:
        bunny, uv = scene_library.bunny_unwrapped(256)
        mat = sb.principled("bunny", base_color=(0.85, 0.85, 0.85), roughness=0.5)
        for k in range(bunnies):
            x, y = -2.5 + (k % 6) * 1.0, -2.6 + (k // 6) * 0.9       # as scene_library.render_scaling_scene
            ob = sb.mesh_object(f"bunny{k}", bunny.transformed(translate=(x, y, 0.0)), material=mat)
            ob.data.uv_layers.new(name=UV_MAP).uv.foreach_set("vector", np.asarray(uv, np.float32).ravel())
            objects.append(ob)
        bpy.context.view_layer.update()
    tris = 0
    for ob in objects:
        ob.data.calc_loop_triangles()
        tris += len(ob.data.loop_triangles)
    with blender_log_muted():
        bpy.ops.wm.save_as_mainfile(filepath=path)
    return {"objects": len(objects), "triangles": tris}


def prtt_command(*args, cwd: str) -> tuple[float, str]:
    """Run ``python -m prtt_addon ARGS`` in ``cwd``: (wall seconds, output); raises on failure."""
    env = dict(os.environ, PYTHONPATH=figures.ROOT)
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "prtt_addon", *args], capture_output=True, text=True, env=env,
                       cwd=cwd)
    wall = time.perf_counter() - t
    if r.returncode != 0:
        raise RuntimeError(f"prtt {' '.join(args)} failed ({r.returncode}):\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
    return wall, r.stdout + r.stderr


def bake(folder: str, blend: str, *, resolution: int, rays: int, bounce_rays: int, atlas: bool) -> dict:
    """Bake ``blend`` by the command line into ``folder``/textures (one relightable
    bounce): the manifest, with the command's wall time as ``wall``."""
    args = ["bake", blend, "--out", "textures", "--unwrap", "SMART", "--resolution", str(resolution),
            "--rays", str(rays), "--bounces", "1", "--bounce-rays", str(bounce_rays),
            "--bounce-mode", "relightable", "--no-vertex", "-q"] + (["--atlas"] if atlas else [])
    wall, _ = prtt_command(*args, cwd=folder)
    with open(os.path.join(folder, "textures", "manifest.json"), encoding="utf-8") as f:
        m = json.load(f)
    m["wall"] = wall
    m["command"] = "prtt " + " ".join(args)
    return m


def export_in_process(blend: str, out: str, encoding: str = "half", calls: int = 2) -> list:
    """Seconds of ``export_glb`` alone, ``calls`` times, in one Blender process
    (a child: the glTF exporter's log stays out of this output) that has
    ``blend`` open."""
    env = dict(os.environ, PYTHONPATH=figures.ROOT)
    r = subprocess.run([sys.executable, "-m", "prtt_addon.dev.bench", "web", "--export-timing", blend, out,
                        encoding, str(calls)], capture_output=True, text=True, env=env, cwd=os.path.dirname(blend))
    line = next((ln for ln in r.stdout.splitlines()[::-1] if ln.startswith(EXPORT_TIMES)), None)
    if r.returncode != 0 or line is None:
        raise RuntimeError(f"export_glb in a Blender process failed ({r.returncode}):\n{r.stdout[-3000:]}\n"
                           f"{r.stderr[-3000:]}")
    return json.loads(line[len(EXPORT_TIMES):])


def _export_timing_child(blend: str, out: str, encoding: str, calls: int) -> int:
    import bpy

    from ... import register
    from ...blender.blendfile import open_scene
    from ...blender.gltf.export import export_glb
    if not hasattr(bpy.types.Scene, "prtt"):
        register()
    scene = open_scene(blend, None, quiet=True)
    if scene is None:
        return 1
    times = []
    with bpy.context.temp_override(scene=scene):
        for _ in range(calls):
            t = time.perf_counter()
            export_glb(bpy.context, out, encoding=encoding)
            times.append(time.perf_counter() - t)
    print(EXPORT_TIMES + json.dumps(times), flush=True)
    return 0


def export(folder: str, blend: str, glb: str, encoding: str = "half") -> dict:
    """``prtt export --encoding ENCODING`` (wall seconds), then ``export_glb`` alone twice."""
    wall, _ = prtt_command("export", blend, "--out", glb, "--encoding", encoding, cwd=folder)
    inproc = export_in_process(os.path.join(folder, blend), os.path.join(folder, "inproc.glb"), encoding)
    os.remove(os.path.join(folder, "inproc.glb"))
    return {"cli_wall_s": wall, "export_glb_s": inproc[0], "export_glb_again_s": inproc[1]}


# --- bytes --------------------------------------------------------------------------------

def payload_bytes(glb: str) -> dict:
    """The PRTT extension's payload ``bytes`` per kind (summed over sets), the
    World's image, and the KTX2s' uncompressed bytes."""
    ext = read_glb_json(glb)["extensions"]["PRTT_radiance_transfer"]
    kinds = {k: 0 for k in PAYLOADS}
    raw = 0
    for s in ext["sets"]:
        for k in PAYLOADS:
            if k in s:
                kinds[k] += int(s[k]["bytes"])
                raw += int(s[k].get("uncompressedBytes", 0))
    env = int(((ext.get("environment") or {}).get("image") or {}).get("bytes", 0))
    textures = sum(kinds.values())
    return {"kinds": {k: v for k, v in kinds.items() if v}, "textures": textures, "environment": env,
            "total": textures + env, "uncompressed_textures": raw, "sets": len(ext["sets"])}


def exr_facts(path: str) -> dict:
    """An EXR's bytes, channel types, compression, and the bytes of it as a
    lossless half EXR (the file itself when it is one, else a half ZIP copy)."""
    import numpy as np
    import OpenEXR
    f = OpenEXR.File(path)
    header = f.header()
    comp = getattr(header.get("compression"), "name", str(header.get("compression")))
    chans = f.channels()
    dtypes = sorted({str(c.pixels.dtype) for c in chans.values()})
    size = os.path.getsize(path)
    half_lossless = dtypes == ["float16"] and comp in LOSSLESS
    out = {"bytes": size, "channels": len(chans), "types": dtypes, "compression": comp,
           "mantissa_bits": header.get("prtt_mantissa_bits"), "half_lossless": half_lossless,
           "half_lossless_bytes": size}
    if not half_lossless:
        with tempfile.TemporaryDirectory(prefix="prtt-bench-exr-") as d:
            h = {k: v for k, v in header.items() if k != "channels"}
            h["compression"] = OpenEXR.ZIP_COMPRESSION
            copy = os.path.join(d, "half.exr")
            OpenEXR.File(h, {n: np.ascontiguousarray(c.pixels.astype(np.float16)) for n, c in chans.items()}
                         ).write(copy)
            out["half_lossless_bytes"] = os.path.getsize(copy)
    return out


def texture_bytes(folder: str, manifest: dict) -> dict:
    """The bake's EXR files the .glb carries (transfer and bounce files)."""
    files = {n: exr_facts(os.path.join(folder, n)) for n in manifest["files"] if n.endswith(".exr")}
    return {"files": files, "total": sum(f["bytes"] for f in files.values()),
            "half_lossless_total": sum(f["half_lossless_bytes"] for f in files.values()),
            "all_half_lossless": all(f["half_lossless"] for f in files.values())}


# --- the page -----------------------------------------------------------------------------

class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


class Site:
    """An HTTP server over a folder holding the repository's viewer/, shaders/
    and tools/js/ (links) and the .glb files, as the tests serve the page."""

    def __init__(self, folder: str):
        self.folder = folder
        for part in ("viewer", "shaders", os.path.join("tools", "js")):
            dst = os.path.join(folder, part)
            if not os.path.exists(dst):
                os.makedirs(os.path.dirname(dst), exist_ok=True)
                os.symlink(os.path.join(figures.ROOT, part), dst)
        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_Quiet, directory=folder))
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"

    def add(self, glb: str, name: str) -> str:
        shutil.copy(glb, os.path.join(self.folder, name))
        return "/" + name

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


def page_url(site: Site, src: str, size, mode: str = "tpfl") -> str:
    w, h = size
    # prepass=1: prtt.render's depth pre-pass, the path docs/bench/web.json's frames were
    # recorded with (the page draws with three's own renderer.render since: bench draw-path).
    return f"{site.url}/viewer/index.html?src={src}&w={w}&h={h}&ui=0&mode={mode}&bounces=1&prepass=1"


def open_page(pw, url: str, size):
    """A freshly launched browser on ``url``: (browser, page, seconds from goto
    to a 'ready' or 'error' title, the title)."""
    b = pw.chromium.launch(executable_path=BROWSER, args=BROWSER_ARGS)
    page = b.new_page(viewport={"width": size[0], "height": size[1]})
    t = time.perf_counter()
    page.goto(url, timeout=PAGE_TIMEOUT_MS)
    page.wait_for_function("document.title.startsWith('ready') || document.title.startsWith('error')",
                           timeout=PAGE_TIMEOUT_MS, polling=20)
    return b, page, time.perf_counter() - t, page.title()


def time_frames(page, frames: int) -> dict:
    """``window.prttDraw()`` ``frames`` + 1 times, the first discarded: ms."""
    ms = [float(page.evaluate("window.prttDraw()")) for _ in range(frames + 1)][1:]
    return {"ms": ms, "median_ms": statistics.median(ms), "min_ms": min(ms), "max_ms": max(ms)}


def measure_page(pw, site: Site, src: str, size, mode: str, frames: int, log) -> dict:
    """Load the page (fresh browser), then time ``frames`` frames."""
    b, page, load_s, title = open_page(pw, page_url(site, src, size, mode), size)
    try:
        row = {"mode": mode, "width": size[0], "height": size[1], "load_s": load_s, "title": title}
        if not title.startswith("ready"):
            log(f"  {mode} {size[0]}x{size[1]}: the page says {title!r}")
            return row
        row.update(time_frames(page, frames))
        return row
    finally:
        b.close()


def webgl_renderer(pw) -> tuple[str, str]:
    """(browser version, WebGL2's unmasked renderer string)."""
    b = pw.chromium.launch(executable_path=BROWSER, args=BROWSER_ARGS)
    try:
        page = b.new_page()
        r = page.evaluate("""() => { const gl = document.createElement('canvas').getContext('webgl2');
            if (!gl) return 'no WebGL2';
            const e = gl.getExtension('WEBGL_debug_renderer_info');
            return gl.getParameter(e ? e.UNMASKED_RENDERER_WEBGL : gl.RENDERER); }""")
        return b.version, r
    finally:
        b.close()


def _spread(row: dict) -> str:
    if "median_ms" not in row:
        return row.get("title", "?")
    return (f"{row['median_ms']:10.1f} {row['min_ms']:9.1f}-{row['max_ms']:<9.1f} "
            f"{100 * (row['max_ms'] - row['min_ms']) / row['median_ms']:5.1f} %")


# --- the run ------------------------------------------------------------------------------

def run(args, log=print) -> dict:
    from playwright.sync_api import sync_playwright
    if not os.path.exists(BROWSER):
        raise SystemExit(f"{BROWSER} is needed (Debian's chromium-headless-shell: ./prtt.sh installs it)")
    size, small = _size(args.size), _size(args.small_size)
    scenes = [s for s in args.scenes.split(",") if s]
    for s in scenes:
        if s not in BUNNIES:
            raise SystemExit(f"--scenes: unknown scene {s!r} (of {', '.join(BUNNIES)})")
    record = {"settings": {"resolution": args.resolution, "rays": args.rays, "bands": 5, "bounces": 1,
                           "bounce_mode": "relightable", "bounce_rays": args.bounce_rays, "texture_sets": "atlas",
                           "unwrap": "SMART", "vertex_transfer": False, "encodings": args.encodings, "size": list(size),
                           "small_size": list(small), "frames": args.frames, "loads": args.loads,
                           "scenes": scenes, "scaling_resolution": args.scaling_resolution,
                           "scaling_rays": args.scaling_rays, "scaling_bounce_rays": args.scaling_bounce_rays},
              "code": code_version(), "loadavg": {"start": _loadavg(), "after": {}}, "errors": []}
    work = args.work or tempfile.mkdtemp(prefix="prtt-bench-web-")
    os.makedirs(work, exist_ok=True)
    site = Site(os.path.join(work, "site"))
    try:
        with sync_playwright() as pw:
            version, renderer = webgl_renderer(pw)
            record["browser"] = {"executable": BROWSER, "version": version, "webgl_renderer": renderer,
                                 "args": BROWSER_ARGS}
            log(f"settings: demo room, {args.resolution}^2 atlas (Smart UV), 5 bands, {args.rays} rays, 1 relightable "
                f"bounce of {args.bounce_rays} rays, tuning auto, no per-vertex transfer (the .glb does not carry "
                f"it); page {size[0]}x{size[1]}, {args.loads} load(s), {args.frames} frame(s) after 1 discarded; "
                f"scaling scenes {', '.join(scenes) or 'none'}: a {args.scaling_resolution}^2 set per object, "
                f"{args.scaling_rays} rays, 1 relightable bounce of {args.scaling_bounce_rays} rays, tpfl at "
                f"{size[0]}x{size[1]} and {small[0]}x{small[1]}")
            log(f"browser: chromium-headless-shell {version}, WebGL2 renderer {renderer!r} "
                f"(SwiftShader: the CPU, {os.cpu_count()} cores; not a graphics card)")
            log(f"machine load average (1, 5, 15 min) at the start: {record['loadavg']['start']}")
            _room(args, record, work, site, pw, size, log)
            _scaling(args, record, work, site, pw, size, small, scenes, log)
    finally:
        site.close()
        if not args.work:
            shutil.rmtree(work, ignore_errors=True)
    record["loadavg"]["end"] = _loadavg()
    log(f"\nmachine load average at the end: {record['loadavg']['end']}; 1-minute load average after each phase: "
        + ", ".join(f"{k} {v}" for k, v in record["loadavg"]["after"].items()))
    return record


def _loads(args, record, site, pw, size, src, what: str, log, keep_last: bool = False):
    """``--loads`` page loads of ``src`` in tpfl, a fresh browser each: (seconds,
    the last (browser, page) when ``keep_last`` else None)."""
    loads, last = [], None
    for i in range(args.loads):
        if last is not None:
            last[0].close()
            last = None
        b, page, load_s, title = open_page(pw, page_url(site, src, size, "tpfl"), size)
        if not title.startswith("ready"):
            b.close()
            record["errors"].append({"scene": what, "mode": "tpfl", "size": list(size), "title": title})
            log(f"    {what} load {i + 1}: the page says {title!r}")
            break
        loads.append(load_s)
        log(f"    {what} load {i + 1}: {load_s:.2f} s ({title})", flush=True)
        last = (b, page)
    if last is not None and not keep_last:
        last[0].close()
        last = None
    return {"seconds": loads, "median_s": statistics.median(loads) if loads else None}, last


def _room(args, record, work, site, pw, size, log) -> None:
    folder = os.path.join(work, "room")
    os.makedirs(folder, exist_ok=True)
    scene = build_blend(os.path.join(folder, "room.blend"))
    log(f"\n[1] demo room: {scene['objects']} objects, {scene['triangles']} triangles; baking "
        f"(minutes at the defaults) ...", flush=True)
    m = bake(folder, "room.blend", resolution=args.resolution, rays=args.rays, bounce_rays=args.bounce_rays,
             atlas=True)
    _mark(record, "bake")
    sec = m["seconds"]
    bake_s = float(sec["total"])
    record["scene"] = {**scene, "sets": len(m["transfer_files"])}
    record["bake"] = {"seconds": bake_s, "wall_s": m["wall"], "stages": sec, "command": m["command"],
                      "texels": m["totals"]["texels"], "rays_traced": m["totals"]["rays_traced"]}
    log(f"    bake: {bake_s:.1f} s (manifest seconds.total: the bake's own stages; transfer trace "
        f"{sec.get('trace', 0):.1f} s, bounce trace {sec.get('bounce_trace', 0):.1f} s); `prtt bake` wall "
        f"{m['wall']:.1f} s (Blender start, Smart UV unwrap, worker, save)")
    exr = texture_bytes(os.path.join(folder, "textures"), m)
    encodings = []
    for enc in args.encodings:
        glb = os.path.join(folder, f"room-{enc}.glb")
        ex = export(folder, "room.blend", os.path.basename(glb), enc)
        _mark(record, f"export {enc}")
        pay = payload_bytes(glb)
        glb_bytes = os.path.getsize(glb)
        e = {"encoding": enc, **ex, "ratio": ex["export_glb_s"] / bake_s, "ratio_cli": ex["cli_wall_s"] / m["wall"],
             "glb": glb_bytes, "payload": pay, "ratio_glb_to_exr": glb_bytes / exr["half_lossless_total"],
             "ratio_textures_to_exr": pay["textures"] / exr["half_lossless_total"]}
        encodings.append(e)
        log(f"    export --encoding {enc}: export_glb {ex['export_glb_s']:.2f} s in a Blender process with the "
            f".blend open (first call; again {ex['export_glb_again_s']:.2f} s); `prtt export` wall "
            f"{ex['cli_wall_s']:.2f} s; export / bake {100 * e['ratio']:.1f} % (export_glb / manifest), "
            f"{100 * e['ratio_cli']:.1f} % (the two commands' wall times); goal <= 10 %: "
            f"{'met' if e['ratio'] <= 0.10 else 'NOT met'}", flush=True)
    first = encodings[0]
    record["export"] = {k: first[k] for k in ("encoding", "cli_wall_s", "export_glb_s", "export_glb_again_s",
                                              "ratio", "ratio_cli")}
    record["bytes"] = {k: first[k] for k in ("glb", "payload", "ratio_glb_to_exr", "ratio_textures_to_exr")}
    record["bytes"]["exr"] = exr
    log("\n[2] bytes:")
    for name, f in exr["files"].items():
        log(f"    {name}: {f['bytes']:,} bytes, {f['channels']} channels {'/'.join(f['types'])}, "
            f"{f['compression']}" + (f", {f['mantissa_bits']} mantissa bits" if f["mantissa_bits"] else "")
            + ("" if f["half_lossless"] else f"; as a half ZIP copy {f['half_lossless_bytes']:,}"))
    log(f"    the bake's EXRs the .glb carries: {exr['total']:,} bytes"
        + (" (already half + lossless compression: their size is the lossless half size)"
           if exr["all_half_lossless"] else f"; as lossless half EXRs {exr['half_lossless_total']:,}"))
    for e in encodings:
        pay = e["payload"]
        log(f"    --encoding {e['encoding']}: .glb {e['glb']:,}; PRTT payloads {pay['total']:,} (textures "
            f"{pay['textures']:,}: " + ", ".join(f"{k} {v:,}" for k, v in pay["kinds"].items())
            + f"; World image {pay['environment']:,}); KTX2 uncompressed {pay['uncompressed_textures']:,}; "
            f".glb / EXRs {e['ratio_glb_to_exr']:.2f} (PRTT textures alone {e['ratio_textures_to_exr']:.2f}); "
            f"goal <= 1: {'met' if e['ratio_glb_to_exr'] <= 1 else 'NOT met'}")

    log(f"\n[3] page load to first frame, {size[0]}x{size[1]}, tpfl, a fresh browser each:", flush=True)
    last = None
    for i, e in enumerate(encodings):
        src = site.add(os.path.join(folder, f"room-{e['encoding']}.glb"), f"room-{e['encoding']}.glb")
        # the first encoding's last page stays open: [4] times tpfl on it
        e["page_load"], kept = _loads(args, record, site, pw, size, src, f"room --encoding {e['encoding']}", log,
                                      keep_last=i == 0)
        _mark(record, f"page loads {e['encoding']}")
        if i == 0:
            last = kept
    record["page_load"] = first["page_load"]
    record["encodings"] = encodings

    src = f"/room-{first['encoding']}.glb"
    log(f"\n[4] frame time at {size[0]}x{size[1]}, --encoding {first['encoding']}, bounces on, {args.frames} "
        f"frame(s) after 1 discarded:")
    log(f"    {'mode':8s} {'median ms':>10} {'min-max ms':>19} {'spread':>7} {'load s':>7}")
    rows = []
    for mode in MODES:
        if mode == "tpfl" and last is not None:
            row = {"mode": mode, "width": size[0], "height": size[1], "load_s": record["page_load"]["seconds"][-1],
                   "title": "ready", **time_frames(last[1], args.frames)}
            last[0].close()
            last = None
        else:
            row = measure_page(pw, site, src, size, mode, args.frames, log)
            if "median_ms" not in row:
                record["errors"].append({"scene": "room", "mode": mode, "size": list(size), "title": row["title"]})
        rows.append(row)
        _mark(record, f"{mode} frames")
        log(f"    {mode:8s} {_spread(row)} {row['load_s']:7.1f}", flush=True)
    if last is not None:
        last[0].close()
    record["frames"] = rows


def _scaling(args, record, work, site, pw, size, small, scenes, log) -> None:
    if not scenes:
        record["scaling"] = []
        return
    log(f"\n[5] frame time against triangles, tpfl, {args.frames} frame(s) after 1 discarded "
        f"(a {args.scaling_resolution}^2 set per object, {args.scaling_rays} rays):")
    rows = []
    for name in scenes:
        folder = os.path.join(work, f"scale-{name}")
        os.makedirs(folder, exist_ok=True)
        sc = build_blend(os.path.join(folder, "scene.blend"), BUNNIES[name])
        m = bake(folder, "scene.blend", resolution=args.scaling_resolution, rays=args.scaling_rays,
                 bounce_rays=args.scaling_bounce_rays, atlas=False)
        t = time.perf_counter()
        wall, _ = prtt_command("export", "scene.blend", "--out", "scene.glb", cwd=folder)
        glb = os.path.join(folder, "scene.glb")
        src = site.add(glb, f"scene-{name}.glb")
        row = {"scene": name, **sc, "sets": len(m["transfer_files"]), "bake_s": float(m["seconds"]["total"]),
               "export_wall_s": wall, "glb_bytes": os.path.getsize(glb), "sizes": []}
        log(f"    {name}: {sc['triangles']} triangles, {sc['objects']} objects, bake {row['bake_s']:.1f} s, "
            f"export {time.perf_counter() - t:.1f} s, .glb {row['glb_bytes']:,} bytes", flush=True)
        for wh in (size, small):
            fr = measure_page(pw, site, src, wh, "tpfl", args.frames, log)
            if "median_ms" not in fr:
                record["errors"].append({"scene": name, "mode": "tpfl", "size": list(wh), "title": fr["title"]})
            else:
                fr["ns_per_pixel"] = 1e6 * fr["median_ms"] / (wh[0] * wh[1])
            row["sizes"].append(fr)
            _mark(record, f"{name} {wh[0]}x{wh[1]}")
            log(f"      {wh[0]}x{wh[1]}: {_spread(fr)}, load {fr['load_s']:.1f} s", flush=True)
        rows.append(row)
    record["scaling"] = rows
    log(f"\n    {'scene':>6} {'triangles':>10} " + " ".join(f"{f'{w}x{h} ms':>15}" for w, h in (size, small))
        + f" {'ns/pixel':>9}")
    for r in rows:
        ms = [s.get("median_ms") for s in r["sizes"]]
        ns = r["sizes"][0].get("ns_per_pixel")
        log(f"    {r['scene']:>6} {r['triangles']:10d} " + " ".join(
            f"{v:15.1f}" if v is not None else f"{'error':>15}" for v in ms)
            + (f" {ns:9.0f}" if ns is not None else ""))


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--export-timing":
        return _export_timing_child(argv[1], argv[2], argv[3], int(argv[4]))
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench web", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=1024, help="the room's atlas (the demo's: 1024)")
    p.add_argument("--rays", type=int, default=256, help="transfer rays per texel (the demo's: 256)")
    p.add_argument("--bounce-rays", type=int, default=64, help="bounce rays per texel (the demo's: 64)")
    p.add_argument("--encodings", default="half,u8",
                   help="prtt export --encoding of the room, comma list; the first one's .glb is drawn in [4]")
    p.add_argument("--size", default="1920x1080", help="page size WxH for the load and frame times")
    p.add_argument("--small-size", default="480x270", help="the second size of the triangle table")
    p.add_argument("--frames", type=int, default=3, help="timed frames per point, after one discarded")
    p.add_argument("--loads", type=int, default=3, help="page loads timed (median)")
    p.add_argument("--scenes", default="21K,300K",
                   help=f"scaling scenes, comma list of {', '.join(BUNNIES)} ('' for none; 1.3M takes long)")
    p.add_argument("--scaling-resolution", type=int, default=128, help="texels a side of each object's set")
    p.add_argument("--scaling-rays", type=int, default=16)
    p.add_argument("--scaling-bounce-rays", type=int, default=8)
    p.add_argument("--work", help="keep the .blend files, textures and .glb files in this folder")
    p.add_argument("--json", default=None, help="the record (default docs/bench/web.json; '' for none)")
    args = p.parse_args(argv)
    if args.frames < 1 or args.loads < 1:
        p.error("--frames and --loads must be >= 1")
    args.encodings = [e for e in args.encodings.split(",") if e]
    if not args.encodings:
        p.error("--encodings: name at least one")
    if args.json is None:
        args.json = figures.bench_path("web.json")
    record = run(args)
    print("\n" + figures.web_block(figures.record_of("bench web", argv, record)))
    if args.json:
        print(f"\nwrote {figures.write_record(args.json, 'bench web', argv, record)}")
    for e in record["errors"]:
        print(f"error: {e['scene']} {e['mode']} {e['size'][0]}x{e['size'][1]}: {e['title']}", file=sys.stderr)
    return 1 if record["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
