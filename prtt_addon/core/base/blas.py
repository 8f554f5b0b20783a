"""Keeping BLAS single-threaded while the bake's own threads run.

The bake runs one thread per core, each calling small matrix products. A BLAS
that also starts its own threads per product oversubscribes the cores, and its
workers busy-wait: measured on the room scene, tracing ran at 0.65 of raw
Embree throughput with numpy's default OpenBLAS threads and 0.80 with one; the
bounce stage spent 30 % of its samples in ``sched_yield`` before this limit.
Environment variables only act before numpy loads, which a library cannot rely
on (Blender loaded numpy long ago), so the limit is set at run time on the BLAS
numpy loaded, through threadpoolctl (OpenBLAS, MKL, BLIS on every platform).
Without a BLAS it knows, nothing changes: results are the same, only slower.
"""
from __future__ import annotations

import contextlib

from threadpoolctl import threadpool_limits


@contextlib.contextmanager
def single_threaded_blas():
    """Within the block, BLAS products run on the calling thread only (the
    previous limits are restored on exit)."""
    with threadpool_limits(limits=1, user_api="blas"):
        yield
