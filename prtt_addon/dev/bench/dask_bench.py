"""``python -m prtt_addon.dev.bench bake --dask local:2``: the bake on a Dask cluster
against the local bake, and a model of the bake on a farm (docs/distributed.md).

Per scene (the room-class scene, and with ``--big`` the same room with
occluder bunnies up to 1.3M triangles), the default bake (transfer + one
bounce under the forest HDRI) runs locally on all cores and on the cluster,
interleaved ``--repeat`` times; the fastest of each is compared. Every run
checks the cluster's textures against the local ones, byte for byte.

Printed: the speed-up (local seconds / cluster seconds), the cluster's
overhead (the share of the workers' thread time not spent in tasks:
scheduling, transfers, assembly on the client, idle at the tail), per pass
the tasks, rays, core-ns per ray and bytes, and the model

    T(W) = start + client + bvh + R / W + tasks(W) * tau / W
           + (scene + sent) * (1 + 2 * ceil(log3 W)) / B + results / B

with W one-thread workers, R the measured core-seconds of ray work, ``client``
the client's own serial work (G-buffers, exit radiance, dilation, writes,
serialising; it builds no BVH), ``bvh`` one BVH build (each worker builds its
own, at the same time, in its first task), ``tau`` the measured worker-thread time lost per task (scheduling,
transfers, idle at the tail), tasks(W) = max(the measured count, 8 W per
pass) as distributed.units_of cuts them, ``scene``/``sent`` the bytes
scattered to every worker and ``results`` the bytes sent back. Dask
scatters with ``broadcast`` as one copy over the client's link and then a
tree copy between workers (branching factor 2: the holders triple each round,
each sending two copies), so the link term grows with log W, not W; every
link is taken as B bytes/s (``--bandwidth``; on one machine the copies are
in the measured times already, so B is infinite there). The model is fitted
on the local:1 run and checked against the cluster run, then extrapolated
to 8 and 64 workers.
"""
from __future__ import annotations

import tempfile
import time

from ...core.bake.executors.dask_spec import parse_spec
from ...core.bake.pipeline.context import BakeSettings
from ...core.bake.pipeline.runner import bake_scene
from ...core.light.envmap import environment_light
from . import figures, scene_library
from .farm_model import model

#: A farm's client link: 10 GbE.
DEFAULT_BANDWIDTH = 1.25e9


def _bake(sc, st, light, dask):
    """(wall seconds, manifest, {file: sha256} of its textures as the manifest
    records them, the cluster's summary or None)."""
    events = []
    with tempfile.TemporaryDirectory(prefix="prtt-bench-") as d:
        t = time.perf_counter()
        m = bake_scene(sc, d, st, light=light, skip_if_unchanged=False, dask=dask, progress=events.append)
        wall = time.perf_counter() - t
    files = {f: info["sha256"] for f, info in m["file_info"].items() if f.endswith(".exr")}
    summary = next((e["dask"] for e in events if e.get("type") == "info" and "dask" in e), None)
    return wall, m, files, summary


def fit_of(wall: float, m: dict, sm: dict) -> dict:
    """The model's terms from one cluster bake (its wall seconds, manifest, summary)."""
    passes = sm["passes"]
    pass_wall = sum(p["wall_seconds"] for p in passes)
    idle = sum(p["wall_seconds"] * p["threads"] - p["task_seconds"] for p in passes)
    return {"start": sm["start_seconds"], "client": max(0.0, wall - sm["start_seconds"] - pass_wall),
            "bvh": sm["bvh_seconds"], "work": sm["task_seconds"] - sm["bvh_seconds"], "tasks": sm["tasks"],
            "tau": max(0.0, idle) / max(sm["tasks"], 1), "passes": len(passes), "scene_bytes": sm["scene_bytes"],
            "sent_bytes": sm["sent_bytes"], "result_bytes": sm["result_bytes"]}


