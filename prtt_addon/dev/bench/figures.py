"""``python -m prtt_addon.dev.bench figures [--check]``: the docs' benchmark
figures, written from the benchmarks' output files.

A benchmark that feeds the docs writes a record (``write_record``: the
command, its date, the machine, the settings it measured and every figure it
printed) under ``docs/bench/``. Each generated block of a page sits between
``<!-- figures:NAME -->`` and ``<!-- /figures:NAME -->`` and is made here
from those records only, so a figure in the README is the last run's, with
its date and machine, never a number copied by hand. ``--check`` (run by the
tests) fails when a page's block differs from what its record gives.
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import datetime
import importlib.metadata
import json
import os
import platform
import re
import sys

from ...core.base.atomic import atomic_write

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))


def bench_path(name: str) -> str:
    """A file under docs/bench/ of this checkout."""
    return os.path.join(ROOT, "docs", "bench", name)


# --- records ------------------------------------------------------------------------------

def machine() -> dict:
    """What ran the benchmark: CPU model, cores, memory, OS, Python and the
    versions of the libraries the timings depend on."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            cpu = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), cpu)
    except OSError:
        pass
    mem = None
    try:
        mem = round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2 ** 30, 1)
    except (ValueError, OSError, AttributeError):
        pass
    system = f"{platform.system()} {platform.release()}"
    try:
        with open("/etc/os-release", encoding="utf-8") as f:
            system = next((ln.split("=", 1)[1].strip().strip('"') for ln in f if ln.startswith("PRETTY_NAME=")),
                          system)
    except OSError:
        pass
    versions = {}
    for dist in ("numpy", "embreex", "OpenEXR", "numba", "bpy"):
        try:
            versions[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            pass
    return {"cpu": cpu, "cores": os.cpu_count(), "memory_gib": mem, "os": system,
            "python": platform.python_version(), "versions": versions}


def settings_dict(settings) -> dict:
    """A settings dataclass as JSON values."""
    return {f.name: getattr(settings, f.name) for f in dataclasses.fields(settings)
            if isinstance(getattr(settings, f.name), (int, float, str, bool, type(None)))}


#: Settings every benchmark line names, changed or not.
HEADLINE = ("rays", "bands", "bounces", "bounce_mode", "tuning", "sampler", "estimator", "storage", "threads")


def settings_line(settings, defaults) -> str:
    """The settings a run measured, as one line: the headline ones, then every
    other one that differs from ``defaults`` (with the default it replaces)."""
    now, base = settings_dict(settings), settings_dict(defaults)
    parts = []
    for k in list(HEADLINE) + sorted(set(now) - set(HEADLINE)):
        if k not in now:
            continue
        changed = now[k] != base.get(k)
        if k in HEADLINE or changed:
            parts.append(f"{k}={now[k]}" + (f" (default {base.get(k)})" if changed else ""))
    return ", ".join(parts) + "; every other setting at its default"


def record_of(command: str, argv, record: dict) -> dict:
    """``record`` with the command line (``command``: "bench bake"), the date
    and the machine: what :func:`write_record` writes."""
    argv = list(sys.argv[1:] if argv is None else argv)
    return {"command": f"python -m prtt_addon.dev.{command} {' '.join(argv)}".strip(),
            "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d"),
            "machine": machine(), **record}


