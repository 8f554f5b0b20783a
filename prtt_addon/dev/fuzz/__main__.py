"""Run the fuzz harnesses and report, reader by reader.

    python -m prtt_addon.dev.fuzz [TARGET ...] [--runs N | --seconds S] [--json FILE]
    ./prtt.sh fuzz ...   (the same)

Each target runs in its own process under atheris (harness.py) on three
corpora: what earlier runs found interesting (``--corpus``/<target>, kept
between runs), the seeds (real files the project writes, made once:
seeds.py) and the saved regression inputs (tests/fuzz_corpus/<target>:
inputs that once broke a reader). libFuzzer's bounds: 1 s an input
(``--timeout``), ``--rss-mb`` of resident memory. Prints, per target,
executions, seconds, executions a second, peak RSS and findings (the
crashing inputs, written to ``--corpus``/findings/<target>/); exits 1 when
any target found something.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time

from . import page
from .seeds import ensure_seeds
from .targets import TARGETS

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
SAVED = os.path.join(ROOT, "tests", "fuzz_corpus")


def run_target(name: str, *, runs: int | None, seconds: float | None, corpus: str, seeds: dict,
               timeout: int = 1, rss_mb: int = 2048, seed: int = 1, fresh: bool = False) -> dict:
    """Fuzz target ``name`` once; returns its report (the numbers printed)."""
    t = TARGETS[name]
    work = os.path.join(corpus, name if not fresh else f"{name}-fresh-{os.getpid()}")
    found = os.path.join(corpus, "findings", name)
    os.makedirs(work, exist_ok=True)
    os.makedirs(found, exist_ok=True)
    before = set(os.listdir(found))
    dirs = [work, os.path.dirname(seeds[t.seeds][0])]
    for kind in dict.fromkeys((name, t.seeds)):       # exr-bands grows from exr's saved inputs too
        if os.path.isdir(os.path.join(SAVED, kind)):
            dirs.append(os.path.join(SAVED, kind))
    flags = [f"-timeout={timeout}", f"-rss_limit_mb={rss_mb}", f"-max_len={t.max_len}", f"-seed={seed}",
             "-print_final_stats=1", f"-artifact_prefix={found}/"]
    flags.append(f"-runs={runs}" if runs is not None else f"-max_total_time={max(1, int(seconds))}")
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "prtt_addon.dev.fuzz.harness", name, *flags, *dirs],
                       capture_output=True, text=True, env=env, cwd=ROOT)
    wall = time.perf_counter() - t0
    stats = dict(re.findall(r"stat::(\w+):\s*(\d+)", p.stderr))
    new = sorted(set(os.listdir(found)) - before)
    report = {"target": name, "reader": t.what, "executions": int(stats.get("number_of_executed_units", 0)),
              "seconds": round(wall, 1), "exec_per_s": int(stats.get("average_exec_per_sec", 0)),
              "peak_rss_mb": int(stats.get("peak_rss_mb", 0)), "corpus": len(os.listdir(work)),
              "findings": [os.path.join(found, f) for f in new], "exit": p.returncode}
    if new or p.returncode not in (0,):
        log = os.path.join(found, f"log-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}.txt")
        with open(log, "w") as f:
            f.write(p.stdout + "\n--- stderr ---\n" + p.stderr)
        # The readers' own repeated complaints (OpenEXR prints one per damaged chunk) are noise here;
        # atheris prints an uncaught exception's traceback on stdout.
        lines = [ln for ln in (p.stdout + "\n" + p.stderr).splitlines()
                 if "EXR_ERR" not in ln and not ln.startswith(("Warning:", "INFO:"))]
        report["log"] = "\n".join(lines[-60:])
        report["log_file"] = log
    return report


def combine(paths: list[str], record: str) -> int:
    """Write ``record`` (the machine, and each run's command, date and reports) from --json files."""
    from ...core.base.atomic import atomic_write
    from ..bench.figures import machine
    runs = []
    for p in paths:
        with open(p, encoding="utf-8") as f:
            runs.append(json.load(f))
    for r in runs:
        for rep in r["reports"]:
            rep.pop("log", None)
            rep.pop("log_file", None)
            rep["findings"] = [os.path.basename(x) for x in rep["findings"]]
    with atomic_write(record) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump({"machine": machine(), "runs": runs}, f, indent=1)
            f.write("\n")
    print(f"wrote {record}: {sum(len(r['reports']) for r in runs)} reports")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m prtt_addon.dev.fuzz", description=__doc__.split("\n\n")[0])
    ap.add_argument("targets", nargs="*", metavar="TARGET", help=f"readers to fuzz (default all: "
                                                                 f"{', '.join(TARGETS)}, page)")
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--runs", type=int, help="executions per target")
    g.add_argument("--seconds", type=float, help="seconds per target (default 60)")
    ap.add_argument("--corpus", default=os.path.join(ROOT, ".fuzz"),
                    help="where seeds, grown corpora and findings are kept (default .fuzz/)")
    ap.add_argument("--timeout", type=int, default=1, help="seconds an input may take (default 1)")
    ap.add_argument("--rss-mb", type=int, default=2048, help="resident memory bound, MB (default 2048)")
    ap.add_argument("--seed", type=int, default=1, help="libFuzzer's random seed (default 1)")
    ap.add_argument("--fresh", action="store_true", help="start from the seeds and saved inputs only "
                                                         "(what CI does), not the grown corpus")
    ap.add_argument("--json", help="write the reports to this file")
    ap.add_argument("--combine", nargs="+", metavar="JSON", help="instead of fuzzing: combine the --json "
                    "reports of earlier runs (e.g. two run side by side) into the record --record names")
    ap.add_argument("--record", help="with --combine: the record to write (docs/bench/fuzz.json; "
                                     "python -m prtt_addon.dev.bench figures writes docs/fuzzing.md's table from it)")
    a = ap.parse_args(argv)
    if a.combine:
        if not a.record:
            ap.error("--combine needs --record")
        return combine(a.combine, a.record)
    names = a.targets or [*TARGETS, "page"]
    bad = [n for n in names if n not in TARGETS and n != "page"]
    if bad:
        ap.error(f"unknown target(s) {bad}; choose from {', '.join(TARGETS)}")
    seconds = a.seconds if a.runs is None and a.seconds is not None else (60.0 if a.runs is None else None)
    seeds = ensure_seeds(os.path.join(a.corpus, "seeds"))
    print(f"{'target':9} {'executions':>11} {'seconds':>8} {'exec/s':>7} {'peak RSS':>9} {'corpus':>7}  findings")
    reports = []
    for n in names:
        if n == "page":
            # The page's JavaScript readers: mutants in node (no coverage across the language boundary).
            r = page.run(seeds, a.runs if a.runs is not None else int(200 * seconds), seed=a.seed,
                         found_dir=os.path.join(a.corpus, "findings", "page"))
        else:
            r = run_target(n, runs=a.runs, seconds=seconds, corpus=a.corpus, seeds=seeds, timeout=a.timeout,
                           rss_mb=a.rss_mb, seed=a.seed, fresh=a.fresh)
        reports.append(r)
        print(f"{n:9} {r['executions']:>11,} {r['seconds']:>8.1f} {r['exec_per_s']:>7,} "
              f"{r['peak_rss_mb']:>6} MB {r['corpus']:>7}  {len(r['findings']) or 'none'}", flush=True)
        for f in r["findings"]:
            print(f"    {f}")
        if r.get("hangs"):
            print(f"    {len(r['hangs'])} inputs hung a decoder (the page ends it after its time limit; "
                  f"kept as {', '.join(r['hangs'][:3])}{' ...' if len(r['hangs']) > 3 else ''})")
        if r["findings"] or r["exit"]:
            print("    " + "\n    ".join(r.get("log", "").splitlines()[-25:]))
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"command": " ".join(["python -m prtt_addon.dev.fuzz"] + (argv or sys.argv[1:])),
                       "date": time.strftime("%Y-%m-%d"), "reports": reports}, f, indent=1)
    return 1 if any(r["findings"] or r["exit"] for r in reports) else 0


if __name__ == "__main__":
    sys.exit(main())
