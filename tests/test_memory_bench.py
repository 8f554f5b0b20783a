"""`python -m prtt_addon.dev.bench memory --quick` end to end: the demo scene
(unwrapped at 256²) baked through `prtt bake` at 128² and 256² and rendered;
the record holds every figure docs/benchmarks.md's block reads, and the
bake's estimate is within the ±20 % the docs claim."""
import json
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# about a minute and a half on 2 cores (the demo once, two bakes and two renders)
pytestmark = [pytest.mark.slow, pytest.mark.blender]


def test_memory_bench_quick(tmp_path):
    pytest.importorskip("bpy")
    from prtt_addon.dev.bench import figures
    r = subprocess.run([sys.executable, "-m", "prtt_addon.dev.bench", "memory", "--quick", "--out", str(tmp_path)],
                       capture_output=True, text=True, cwd=ROOT, timeout=900,
                       env=dict(os.environ, PYTHONPATH=ROOT))
    assert r.returncode == 0, r.stderr[-3000:]
    rec = json.load(open(tmp_path / "memory.json"))
    assert [x["size"] for x in rec["demo"]] == [128, 256]
    for x in rec["demo"]:
        assert x["worker_peak_mb"] > 0 and x["render_peak_mb"] > 0 and x["blender_side_peak_mb"] > 0
        assert 0.8 <= x["estimate_mb"] / x["worker_peak_mb"] <= 1.2, x
        assert {"gbuffer", "trace", "write transfer", "bounce"} <= set(x["stages_mb"])
    assert (tmp_path / "memory.png").stat().st_size > 10_000
    assert "| 128² |" in figures.memory_block(rec)