def write_record(path: str, command: str, argv, record: dict) -> str:
    """Write ``record`` with the command line (``command``: "bench bake"), the
    date and the machine as JSON at ``path`` (atomically). Returns the path."""
    out = record_of(command, argv, record)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with atomic_write(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(out, f, indent=1, sort_keys=False)
            f.write("\n")
    return path


def machine_text(m: dict) -> str:
    v = m.get("versions", {})
    libs = ", ".join(f"{k} {v[k]}" for k in ("embreex", "numpy", "numba") if k in v)
    mem = f", {m['memory_gib']:g} GiB" if m.get("memory_gib") else ""
    return f"{m.get('cpu', '?')}, {m.get('cores', '?')} cores{mem}, {m.get('os', '?')}, Python {m.get('python', '?')}" \
           + (f", {libs}" if libs else "")


# --- blocks -------------------------------------------------------------------------------

def _load(name: str) -> dict:
    with open(bench_path(name), encoding="utf-8") as f:
        return json.load(f)


def _si(n: float) -> str:
    return f"{n / 1e6:.3g}M" if n >= 1e6 else f"{n / 1e3:.0f}K"


def _without(st: dict) -> str:
    """The bake table's note on what its first rows leave out of the defaults."""
    if st.get("guiding") is False and st.get("texel_validity") is False:
        return "without guided rays or texel validity (the default bake is the last row), "
    if st.get("guiding") is False:
        return "without guided rays (the default bake, guided, is the last row), "
    return ""


def bake_block() -> str:
    """README: the transfer bake's figures (docs/bench/bake.json, bench bake)."""
    r = _load("bake.json")
    s, st, sc = r["seconds"], r["settings"], r["scene"]
    pairs = r["ratio_pairs"]
    skipped = 100 * (1 - r["rays_traced"] / max(r["rays_naive"], 1))
    lines = [
        f"`{r['command']}`, {r['date']}, on {machine_text(r['machine'])}. Room-class scene, "
        f"{_si(sc['triangles'])} triangles, {'one' if sc['sets'] == 1 else sc['sets']} {sc['resolution']}² atlas ({r['texels']:,} texels), "
        f"{st['bands']} bands, {st['rays']} rays per texel, transfer only (bounces = {st['bounces']}; "
        f"`bench bounce` times the bounce), {r['threads']} threads, "
        f"{_without(st)}"
        f"every other setting at its default:",
        "",
        "| | measured |",
        "|---|---|",
        f"| whole transfer bake (BVH, G-buffer, {_si(r['rays_traced'])} rays, dilation, EXR) | "
        f"**{s['total']:.1f} s** (fastest of {r['repeat']}; stages: BVH {s['bvh']:.2f}, analytic test "
        f"{s['analytic_test']:.2f}, G-buffer {s['gbuffer']:.2f}, trace {s['trace']:.2f}, dilate {s['dilate']:.2f}, "
        f"write {s['write']:.2f} s) |",
        f"| end to end | {r['mrays_per_s_end_to_end']:.1f} Mrays/s on {r['threads']} threads (trace stage alone "
        f"{r['mrays_per_s_trace']:.1f}) |",
        f"| end-to-end / raw embreex on the same rays ({r['raw_mrays_per_s']:.1f} Mrays/s) | "
        f"**{r['ratio']:.3f}** (fastest of each of {r['repeat']} interleaved pairs; single pairs "
        f"{min(pairs):.3f}–{max(pairs):.3f}); trace stage alone {r['ratio_trace']:.3f}; target ≥ 0.8 |",
        f"| texel-samples per second per core | {r['texel_samples_per_s_per_core'] / 1e6:.1f} M (C++ SH-lightmap "
        f"baker reference: 1.5 M) |",
        f"| rays skipped (analytic texels, below-horizon rays) | {skipped:.1f} % |",
        f"| transfer texture on disk (half, ZIP) | {r['output_bytes'] / 1e6:.1f} MB |",
    ]
    if r.get("guided") and "inside_texels" in r["guided"]:
        gd = r["guided"]
        lines.append(f"| the default bake, with guided rays, their filter and texel validity | **{gd['total_s']:.1f} s** "
                     f"(fastest of {len(gd['pairs_s'])}; {gd['guided_texels']:,} texels guided, "
                     f"{gd['filtered_texels']:,} smoothed, {gd['inside_texels']:,} inside geometry, "
                     f"{gd['moved_texels']:,} moved across walls), {gd['total_s'] / s['total']:.2f} × the bake without |")
    elif r.get("guided"):
        gd = r["guided"]
        lines.append(f"| the default bake, with guided rays (`--guiding`) | **{gd['total_s']:.1f} s** (fastest of "
                     f"{len(gd['pairs_s'])}; {gd['guided_texels']:,} texels guided), {gd['total_s'] / s['total']:.2f} × "
                     f"the bake without |")
    if r.get("scaling_triangles"):
        lines += ["", "| triangles (same atlas + occluder-only bunnies) | BVH s | trace s | total s |",
                  "|---|---|---|---|"]
        lines += [f"| {_si(t['triangles'])} | {t['bvh']:.2f} | {t['trace']:.1f} | {t['total']:.1f} |"
                  for t in r["scaling_triangles"]]
    if r.get("scaling_resolution"):
        lines += ["", "| resolution (room) | total s |", "|---|---|"]
        lines += [f"| {t['resolution']}² | {t['total']:.2f} |" for t in r["scaling_resolution"]]
    return "\n".join(lines)


def _full_hd_frames() -> list:
    """The 1920 x 1080 rows of docs/bench/render_llvmpipe.csv (bench render --csv)."""
    with open(bench_path("render_llvmpipe.csv"), newline="", encoding="utf-8") as f:
        return [r for r in csv.DictReader(f) if (r["width"], r["height"]) == ("1920", "1080")]


def render_block() -> str:
    """README: preview frame times at 1920 x 1080 (docs/bench/render_llvmpipe.csv,
    bench render --csv, with its .meta.json when the run wrote one)."""
    full = _full_hd_frames()
    meta_path = bench_path("render_llvmpipe.csv.meta.json")
    if os.path.isfile(meta_path):
        with open(meta_path, encoding="utf-8") as f:
            meta = json.load(f)
        head = (f"`{meta['command']}`, {meta['date']}, {meta.get('gpu', '')} on {machine_text(meta['machine'])}; "
                f"ms per frame at 1920 × 1080:")
    else:
        head = ("`python -m prtt_addon.dev.bench render --csv docs/bench/render_llvmpipe.csv`, Mesa llvmpipe on "
                "2 CPU cores (a run before 2026-11-25, which recorded no date or machine); ms per frame "
                "at 1920 × 1080:")
    scenes = list(dict.fromkeys(r["scene"] for r in full))
    names = {"tpfl": "TPFL, fragment (PRTT)", "vertex-tpfl": "TPFL, vertex (baseline)", "tp": "TP, fragment",
             "diffuse": "diffuse", "vertex-tp": "TP, vertex"}
    lines = [head, "", "| mode | " + " | ".join(f"{s} triangles" for s in scenes) + " |",
             "|---|" + "---|" * len(scenes)]
    for mode in ("tpfl", "vertex-tpfl", "tp"):
        ms = {r["scene"]: float(r["frame_ms"]) for r in full if r["mode"] == mode}
        lines.append(f"| {names[mode]} | " + " | ".join(f"{ms[s]:.0f}" for s in scenes if s in ms) + " |")
    tri = {r["scene"]: int(r["triangles"]) for r in full}
    first, last = scenes[0], scenes[-1]
    grow = {mode: next(float(r["frame_ms"]) for r in full if r["mode"] == mode and r["scene"] == last)
            / next(float(r["frame_ms"]) for r in full if r["mode"] == mode and r["scene"] == first)
            for mode in ("tpfl", "vertex-tpfl")}
    lines += ["", f"{tri[last] / tri[first]:.0f} × more triangles: the fragment method's frame × {grow['tpfl']:.1f} "
                  f"(triangle setup on the CPU), the per-vertex baseline's × {grow['vertex-tpfl']:.0f}."]
    return "\n".join(lines)


def preview_block() -> str:
    """docs/preview.md: every mode's frame time at 1920 x 1080 and its growth
    from the smallest to the largest scene (docs/bench/render_llvmpipe.csv)."""
    full = _full_hd_frames()
    scenes = list(dict.fromkeys(r["scene"] for r in full))
    names = {"tpfl": "TPFL (fragment)", "tp": "TP (fragment)", "diffuse": "diffuse (fragment)",
             "vertex-tpfl": "TPFL (vertex)", "vertex-tp": "TP (vertex)"}
    lines = ["| 1920 × 1080, ms per frame | " + " | ".join(scenes) + " | growth |",
             "|---|" + "---|" * (len(scenes) + 1)]
    for mode, label in names.items():
        ms = {r["scene"]: float(r["frame_ms"]) for r in full if r["mode"] == mode}
        if not ms:
            continue
        grow = ms[scenes[-1]] / ms[scenes[0]]
        lines.append(f"| {label} | " + " | ".join(f"{ms[s]:.0f}" for s in scenes) +
                     f" | × {grow:.1f} |" if grow < 10 else f"| {label} | " +
                     " | ".join(f"{ms[s]:.0f}" for s in scenes) + f" | × {grow:.0f} |")
    return "\n".join(lines)


def dask_block() -> str:
    """docs/distributed.md: the bake on a local Dask cluster against the local
    bake, per scene and per pass (docs/bench/dask.json, bench bake --dask)."""
    r = _load("dask.json")
    st = r["settings"]
    lines = [
        f"`{r['command']}`, {r['date']}, on {machine_text(r['machine'])}. The default bake (transfer "
        f"{st['rays']} rays + {st['bounces']} {st['bounce_mode']} bounce of {st['bounce_rays']} rays, tuning "
        f"{st['tuning']}, forest HDRI), {r['resolution']}² atlas, cluster {r['cluster']}, fastest of {r['repeat']} "
        f"interleaved runs, textures checked identical every run:",
        "",
        "| scene | local bake | cluster | speed-up | cluster overhead |",
        "|---|---|---|---|---|"]
    for s in r["scenes"]:
        lines.append(f"| {s['name'].split(' (')[0]}, {_si(s['triangles'])} triangles | {s['local_s']:.2f} s | {s['cluster_s']:.2f} s "
                     f"(start {s['start_s']:.2f} s) | {s['local_s'] / s['cluster_s']:.2f} | "
                     f"{100 * s['overhead']:.1f} % |")
    lines += ["", "| scene | pass | tasks | rays | task s | wall s | core ns/ray | sent to each worker | "
                  "result B/ray | overhead |", "|---|---|---|---|---|---|---|---|---|---|"]
    for s in r["scenes"]:
        for p in s["passes"]:
            rays = max(p["rays"], 1)
            lines.append(f"| {_si(s['triangles'])} | {p['what']} | {p['tasks']} | {p['rays'] / 1e6:.1f} M | "
                         f"{p['task_seconds']:.2f} | {p['wall_seconds']:.2f} | {1e9 * p['task_seconds'] / rays:.1f} | "
                         f"{p['sent_bytes'] / 1e6:.1f} MB | {p['result_bytes'] / rays:.2f} | "
                         f"{100 * p['overhead']:.1f} % |")
    lines.append("")
    lines.append("The scene goes to every worker once: " + ", ".join(
        f"{s['scene_bytes'] / 1e6:.1f} MB ({_si(s['triangles'])} triangles)" for s in r["scenes"]) +
        ". A unit is on average " + ", ".join(
        f"{s['rays'] / max(s['tasks'], 1) / 1e6:.1f} M rays and {s['task_s'] / max(s['tasks'], 1):.2f} s of a core, "
        f"returning {s['result_bytes'] / max(s['tasks'], 1) / 1e6:.1f} MB ({_si(s['triangles'])})"
        for s in r["scenes"]) + ".")
    return "\n".join(lines)


def dask_model_block() -> str:
    """docs/distributed.md: the farm model fitted on a local:1 run and checked
    on the cluster run (docs/bench/dask.json)."""
    r = _load("dask.json")
    models = [s for s in r["scenes"] if s.get("model")]
    if not models:
        return f"(the last run, `{r['command']}`, fitted no model: run it without --no-model)"
    from .farm_model import model  # the one formula of the model (loads the bake's modules: only here)
    local = re.search(r"--dask local:(\d+)", r["command"])
    bw = models[0]["model"]["bandwidth"]
    lines = [f"From `{r['command']}`, {r['date']}; links of B = {bw / 1e9:.2f} GB/s:", "",
             "| scene | fitted on `local:1` | cluster: predicted / measured | 1 worker | 8 workers | 64 workers |",
             "|---|---|---|---|---|---|"]
    for s in models:
        m = s["model"]
        pred = model(m, int(local.group(1)), float("inf")) if local else None
        check = (f"{pred:.2f} / {s['cluster_s']:.2f} s ({100 * (pred / s['cluster_s'] - 1):+.0f} %)"
                 if pred else "not a local cluster")
        lines.append(f"| {_si(s['triangles'])} triangles | {m['fit_on_local_1_s']:.2f} s: start {m['start']:.2f}, "
                     f"client {m['client']:.2f}, BVH {m['bvh']:.2f}, ray work {m['work']:.2f} core-s, "
                     f"{m['tasks']} tasks × {1e3 * m['tau']:.1f} ms, "
                     f"{(m['scene_bytes'] + m['sent_bytes']) / 1e6:.0f} MB to each worker, "
                     f"{m['result_bytes'] / 1e6:.0f} MB back | {check} | "
                     + " | ".join(f"{m['farm_s'][w]:.1f} s" for w in ("1", "8", "64")) + " |")
    return "\n".join(lines)


def _mb(n: float) -> str:
    return f"{n / 1e6:.2f} MB"


def web_block(r: dict | None = None) -> str:
    """docs/benchmarks.md: the glTF export and the web viewer
    (docs/bench/web.json, bench web); ``r``: a record instead of the file."""
    r = _load("web.json") if r is None else r
    st, sc, b, ex, by = r["settings"], r["scene"], r["bake"], r["export"], r["bytes"]
    pay, exr = by["payload"], by["exr"]
    w, h = st["size"]
    sw, sh = st["small_size"]
    br, la = r["browser"], r["loadavg"]
    kinds = {"transfer": "transfer", "relightDC": "relightable bounce DC rows",
             "relightGlossy": "relightable bounce glossy rows", "bounce": "baked bounce"}
    rest = by["glb"] - pay["total"]
    files = ", ".join(f"`{n}` {_mb(f['bytes'])} ({f['channels']} {'/'.join(f['types'])} channels, "
                      f"{f['compression'].replace('_COMPRESSION', '')})" for n, f in exr["files"].items())
    same = ("half with lossless compression already: their size is the lossless half size" if exr["all_half_lossless"]
            else f"as lossless half EXRs (half ZIP copies where not): {_mb(exr['half_lossless_total'])}")
    loads = r["page_load"]["seconds"]
    code = r.get("code")
    at = (f" (code at {code['commit']}" + (f", with {', '.join(code['changed'])} changed" if code["changed"] else "")
          + ")") if code else ""
    lines = [
        f"`{r['command']}`, {r['date']}{at}, on {machine_text(r['machine'])}; chromium-headless-shell "
        f"{br['version']}, WebGL2 on `{br['webgl_renderer']}`: SwiftShader, the CPU, so the frame times measure "
        f"a software rasteriser, not a graphics card. Machine load average (1, 5, 15 min) {la['start']} at the "
        f"start, {la.get('end')} at the end" + (
            "; 1-minute load average as each phase ended (this benchmark alone keeps about 2 busy): "
            + ", ".join(f"{k} {v}" for k, v in la["after"].items()) if la.get("after") else "") + ".",
        "",
        "| | measured |",
        "|---|---|",
        f"| scene | the demo room: {sc['triangles']:,} triangles, {sc['objects']} objects, one {st['resolution']}² "
        f"atlas (Smart UV), {st['bands']} bands, {st['rays']} rays, {st['bounces']} relightable bounce of "
        f"{st['bounce_rays']} rays, no per-vertex transfer |",
        f"| bake | **{b['seconds']:.1f} s** (the manifest's `seconds.total`: the bake's own stages); wall time of "
        f"`prtt bake` {b['wall_s']:.1f} s (Blender's start, the Smart UV unwrap, the worker, the save) |",
        f"| export (`--encoding {ex.get('encoding', 'half')}`) | **{ex['export_glb_s']:.2f} s**: `export_glb` in a Blender process with the .blend open (first "
        f"call; a second {ex['export_glb_again_s']:.2f} s); wall time of `prtt export` {ex['cli_wall_s']:.2f} s |",
        f"| export / bake | **{100 * ex['ratio']:.1f} %** (`export_glb` / bake); the two commands' wall times "
        f"{100 * ex['ratio_cli']:.1f} %; goal ≤ 10 % |",
        f"| .glb | {_mb(by['glb'])}: PRTT textures {_mb(pay['textures'])} ("
        + ", ".join(f"{kinds.get(k, k)} {_mb(v)}" for k, v in pay["kinds"].items())
        + f"; KTX2 RGBA16F, zstd; {_mb(pay['uncompressed_textures'])} uncompressed), the World's image "
        f"{_mb(pay['environment'])}, the rest (meshes, materials, images) {_mb(rest)} |",
        f"| the bake's EXRs it carries | {_mb(exr['total'])}: {files}; {same} |",
        f"| .glb / EXRs | **{by['ratio_glb_to_exr']:.2f}** (the PRTT textures alone "
        f"{by['ratio_textures_to_exr']:.2f}); goal ≤ 1 |",
        *[f"| `--encoding {e['encoding']}` | export {e['export_glb_s']:.2f} s `export_glb` (again "
          f"{e['export_glb_again_s']:.2f} s; `prtt export` {e['cli_wall_s']:.2f} s): **{100 * e['ratio']:.1f} %** "
          f"of the bake; .glb {_mb(e['glb'])} (PRTT textures {_mb(e['payload']['textures'])}): "
          f"**{e['ratio_glb_to_exr']:.2f}** × the EXRs; page load " + (
              f"{e['page_load']['median_s']:.1f} s (median of {len(e['page_load']['seconds'])}) |"
              if e["page_load"]["seconds"] else "did not reach `ready` |")
          for e in r.get("encodings", [])[1:]],
        f"| page load to the first frame ({w} × {h}, tpfl, `--encoding {ex.get('encoding', 'half')}`) | " + (
            f"**{r['page_load']['median_s']:.1f} s**, median of {len(loads)} loads in a freshly launched browser "
            f"each ({', '.join(f'{v:.1f}' for v in loads)} s): `goto` until the title says `ready` |"
            if loads else "no load reached `ready` |"),
        "",
        f"| mode, {w} × {h}, bounces on (`--encoding {ex.get('encoding', 'half')}`) | ms per frame, median of {st['frames']} | min–max | FPS |",
        "|---|---|---|---|"]
    for f in r["frames"]:
        if "median_ms" in f:
            lines.append(f"| {f['mode']} | **{f['median_ms']:.0f}** | {f['min_ms']:.0f}–{f['max_ms']:.0f} | "
                         f"{1000 / f['median_ms']:.3g} |")
        else:
            lines.append(f"| {f['mode']} | the page said `{f['title']}` | | |")
    if r.get("scaling"):
        lines += ["", f"Frame time against triangles, tpfl, bounces on; each scene a {st['scaling_resolution']}² "
                      f"texture set per object, {st['scaling_rays']} rays, 1 relightable bounce of "
                      f"{st['scaling_bounce_rays']} rays (the rays do not change a frame's work; the sets are not the 1024² "
                      f"atlas above, so compare these rows with each other); "
                      f"median of {st['frames']} frames:", "",
                  f"| scene | triangles | .glb | {w} × {h} ms | {sw} × {sh} ms | ns per pixel at {w} × {h} |",
                  "|---|---|---|---|---|---|"]
        for s in r["scaling"]:
            ms = [f"**{z['median_ms']:.0f}**" if "median_ms" in z else f"`{z['title']}`" for z in s["sizes"]]
            ns = s["sizes"][0].get("ns_per_pixel")
            lines.append(f"| {s['scene']} | {s['triangles']:,} | {_mb(s['glb_bytes'])} | {ms[0]} | {ms[1]} | "
                         + (f"{ns:.0f}" if ns is not None else "") + " |")
    return "\n".join(lines)


#: The goals of issue #35 for the demo's bake, largest process, in MiB (1 GB = 10^9 bytes; 1.5 GB; 4 GB).
MEMORY_GOALS_MB = {1024: 1e9 / 2 ** 20, 2048: 1.5e9 / 2 ** 20, 4096: 4e9 / 2 ** 20}


def memory_block(r: dict | None = None) -> str:
    """docs/benchmarks.md: peak memory and seconds against the atlas
    (docs/bench/memory.json, bench memory); ``r``: a record instead of the file."""
    r = _load("memory.json") if r is None else r
    rows = r["demo"]
    code = f" (code at {r['commit']})" if r.get("commit") else ""
    lines = [
        f"`{r['command']}`, {r['date']}{code}, on {machine_text(r['machine'])}. The demo room (21K "
        f"triangles, Smart UV into one atlas as `prtt demo` unwraps it) baked by `prtt bake` at each size with the "
        f"defaults (256 rays, per-vertex transfer, one relightable bounce, tuning auto), then drawn by "
        f"`prtt render` at 320 × 180 (llvmpipe: the GPU's textures are in the process's memory). MiB = 2^20 bytes.",
        "",
        "| atlas | covered texels | bake s | µs per atlas texel | **worker peak RSS** | estimate before the bake "
        "| goal (#35) | Blender side (bake command) | render: peak RSS, s | textures (as stored, uncompressed) | on disk |",
        "|---|---|---|---|---|---|---|---|---|---|---|"]
    for x in rows:
        goal = MEMORY_GOALS_MB.get(x["size"])
        est = x.get("estimate_mb")
        off = f" ({100 * (est / x['worker_peak_mb'] - 1):+.0f} %)" if est else ""
        lines.append(
            f"| {x['size']}² | {x['texels']:,} | {x['seconds']['total']:.1f} | "
            f"{1e6 * x['seconds']['total'] / x['atlas_texels']:.2f} | **{x['worker_peak_mb']:.0f} MiB** | "
            f"{est or 0:.0f} MiB{off} | "
            + (f"≤ {goal:.0f} MiB: {'met' if x['worker_peak_mb'] <= goal else '**not met**'}" if goal else "—")
            + f" | {x['blender_side_peak_mb']:.0f} MiB | {x['render_peak_mb']:.0f} MiB, {x['render_s']:.1f} s | "
            f"{x['texture_bytes'] / 2 ** 20:.0f} MiB | {x['disk_bytes'] / 2 ** 20:.0f} MiB |")
    stages = []
    for x in rows:
        for k in x["stages_mb"] or {}:
            if k not in stages:
                stages.append(k)
    lines += ["", "Peak RSS of the worker per stage (MiB; each stage's own peak, including what earlier stages "
                  "still hold: the manifest's `memory`):", "",
              "| atlas | " + " | ".join(stages) + " |", "|---|" + "---|" * len(stages)]
    for x in rows:
        lines.append(f"| {x['size']}² | " + " | ".join(f"{(x['stages_mb'] or {}).get(k, float('nan')):.0f}"
                                                       for k in stages) + " |")
    if all("render_estimate_mb" in x for x in rows):
        lines += ["", "`prtt render` of each bake (320 × 180): what the process held before its textures, their "
                      "bytes on the GPU (llvmpipe: this process's memory), the rest of its peak (the upload's band, "
                      "the frame, allocator slack) and the estimate it printed before loading them "
                      "(`offscreen.check_memory`):", "",
                  "| atlas | **render peak RSS** | held before the textures | textures on the GPU "
                  "| peak − before − GPU | its estimate | render s |",
                  "|---|---|---|---|---|---|---|"]
        for x in rows:
            rest = x["render_peak_mb"] - x["render_base_mb"] - x["render_gpu_mb"]
            lines.append(
                f"| {x['size']}² | **{x['render_peak_mb']:.0f} MiB** | {x['render_base_mb']:.0f} MiB | "
                f"{x['render_gpu_mb']:.0f} MiB | {rest:.0f} MiB | {x['render_estimate_mb']:.0f} MiB "
                f"({100 * (x['render_estimate_mb'] / x['render_peak_mb'] - 1):+.0f} %) | {x['render_s']:.1f} |")
    b = r.get("bunnies")
    if b:
        lines += ["", f"{b['scene']}: {b['triangles']:,} triangles in {b['sets']} texture sets, {b['texels']:,} "
                      f"texels, the same defaults (`bake-job`): **{b['worker_peak_mb']:.0f} MiB** peak "
                      f"(estimate {b['estimate_mb'] or 0:.0f} MiB, "
                      f"{100 * ((b['estimate_mb'] or 0) / b['worker_peak_mb'] - 1):+.0f} %), "
                      f"{b['seconds']['total']:.1f} s."]
    d = r.get("dask")
    if d:
        code = f", code at {d['commit']}" if d.get("commit") else ""
        lines += ["", f"On a local Dask cluster of 2 worker processes (`bake-job --dask local:2`, the demo's job; "
                      f"`{d['command']}`, {d['date']}{code}): the client plans, builds the G-buffers and exit "
                      f"tables and writes; each worker holds the scene and what a pass sends it "
                      f"(the manifest's `memory.dask_workers`):", "",
                  "| atlas | client peak | client estimate | worker peaks | worker estimate (largest check) |",
                  "|---|---|---|---|---|"]
        for x in d["runs"]:
            top = max(x["worker_peaks_mb"]) if x["worker_peaks_mb"] else None
            west = x.get("worker_estimate_mb")
            lines.append(
                f"| {x['size']}² | **{x['client_peak_mb']:.0f} MiB** | {x['client_estimate_mb']:.0f} MiB "
                f"({100 * (x['client_estimate_mb'] / x['client_peak_mb'] - 1):+.0f} %) | "
                + ", ".join(f"{v:.0f}" for v in x["worker_peaks_mb"]) + " MiB | "
                + (f"{west:.0f} MiB ({100 * (west / top - 1):+.0f} %) |" if west and top else "— |"))
    m = r.get("memray")
    if m:
        lines += ["", f"What the {m['size']}² bake's heap peak ({m['heap_peak_mb']:.0f} MiB as memray counts it: "
                      f"planes already given back page by page still count there) is made of, by allocation site:",
                  "", "| MiB | where (innermost PRTT frames) |", "|---|---|"]
        lines += [f"| {s['mb']:.0f} | `{s['where']}` |" for s in m["sites"]]
    return "\n".join(lines)


def fuzz_block(r: dict | None = None) -> str:
    """docs/fuzzing.md: executions, speed, peak RSS and findings per reader
    (docs/bench/fuzz.json, ``python -m prtt_addon.dev.fuzz --combine``)."""
    r = _load("fuzz.json") if r is None else r
    lines = [f"On {machine_text(r['machine'])}; " + "; ".join(f"`{x['command']}` ({x['date']})" for x in r["runs"])
             + ". libFuzzer's bounds: 1 s an input, 2048 MB resident.", "",
             "| reader | what it covers | executions | seconds | executions/s | peak RSS | corpus | findings |",
             "|---|---|---|---|---|---|---|---|"]
    for x in r["runs"]:
        for t in x["reports"]:
            found = ", ".join(t["findings"]) if t["findings"] else "none"
            if t.get("hangs"):          # the page's: contained by its decoder's time limit
                found += f" ({len(t['hangs'])} hung, ended by the page's time limit)"
            lines.append(f"| `{t['target']}` | {t['reader']} | {t['executions']:,} | {t['seconds']:.0f} | "
                         f"{t['exec_per_s']:,} | {t['peak_rss_mb']} MB | {t['corpus']} | {found} |")
    return "\n".join(lines)


#: Generated blocks: name -> (pages, maker).
BLOCKS = {"bake": (("README.md",), bake_block), "render": (("README.md",), render_block),
          "preview": (("docs/preview.md",), preview_block),
          "dask": (("docs/distributed.md",), dask_block), "dask-model": (("docs/distributed.md",), dask_model_block),
          "web": (("docs/benchmarks.md",), web_block), "memory": (("docs/benchmarks.md",), memory_block),
          "fuzz": (("docs/fuzzing.md",), fuzz_block)}


def _pattern(name: str):
    return re.compile(rf"<!-- figures:{name} -->\n(.*?)\n?<!-- /figures:{name} -->", re.S)


def stale_blocks(write: bool = False) -> list:
    """(page, block) pairs whose text differs from their record's; with
    ``write``, rewritten."""
    stale = []
    for name, (pages, make) in BLOCKS.items():
        text = make()
        for page in pages:
            path = os.path.join(ROOT, page)
            with open(path, encoding="utf-8") as f:
                doc = f.read()
            m = _pattern(name).search(doc)
            if m is None:
                stale.append((page, f"{name} (no <!-- figures:{name} --> block)"))
                continue
            if m.group(1) != text:
                stale.append((page, name))
                if write:
                    doc = doc[:m.start()] + f"<!-- figures:{name} -->\n{text}\n<!-- /figures:{name} -->" \
                        + doc[m.end():]
                    with atomic_write(path) as tmp:
                        with open(tmp, "w", encoding="utf-8") as f:
                            f.write(doc)
    return stale


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench figures", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--check", action="store_true", help="only report stale blocks (exit 1 if any)")
    args = p.parse_args(argv)
    stale = stale_blocks(write=not args.check)
    for page, name in stale:
        print(f"{page}: figures block {name} {'is stale' if args.check else 'rewritten'}")
    if not stale:
        print("every figures block matches its benchmark record")
    return 1 if args.check and stale else 0


if __name__ == "__main__":
    sys.exit(main())
