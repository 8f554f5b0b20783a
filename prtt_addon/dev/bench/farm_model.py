"""The farm model of docs/distributed.md: predicted bake seconds on W
one-thread Dask workers from the terms fitted on one run (dask_bench.fit_of)."""
from __future__ import annotations

import math


def model(fit: dict, workers: int, bandwidth: float) -> float:
    """Predicted bake seconds on ``workers`` one-thread workers (module docstring)."""
    rounds = math.ceil(math.log(workers, 3) - 1e-9) if workers > 1 else 0
    link = ((fit["scene_bytes"] + fit["sent_bytes"]) * (1 + 2 * rounds) + fit["result_bytes"]) / bandwidth
    tasks = max(fit["tasks"], dask_units_per_thread() * workers * fit["passes"])
    return fit["start"] + fit["client"] + fit["bvh"] + fit["work"] / workers + tasks * fit["tau"] / workers + link


def dask_units_per_thread() -> int:
    from ...core.bake.executors.dask_cluster import UNITS_PER_THREAD
    return UNITS_PER_THREAD
