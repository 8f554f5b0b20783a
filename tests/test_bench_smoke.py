"""The benchmark commands run end to end (small sizes; the real runs are in the README)."""
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = dict(os.environ, PYTHONPATH=ROOT)
pytestmark = pytest.mark.slow


def bench(*args):
    r = subprocess.run([sys.executable, "-m", "prtt_addon.bench", *args], capture_output=True,
                       text=True, env=ENV, cwd=ROOT, timeout=1200)
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_bake_bench():
    out = bench("bake", "--resolution", "256", "--rays", "64")
    assert "ratio end-to-end / raw Embree" in out and "texel-samples/s/core" in out


def test_bounce_bench():
    out = bench("bounce", "--resolution", "256", "--rays", "64", "--bounce-rays", "16")
    assert "shading evaluations" in out
