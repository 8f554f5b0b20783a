"""``python -m prtt_addon.dev.bench bake``: the transfer bake against raw Embree.

Bakes the transfer of the room-class scene (1024^2 atlas, 5 bands, 256 rays
per texel by default; ``bounces = 0``: the bounce has its own benchmark,
``bench bounce``, and its rays are not the transfer rays the ratio divides)
through the real pipeline (``core.bake.pipeline.runner.bake_scene``: G-buffer,
analytic test, rays, projection, dilation, EXR writing) and prints seconds per
stage and rays/s end to end (``--dask``: the bake on a Dask cluster against
the local one instead, bench/dask_bench.py). Then, in the same run, it regenerates the *same
rays* for a sample of the bake's chunks and traces them with bare embreex
``run(..., query='OCCLUDED')`` calls on the same number of threads: the raw
Embree throughput the pipeline is compared with (target >= 0.8).

Timing noise on a shared machine is +-5-20 % between runs, and a bake and a
raw run that happen to meet different noise give a ratio off by as much. So
the two are interleaved ``--repeat`` times (bake, raw, bake, raw, ...) and
each side's fastest run is compared (the usual best-of-N of ``timeit``); every
pair's own ratio is printed too.

The settings measured are printed first and written, with the date, the
machine and every figure printed, to ``docs/bench/bake.json`` (``--json``);
``python -m prtt_addon.dev.bench figures`` writes the README's table from it.

Also reported: texel-samples per second per core (texels x rays per texel, the
unit of the C++ SH-lightmap baker reference, 1.5 M/s/core on this class of
machine), and with ``--scaling`` a table over triangle counts and resolutions.
"""
from __future__ import annotations

import argparse
import concurrent.futures as cf
import dataclasses
import os
import tempfile
import time

import numpy as np

from ...core.bake.estimators.raytrace import RayScene
from ...core.bake.estimators.sampling import pattern_bank
from ...core.bake.estimators.transfer import chunk_frames, chunk_plan
from ...core.bake.pipeline.context import BakeSettings
from ...core.bake.pipeline.runner import bake_scene
from ...core.bake.pipeline.stages import bake_points_input, scene_face_data
from ...core.texels.gbuffer import build_gbuffer
from . import dask_bench, figures, scene_library

#: Reference: an open C++ SH-lightmap baker on Embree 4, per core (issue 3).
CPP_REFERENCE_TEXEL_SAMPLES_PER_CORE = 1.5e6


def raw_embree_batches(sc, settings: BakeSettings, *, fraction: float = 0.125) -> tuple:
    """The bake's own rays for a sample of its chunks, as (RayScene, [(origins, dirs)])."""
    rs = RayScene(sc.positions)
    fn, normal_group, clear, _ = scene_face_data(sc, analytic=settings.analytic)
    batches = []
    for s in range(sc.n_sets):
        gb = build_gbuffer(sc, s)
        pts = bake_points_input(sc, s, gb, fn, clear, normal_group)
        chunks, G = chunk_plan(pts, settings)
        dirs_bank, _, _ = pattern_bank(G, settings.rays, settings.bands, settings.sampler,
                                       settings.distribution, settings.seed)
        step = max(1, int(round(1.0 / fraction)))
        for ch in chunks[::step]:
            idx = ch.idx
            fr = chunk_frames(rs, pts, idx, settings.seed, shared=ch.shared)
            if ch.shared:
                # The bake traces a shared chunk direction by direction: same order here.
                Dw = dirs_bank[ch.g] @ np.asarray(fr.R[0]).T
                batches.append((np.ascontiguousarray(np.tile(fr.origins, (settings.rays, 1))),
                                np.ascontiguousarray(np.repeat(Dw, idx.size, axis=0))))
                continue
            D = np.matmul(dirs_bank[ch.g][None], fr.R.transpose(0, 2, 1))
            O = np.repeat(fr.origins, settings.rays, axis=0)
            D = D.reshape(-1, 3)
            if fr.horizon.any():
                below = (np.einsum("nsc,nc->ns", D.reshape(idx.size, -1, 3), fr.geo_normal) <= 0)
                keep = ~(below & fr.horizon[:, None]).ravel()
                O, D = O[keep], D[keep]
            batches.append((np.ascontiguousarray(O), np.ascontiguousarray(D)))
    return rs, batches


def raw_embree_rays_per_s(rs, batches, threads: int) -> float:
    """Trace ``batches`` with bare embreex calls on ``threads`` threads: rays/s.

    Batches go to whichever thread is free, biggest first (as the bake's
    chunks do), so an unlucky static split cannot make Embree look slow."""
    n_rays = sum(b[0].shape[0] for b in batches)
    order = sorted(batches, key=lambda b: -b[0].shape[0])
    t = time.perf_counter()
    with cf.ThreadPoolExecutor(threads) as ex:
        list(ex.map(lambda b: rs.occluded_raw(*b), order))
    return n_rays / (time.perf_counter() - t)


