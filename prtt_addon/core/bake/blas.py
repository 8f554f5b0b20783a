"""Keeping BLAS single-threaded while the bake's own threads run.

The bake runs one thread per core, each calling small matrix products. An
OpenBLAS that also starts its own threads per product oversubscribes the cores,
and its workers busy-wait: measured on the room scene, tracing ran at 0.65 of
raw Embree throughput with numpy's default OpenBLAS threads and 0.80 with one.
Environment variables only act before numpy loads, which a library cannot
rely on (Blender loaded numpy long ago), so this module calls OpenBLAS's own
``openblas_set_num_threads`` on the library numpy loaded, found in the process
memory map. Where that is not possible (no OpenBLAS, not Linux), it does
nothing; results are the same, only slower.
"""
from __future__ import annotations

import contextlib
import ctypes
import re
import sys

_SUFFIXES = ("", "64_")


def _openblas_libs():
    if not sys.platform.startswith("linux"):
        return []
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as f:
            paths = set(re.findall(r"(/\S*openblas\S*\.so[\w.]*)", f.read()))
    except OSError:
        return []
    libs = []
    for p in sorted(paths):
        try:
            h = ctypes.CDLL(p)
        except OSError:
            continue
        for suf in _SUFFIXES:
            get = getattr(h, f"openblas_get_num_threads{suf}", None)
            put = getattr(h, f"openblas_set_num_threads{suf}", None)
            if get is not None and put is not None:
                get.restype = ctypes.c_int
                put.argtypes = [ctypes.c_int]
                libs.append((get, put))
                break
    return libs


@contextlib.contextmanager
def single_threaded_blas():
    """Within the block, OpenBLAS products run on the calling thread only."""
    libs = _openblas_libs()
    saved = []
    for get, put in libs:
        saved.append((put, get()))
        put(1)
    try:
        yield
    finally:
        for put, n in saved:
            put(n)
