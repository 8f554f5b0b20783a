"""numba, the optional compiler of PRTT's few per-element loops.

Two loops gain from it: the bounce's per-hit shading (bake/estimators/hit_jit.py) and
the UV island labels (texels/islands_jit.py). Each keeps a numpy path, used
when numba is not installed (the extension zip does not bundle it: two
~45 MB wheels per Python and platform, and a numpy range of its own), when
it fails to import (a numpy it does not support), or with PRTT_NO_NUMBA=1 in
the environment; the numpy paths run the bakes' earlier arithmetic exactly.

Modules that need numba are imported through :func:`load`, never at the top
of a module Blender's UI imports: numba's import costs ~0.3 s.
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
import os
import threading

_lock = threading.Lock()
#: module name -> why it could not be loaded (numba installed but failing).
failures: dict[str, str] = {}


def available() -> bool:
    """numba is installed and not switched off (PRTT_NO_NUMBA=1); checked
    without importing it."""
    if os.environ.get("PRTT_NO_NUMBA", "") not in ("", "0"):
        return False
    return importlib.util.find_spec("numba") is not None


@functools.lru_cache(maxsize=None)
def _import(name: str):
    try:
        return importlib.import_module(name)
    except Exception as e:      # numba refusing this numpy, a broken install: the caller's numpy path
        failures[name] = f"{type(e).__name__}: {e}"
        return None


def load(name: str):
    """The numba-compiled module ``name`` (absolute), or None when numba is
    off, missing, fails to import, or failed to compile a function of the
    module (:func:`broken`). Thread-safe: the bake's threads ask at once."""
    if not available() or name in failures:
        return None
    with _lock:
        return _import(name)


def broken(name: str, exc: BaseException) -> None:
    """Record that module ``name`` imported but a function of it failed to
    compile or run (a numba or llvmlite the code was not written for): from
    now on :func:`load` returns None for it and callers take their numpy path."""
    failures[name] = f"{type(exc).__name__}: {exc}"


def version(name: str) -> str | None:
    """numba's version when the compiled module ``name`` loads (the Dask code
    identity: numba's sums round differently from numpy's), else None."""
    if load(name) is None:
        return None
    import importlib.metadata
    try:
        return importlib.metadata.version("numba")
    except importlib.metadata.PackageNotFoundError:       # a vendored numba without metadata
        import numba
        return str(numba.__version__)