def run_bake(sc, settings: BakeSettings) -> dict:
    with tempfile.TemporaryDirectory(prefix="prtt-bench-") as d:
        t = time.perf_counter()
        m = bake_scene(sc, d, settings, skip_if_unchanged=False)
        m["wall"] = time.perf_counter() - t
        m["output_bytes"] = sum(os.path.getsize(os.path.join(d, f)) for f in m["files"])
    return m


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m prtt_addon.dev.bench bake", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=1024)
    p.add_argument("--rays", type=int, default=256)
    p.add_argument("--bands", type=int, default=5)
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--per-object", action="store_true", help="one texture set per object instead of an atlas")
    p.add_argument("--raw-fraction", type=float, default=0.125,
                   help="share of the bake's chunks re-traced for the raw Embree baseline")
    p.add_argument("--repeat", type=int, default=None,
                   help="bake / raw Embree pairs, interleaved; each side's fastest run is compared (default 5; "
                        "with --dask: local / cluster pairs, default 2)")
    p.add_argument("--scaling", action="store_true",
                   help="also print the 21K -> 1.3M triangles and 256^2 -> 2048^2 tables")
    p.add_argument("--json", default=None,
                   help="where the run's settings and figures go (default docs/bench/bake.json, with --dask "
                        "docs/bench/dask.json; '' for none)")
    dask_bench.add_arguments(p)
    args = p.parse_args(argv)
    args.argv = argv
    if args.json is None:
        args.json = figures.bench_path("dask.json" if args.dask else "bake.json")
    if args.dask:
        args.repeat = 2 if args.repeat is None else args.repeat
        return dask_bench.run(args)
    args.repeat = 5 if args.repeat is None else args.repeat
    # Transfer only: bounces (on by default) are bench bounce's, and their rays
    # are not the transfer rays that the ratio to raw Embree counts. Without
    # guided rays or texel validity: the ratio is the cosine kernel's against
    # raw Embree on its own rays (guided texels trace other rays, with numpy
    # work per ray; validity traces rays of its own); the default bake (guided
    # rays, their filter, texel validity) is timed beside each pair.
    st = BakeSettings(rays=args.rays, bands=args.bands, threads=args.threads, bounces=0, guiding=False,
                      texel_validity=False)
    d = BakeSettings()
    st_default = dataclasses.replace(st, guiding=d.guiding, texel_validity=d.texel_validity,
                                     guided_filter=d.guided_filter)
    cores = st.n_threads
    print("settings: " + figures.settings_line(st, BakeSettings()))

    t = time.perf_counter()
    sc = scene_library.room_scene(args.resolution, atlas=not args.per_object)
    t_scene = time.perf_counter() - t
    print(f"room-class scene: {sc.n_triangles} triangles, {sc.n_sets} texture set(s) at "
          f"{args.resolution}^2, {args.bands} bands, {args.rays} rays/texel, {cores} threads "
          f"(scene build/unwrap or cache load: {t_scene:.2f} s, not part of the bake)")
    rs_raw, batches = raw_embree_batches(sc, st, fraction=args.raw_fraction)
    n_raw = sum(b[0].shape[0] for b in batches)
    raw_1 = raw_embree_rays_per_s(rs_raw, batches, 1)
    runs, raws, guided_runs = [], [], []
    print(f"\n{args.repeat} interleaved pair(s) of a bake (--no-guiding --no-texel-validity) and raw embreex OCCLUDED "
          f"on {n_raw:,} of its rays ({cores} threads), each followed by the default bake (guided rays, their "
          f"filter, texel validity):")
    for i in range(max(1, args.repeat)):
        m = run_bake(sc, st)
        raw = raw_embree_rays_per_s(rs_raw, batches, cores)
        g = run_bake(sc, st_default)
        runs.append(m)
        raws.append(raw)
        guided_runs.append(g)
        print(f"  pair {i + 1}: bake {m['seconds']['total']:6.2f} s, {m['rays_per_second_end_to_end'] / 1e6:6.2f} "
              f"Mrays/s end to end; raw {raw / 1e6:6.2f} Mrays/s; ratio {m['rays_per_second_end_to_end'] / raw:.3f}; "
              f"default bake {g['seconds']['total']:6.2f} s",
              flush=True)
    m = min(runs, key=lambda r: r["seconds"]["total"])
    raw = max(raws)
    sec, tot = m["seconds"], m["totals"]
    print("\nseconds per stage (fastest bake):")
    for k in ("bvh", "analytic_test", "gbuffer", "trace", "dilate", "write", "total"):
        print(f"  {k:14s} {sec[k]:8.3f}")
    texel_samples = tot["texels"] * args.rays
    print(f"\ntexels {tot['texels']}, analytic (zero-ray) {tot['analytic_texels']}, "
          f"rays traced {tot['rays_traced']:,} of naive {tot['rays_naive']:,} "
          f"({100 * (1 - tot['rays_traced'] / max(tot['rays_naive'], 1)):.1f}% skipped)")
    e2e = m["rays_per_second_end_to_end"]
    print(f"end-to-end: {sec['total']:.2f} s, {e2e / 1e6:.2f} Mrays/s traced; "
          f"{texel_samples / sec['total'] / cores / 1e6:.2f} M texel-samples/s/core "
          f"(C++ reference {CPP_REFERENCE_TEXEL_SAMPLES_PER_CORE / 1e6:.1f} M: "
          f"x{texel_samples / sec['total'] / cores / CPP_REFERENCE_TEXEL_SAMPLES_PER_CORE:.1f})")
    print(f"raw embreex OCCLUDED on {n_raw:,} of the same rays: {raw_1 / 1e6:.2f} Mrays/s on 1 thread, "
          f"{raw / 1e6:.2f} Mrays/s on {cores} (fastest of {len(raws)})")
    pair = sorted(r["rays_per_second_end_to_end"] / w for r, w in zip(runs, raws))
    print(f"ratio end-to-end / raw Embree: {e2e / raw:.3f}   (fastest of each; pairs {pair[0]:.3f}-{pair[-1]:.3f}, "
          f"median {pair[len(pair) // 2]:.3f}; trace stage alone: {m['rays_per_second_trace'] / raw:.3f}; "
          f"target >= 0.8)")
    g = min(guided_runs, key=lambda r: r["seconds"]["total"])
    guided_texels = int(g["totals"].get("guided_texels", 0))
    per_set = {k: sum(int(r.get(k, 0)) for r in g["sets"]) for k in ("inside_texels", "filtered_texels", "moved_texels")}
    print(f"default bake (guided rays, their filter, texel validity): {g['seconds']['total']:.2f} s (fastest of "
          f"{len(guided_runs)}), {guided_texels:,} texels guided ({per_set['filtered_texels']:,} smoothed), "
          f"{per_set['inside_texels']:,} inside geometry, {per_set['moved_texels']:,} moved across walls; "
          f"{g['seconds']['total'] / sec['total']:.2f} x the bake without")
    print(f"texture bytes: {m['output_bytes']:,} on disk (half, ZIP); "
          f"{args.bands ** 2 * 2} B/texel in memory as half, {args.bands ** 2 * 4} B as float")
    record = {"scene": {"triangles": int(sc.n_triangles), "sets": int(sc.n_sets), "resolution": args.resolution},
              "settings": figures.settings_dict(st), "threads": cores, "repeat": len(runs),
              "seconds": {k: float(sec[k]) for k in ("bvh", "analytic_test", "gbuffer", "trace", "dilate", "write",
                                                      "total")},
              "texels": int(tot["texels"]), "rays_traced": int(tot["rays_traced"]),
              "rays_naive": int(tot["rays_naive"]),
              "mrays_per_s_end_to_end": e2e / 1e6, "mrays_per_s_trace": m["rays_per_second_trace"] / 1e6,
              "raw_mrays_per_s": raw / 1e6, "raw_mrays_per_s_1_thread": raw_1 / 1e6,
              "ratio": e2e / raw, "ratio_pairs": pair, "ratio_trace": m["rays_per_second_trace"] / raw,
              "texel_samples_per_s_per_core": texel_samples / sec["total"] / cores,
              "output_bytes": int(m["output_bytes"]),
              "guided": {"total_s": float(g["seconds"]["total"]), "guided_texels": guided_texels, **per_set,
                         "pairs_s": [float(r["seconds"]["total"]) for r in guided_runs]},
              "pairs": [{"total_s": float(r["seconds"]["total"]),
                         "ratio": r["rays_per_second_end_to_end"] / w} for r, w in zip(runs, raws)]}

    if args.scaling:
        record["scaling_triangles"], record["scaling_resolution"] = [], []
        print("\nscaling with triangles (room atlas 1024^2 + occluder-only subdivided bunnies):")
        print(f"  {'triangles':>10} {'bvh s':>7} {'trace s':>8} {'total s':>8} {'Mrays/s':>8}")
        for target in (21_000, 300_000, 1_300_000):
            sct = scene_library.triangle_scaling_scene(target, 1024)
            mm = run_bake(sct, st)
            print(f"  {sct.n_triangles:10d} {mm['seconds']['bvh']:7.2f} {mm['seconds']['trace']:8.2f} "
                  f"{mm['seconds']['total']:8.2f} {mm['rays_per_second_end_to_end'] / 1e6:8.2f}")
            record["scaling_triangles"].append({"triangles": int(sct.n_triangles),
                                                **{k: float(mm["seconds"][k]) for k in ("bvh", "trace", "total")}})
        print("scaling with resolution (room, same settings):")
        print(f"  {'texels':>10} {'total s':>8} {'Mrays/s':>8}")
        for res in (256, 512, 1024, 2048):
            mm = run_bake(scene_library.room_scene(res, atlas=True), st)
            print(f"  {res:>5}^2     {mm['seconds']['total']:8.2f} {mm['rays_per_second_end_to_end'] / 1e6:8.2f}")
            record["scaling_resolution"].append({"resolution": res, "total": float(mm["seconds"]["total"])})
    if args.json:
        print(f"\nwrote {figures.write_record(args.json, 'bench bake', argv, record)}")
    return 0
