"""The benchmark commands run end to end (small sizes; the real runs are in the README)."""
import os
import subprocess
import sys

import pytest

from prtt_addon.dev.bench.stress import CASES

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = dict(os.environ, PYTHONPATH=ROOT)
pytestmark = pytest.mark.slow


def bench(*args):
    r = subprocess.run([sys.executable, "-m", "prtt_addon.dev.bench", *args], capture_output=True,
                       text=True, env=ENV, cwd=ROOT, timeout=1200)
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_bake_bench(tmp_path):
    out = bench("bake", "--resolution", "256", "--rays", "64", "--repeat", "2", "--json", str(tmp_path / "b.json"))
    assert "ratio end-to-end / raw Embree" in out and "texel-samples/s/core" in out
    assert "pair 1:" in out and "pair 2:" in out and "fastest of 2" in out


def test_bounce_bench():
    out = bench("bounce", "--resolution", "256", "--rays", "64", "--bounce-rays", "16")
    assert "shading evaluations" in out and "bounce / transfer:" in out and "within that bake:" in out
    assert "x the transfer-only bake" in out


def test_sweep_quick(tmp_path):
    out = bench("sweep", "--quick", "--out", str(tmp_path))
    for name in ("rays", "resolution", "bands", "storage", "scenes"):
        assert (tmp_path / f"{name}.csv").is_file(), out
    assert (tmp_path / "error_vs_seconds.png").is_file()


def test_sweep_denoise_quick(tmp_path):
    out = bench("sweep", "--quick", "--only", "bounce,denoise", "--out", str(tmp_path))
    assert (tmp_path / "denoise.csv").is_file() and (tmp_path / "denoise_transfer.csv").is_file(), out
    assert (tmp_path / "bounce_denoise.png").is_file() and (tmp_path / "transfer_denoise.png").is_file()
    assert "edge-aware: reaches the raw 32-ray bounce error" in out
    assert "edge-aware: reaches the raw 64-ray transfer error" in out


def test_stress_bench():
    out = bench("stress")
    assert f"{len(CASES)}/{len(CASES)} cases hold" in out, out


def test_auto_bench_quick(tmp_path):
    out = bench("auto", "--quick", "--out", str(tmp_path))
    last = out.strip().splitlines()[-1]
    assert last.startswith("auto vs fixed: time ÷ ") and ", bytes ÷ " in last and " % vs " in last, out
    for name in ("fixed", "grid 1/2", "auto"):
        assert f"  {name}" in out


def test_relight_bench_quick(tmp_path):
    out = bench("relight", "--quick", "--out", str(tmp_path))
    for scene in ("ball", "room"):
        assert f"  {scene}: relightable bounce " in out and "relit vs rebaked at most" in out, out
        assert f"  {scene:6s}    90 deg  relit vs rebaked" in out


def test_bake_bench_on_a_dask_cluster(tmp_path):
    pytest.importorskip("distributed")
    # Its record goes to tmp_path: the default, docs/bench/dask.json, is what docs/distributed.md is written from.
    out = bench("bake", "--dask", "local:2", "--resolution", "128", "--rays", "32", "--repeat", "1",
                "--json", str(tmp_path / "dask.json"))
    assert "textures identical: True" in out and "speed-up over the local bake:" in out
    assert "check: 2 local workers predicted" in out and "farm, 64 workers" in out


def test_sweep_adaptive_bounce_quick(tmp_path):
    out = bench("sweep", "--quick", "--only", "adaptive_bounce", "--out", str(tmp_path))
    assert (tmp_path / "adaptive_bounce.csv").is_file(), out
    assert "oracle allocation needs" in out
