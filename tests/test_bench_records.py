"""Benchmarks print the settings they measured and write records the docs'
figures are made from (issue 37): `bench bake` times the transfer alone, its
stages add up to its total, and every generated block of README.md matches
its record (`python -m prtt_addon.dev.bench figures --check`)."""
import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = dict(os.environ, PYTHONPATH=ROOT)


def test_bench_bake_measures_the_transfer_it_prints(tmp_path):
    record = tmp_path / "bake.json"
    r = subprocess.run([sys.executable, "-m", "prtt_addon.dev.bench", "bake", "--resolution", "64", "--rays", "16",
                        "--repeat", "1", "--json", str(record)], capture_output=True, text=True, env=ENV,
                       cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stderr
    first = r.stdout.splitlines()[0]
    assert first.startswith("settings: rays=16 (default 256), bands=5, bounces=0 (default 1)"), first
    rec = json.loads(record.read_text())
    assert rec["settings"]["bounces"] == 0 and rec["settings"]["rays"] == 16
    assert rec["date"] and rec["machine"]["cores"] == os.cpu_count() and "embreex" in rec["machine"]["versions"]
    assert rec["command"].startswith("python -m prtt_addon.dev.bench bake --resolution 64")
    s = rec["seconds"]
    stages = sum(v for k, v in s.items() if k != "total")
    # the stages are the bake (a bounce would add time no stage shows)
    assert 0.6 * s["total"] <= stages <= 1.05 * s["total"], s
    assert abs(rec["ratio"] - rec["mrays_per_s_end_to_end"] / rec["raw_mrays_per_s"]) < 1e-9


def test_readme_figures_match_their_records():
    r = subprocess.run([sys.executable, "-m", "prtt_addon.dev.bench", "figures", "--check"], capture_output=True,
                       text=True, env=ENV, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
