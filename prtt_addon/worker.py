"""The bake worker: ``python -m prtt_addon.worker JOB.npz OUTDIR``.

Runs in its own process so Blender's UI never freezes and a crash in native code
cannot take Blender down. Protocol (docs/worker-protocol.md): one JSON object
per line on stdout, flushed:

  {"type": "start", "pid": ..., "sets": [...], "settings": {...}}
  {"type": "progress", "stage": "bvh|analytic-test|gbuffer|trace|vertex|bounce",
   "fraction": 0..1, "set": ..., "rays_per_s": ...}
  {"type": "warning", "message": ...}
  {"type": "error", "message": ..., "error": "SceneError|BakeError|..."}
  {"type": "cancelled"}
  {"type": "done", "manifest": path, "skipped": bool, "seconds": ...}

Exit status: 0 done (or skipped: up to date), 1 bad input or failure,
2 usage, 3 cancelled by SIGINT/SIGTERM (previous outputs intact).
"""
import os

# One BLAS thread per worker thread: the bake already runs a thread per core,
# and nested BLAS threads would oversubscribe. Must precede the numpy import.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import json  # noqa: E402
import signal  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_CANCELLED = 0, 1, 2, 3


class JsonLines:
    """Writes events as JSON lines; progress is throttled to ~10 per second.

    If the reader goes away (broken pipe: Blender quit or killed), the bake is
    cancelled through ``cancel`` rather than running on unobserved.
    """

    def __init__(self, stream=None, min_interval=0.1, cancel: threading.Event | None = None):
        self.stream = stream or sys.stdout
        self.min_interval = min_interval
        self.cancel = cancel
        self.broken = False
        self._last = 0.0
        self._lock = threading.Lock()

    def __call__(self, event: dict) -> None:
        now = time.monotonic()
        if (event.get("type") == "progress" and 0.0 < event.get("fraction", 0.0) < 1.0
                and now - self._last < self.min_interval):
            return
        self._last = now
        line = json.dumps(event, default=_jsonable)
        with self._lock:
            if self.broken:
                return
            try:
                self.stream.write(line + "\n")
                self.stream.flush()
            except (BrokenPipeError, OSError):
                self.broken = True
                if self.cancel is not None:
                    self.cancel.set()
                # Keep interpreter shutdown from failing on the dead pipe too.
                try:
                    sys.stdout = open(os.devnull, "w")
                except OSError:
                    pass


def _jsonable(o):
    import numpy as np
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def job_light(extra: dict, override=None):
    """The (K, 3) light of a job: ``override`` if given, else extra["light"]["coeffs"]."""
    import numpy as np
    if override is not None:
        return override
    spec = extra.get("light")
    if not spec:
        return None
    coeffs = np.asarray(spec.get("coeffs"), dtype=np.float64)
    if coeffs.ndim != 2 or coeffs.shape[1] != 3:
        raise ValueError(f"job light: coeffs must be (K, 3) RGB SH, got shape {coeffs.shape}")
    return coeffs


def run_job(job_path: str, out_dir: str, emit, cancel: threading.Event, *,
            overrides: dict | None = None, resolution=None, force: bool = False,
            light_override=None) -> int:
    """Load a job and bake it, reporting through ``emit``. Returns an exit status."""
    from .core.bake import BakeError, BakeSettings, bake_scene
    from .core.memory import MemoryLimitError
    from .core.scene import SceneError, load_scene
    from .core.transfer import Cancelled
    from .core.unwrap import UnwrapError

    try:
        sc, extra = load_scene(job_path)
        settings = dict(extra.get("settings", {}))
        settings.update(overrides or {})
        st = BakeSettings.from_dict(settings).validate()
        if resolution is not None:
            sc.set_resolution[:] = resolution
            from .core.scene import validate
            validate(sc)
        light = job_light(extra, light_override)
        emit({"type": "start", "pid": os.getpid(), "sets": sc.set_names,
              "triangles": sc.n_triangles, "settings": st.as_dict(),
              "light": None if light is None else extra.get("light", {}).get("description", "given")})
        bake_scene(sc, out_dir, st, light=light, progress=emit, cancel=cancel, skip_if_unchanged=not force)
    except Cancelled:
        emit({"type": "cancelled"})
        return EXIT_CANCELLED
    except (SceneError, BakeError, MemoryLimitError, UnwrapError, ValueError, OSError) as exc:
        emit({"type": "error", "error": type(exc).__name__, "message": str(exc)})
        return EXIT_FAILED
    except Exception as exc:  # report, never die silently
        emit({"type": "error", "error": type(exc).__name__, "message": str(exc),
              "traceback": traceback.format_exc()})
        return EXIT_FAILED
    return EXIT_OK


def install_cancel_handlers(cancel: threading.Event) -> None:
    def handler(signum, frame):
        cancel.set()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handler)


def main(argv=None) -> int:
    import argparse
    p = argparse.ArgumentParser(prog="python -m prtt_addon.worker",
                                description="Bake a PRTT job, reporting JSON lines on stdout.")
    p.add_argument("job", help="job file (.npz, see docs/format.md)")
    p.add_argument("out_dir", help="folder for the textures and manifest.json")
    p.add_argument("--force", action="store_true", help="bake even if the outputs are up to date")
    try:
        args = p.parse_args(argv)
    except SystemExit as exc:
        return EXIT_USAGE if exc.code else EXIT_OK
    cancel = threading.Event()
    install_cancel_handlers(cancel)
    return run_job(args.job, args.out_dir, JsonLines(cancel=cancel), cancel, force=args.force)


if __name__ == "__main__":
    sys.exit(main())