def run(args) -> int:
    spec = parse_spec(args.dask)
    light = environment_light("forest", 5)
    st = BakeSettings(rays=args.rays, bands=args.bands, threads=args.threads)
    print("settings: " + figures.settings_line(st, BakeSettings()))
    record = {"settings": figures.settings_dict(st), "cluster": spec.describe(), "resolution": args.resolution,
              "repeat": max(1, args.repeat), "scenes": []}
    todo = [("room", lambda: scene_library.room_scene(args.resolution, atlas=True, materials=True))]
    if args.big:
        todo.append(("room + bunnies (1.3M triangles)",
                     lambda: scene_library.with_room_materials(scene_library.triangle_scaling_scene(1_300_000, args.resolution))))
    for name, make in todo:
        sc = make()
        print(f"\n{name}: {sc.n_triangles:,} triangles, {args.resolution}^2 atlas, transfer {st.rays} rays + "
              f"1 bounce x {st.bounce_rays} rays (tuning {st.tuning}), forest HDRI; local: {st.n_threads} threads; "
              f"cluster: {spec.describe()}")
        locals_, clusters = [], []
        for i in range(max(1, args.repeat)):
            wl, ml, fl, _ = _bake(sc, st, light, None)
            wd, md, fd, sm = _bake(sc, st, light, args.dask)
            same = fl == fd
            locals_.append(wl)
            clusters.append((wd, md, sm))
            print(f"  pair {i + 1}: local {wl:6.2f} s, cluster {wd:6.2f} s (start {sm['start_seconds']:.2f} s, "
                  f"overhead {100 * sm['overhead']:.1f} %), textures identical: {same}", flush=True)
            if not same:
                print("  ERROR: the cluster's textures differ from the local bake's")
                return 1
        wl = min(locals_)
        wd, md, sm = min(clusters, key=lambda c: c[0])
        print(f"  speed-up over the local bake: {wl / wd:.2f} (local {wl:.2f} s / cluster {wd:.2f} s, fastest of "
              f"{len(locals_)}); cluster overhead {100 * sm['overhead']:.1f} % of its thread time")
        print(f"  {'pass':9s} {'tasks':>5} {'rays':>12} {'task s':>7} {'wall s':>7} {'core ns/ray':>11} "
              f"{'sent MB':>8} {'result B/ray':>12} {'overhead':>8}")
        for p in sm["passes"]:
            print(f"  {p['what']:9s} {p['tasks']:5d} {p['rays']:12,d} {p['task_seconds']:7.2f} {p['wall_seconds']:7.2f} "
                  f"{1e9 * p['task_seconds'] / max(p['rays'], 1):11.1f} {p['sent_bytes'] / 1e6:8.1f} "
                  f"{p['result_bytes'] / max(p['rays'], 1):12.2f} {100 * p['overhead']:7.1f}%")
        rec = {"name": name, "triangles": int(sc.n_triangles), "local_s": wl, "cluster_s": wd,
               "start_s": sm["start_seconds"], "overhead": sm["overhead"], "scene_bytes": sm["scene_bytes"],
               "rays": sm["rays"], "tasks": sm["tasks"], "task_s": sm["task_seconds"],
               "result_bytes": sm["result_bytes"], "pairs": [[a, c[0]] for a, c in zip(locals_, clusters)],
               "passes": [{k: p[k] for k in ("what", "tasks", "rays", "task_seconds", "wall_seconds", "sent_bytes",
                                             "result_bytes", "overhead")} for p in sm["passes"]]}
        record["scenes"].append(rec)
        print(f"  scene scattered to every worker: {sm['scene_bytes'] / 1e6:.1f} MB; per unit: "
              f"{sm['rays'] / max(sm['tasks'], 1):,.0f} rays, {sm['task_seconds'] / max(sm['tasks'], 1):.3f} s, "
              f"{sm['result_bytes'] / max(sm['tasks'], 1) / 1e3:.0f} kB of results")
        if args.model:
            w1, m1, _, s1 = _bake(sc, st, light, "local:1")
            fit = fit_of(w1, m1, s1)
            print(f"  model fitted on local:1 ({w1:.2f} s): start {fit['start']:.2f} s, client {fit['client']:.2f} s, "
                  f"bvh {fit['bvh']:.2f} s, ray work {fit['work']:.2f} core-s, {fit['tasks']} tasks in "
                  f"{fit['passes']} passes x {1e3 * fit['tau']:.1f} ms, "
                  f"{(fit['scene_bytes'] + fit['sent_bytes']) / 1e6:.1f} MB to each worker, "
                  f"{fit['result_bytes'] / 1e6:.1f} MB back")
            if spec.kind == "local":
                pred = model(fit, spec.workers, float("inf"))
                print(f"  check: {spec.workers} local workers predicted {pred:.2f} s, measured {wd:.2f} s "
                      f"({100 * (pred / wd - 1):+.0f} %)")
            for w in (1, 8, 64):
                print(f"  farm, {w:2d} workers, {args.bandwidth / 1e9:.2f} GB/s client link: "
                      f"{model(fit, w, args.bandwidth):7.2f} s")
            rec["model"] = {"fit_on_local_1_s": w1, **fit,
                            "farm_s": {str(w): model(fit, w, args.bandwidth) for w in (1, 8, 64)},
                            "bandwidth": args.bandwidth}
    if args.json:
        print(f"\nwrote {figures.write_record(args.json, 'bench bake', args.argv, record)}")
    return 0


def add_arguments(p) -> None:
    p.add_argument("--dask", metavar="local[:N]|tcp://HOST:PORT",
                   help="compare the bake on this Dask cluster with the local one (and model a farm)")
    p.add_argument("--big", action="store_true", help="with --dask: also the 1.3M-triangle scene")
    p.add_argument("--no-model", dest="model", action="store_false",
                   help="with --dask: skip the local:1 run that fits the farm model")
    p.add_argument("--bandwidth", type=float, default=DEFAULT_BANDWIDTH,
                   help="with --dask: the farm's client link in bytes/s for the model (default 10 GbE)")
