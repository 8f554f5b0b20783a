"""The bake worker: ``python -m prtt_addon.worker JOB.npz OUTDIR``.

Runs in its own process so Blender's UI never freezes and a crash in native code
cannot take Blender down. Protocol (docs/worker-protocol.md): one JSON object
per line on stdout, flushed:

  {"type": "progress", "stage": "load", "fraction": 0.0}
  {"type": "start", "pid": ..., "sets": [...], "settings": {...}}
  {"type": "progress", "stage": "bvh|analytic-test|gbuffer|tables|trace|vertex|bounce|write",
   "fraction": 0..1, "set": ..., "rays_per_s": ...}
  {"type": "warning", "message": ...}
  {"type": "info", "message": ...}      (work skipped on purpose, e.g. bounce levels stopped early)
  {"type": "error", "message": ..., "error": "SceneError|BakeError|..."}
  {"type": "cancelled"}
  {"type": "done", "manifest": path, "skipped": bool, "seconds": ...}

Exit status: 0 done (or skipped: up to date), 1 bad input or failure,
2 usage, 3 cancelled by SIGINT/SIGTERM (previous outputs intact), within 2 s
of the signal at any stage (:class:`Watchdog`).
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

from .core.base import atomic  # noqa: E402  (no numpy: the environment above still applies)

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
    if not isinstance(spec, dict):
        raise ValueError(f"job light: expected a JSON object with coeffs, got {type(spec).__name__}")
    try:
        coeffs = np.asarray(spec.get("coeffs"), dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"job light: coeffs must be (K, 3) RGB SH numbers ({exc})") from None
    if coeffs.ndim != 2 or coeffs.shape[1] != 3:
        raise ValueError(f"job light: coeffs must be (K, 3) RGB SH, got shape {coeffs.shape}")
    if not np.isfinite(coeffs).all():
        raise ValueError("job light: coeffs has NaN/Inf values")
    return coeffs


def job_sun(extra: dict):
    """The job's sun (core.light.sun.Sun) from extra["sun"], or None; ValueError
    (SunError) naming what is wrong with it (a job file is untrusted input)."""
    from .core.light.sun import Sun  # deferred (start-up)
    spec = extra.get("sun")
    return None if spec is None else Sun.from_dict(spec)


def job_lamps(extra: dict) -> tuple:
    """The job's point and spot lamps (core.light.lamp.Lamp) from extra["lamps"],
    or (); ValueError (LampError) naming what is wrong (untrusted input)."""
    from .core.light.lamp import lamps_from_list  # deferred (start-up)
    spec = extra.get("lamps")
    return () if spec is None else lamps_from_list(spec)


def check_job_memory(job, st, *, resolution=None, bouncing: bool) -> None:
    """Refuse (MemoryLimitError) a job whose arrays plus the least any bake of
    it holds (memory_plan.floor_bytes: its largest set's float32 planes) do
    not fit in the available memory, from its headers alone (before loading):
    a refusal here would truly not have fit. The bake's full estimate, which
    needs the loaded UV layout, is checked once the job is loaded
    (core/bake/pipeline/memory_check.check_memory). ``bouncing`` is kept for callers."""
    import numpy as np

    # Deferred imports (start-up): the worker installs its signal handlers
    # before numpy, Embree and the bake load, so a SIGTERM during start-up is a
    # clean cancel (exit 3), not a kill.
    from .core.bake.pipeline.memory_plan import floor_bytes  # deferred (start-up)
    from .core.base.memory import GiB, check_fits  # deferred (start-up)
    from .core.model.scene import MAX_RESOLUTION  # deferred (start-up)
    res = job.set_resolution() if resolution is None else np.full((len(job.set_resolution()), 2), resolution)
    # An out-of-range resolution fails validation with its own message; here it
    # must not fail first as an absurd memory need: such sets count as 1 texel.
    res = np.asarray(res).reshape(-1, 2)
    res = np.where((res >= 1) & (res <= MAX_RESOLUTION), res, 1).astype(np.int64)
    arrays = job.peak_bytes()
    bake = floor_bytes(res, bands=st.bands, n_triangles=job.members["positions"].shape[0])
    check_fits(arrays + bake, f"job {job.path} (its arrays {arrays / GiB:.2f} GiB, the bake "
                              f"{bake / GiB:.2f} GiB)")


def run_job(job_path: str, out_dir: str, emit, cancel: threading.Event, *,
            overrides: dict | None = None, resolution=None, force: bool = False,
            light_override=None, dask: str | None = None) -> int:
    """Load a job and bake it, reporting through ``emit``. Returns an exit status.

    The job's headers, settings and memory need are checked before any array
    is read (core.io.jobfile.JobFile); ``cancel`` is honoured while loading too.
    ``dask``: bake_scene's (trace on a Dask cluster).
    """
    # Deferred imports (start-up): the worker installs its signal handlers
    # before numpy, Embree and the bake load, so a SIGTERM during start-up is a
    # clean cancel (exit 3), not a kill.
    from .core.bake.pipeline.context import BakeSettings  # deferred (start-up)
    from .core.bake.pipeline.runner import bake_scene  # deferred (start-up)
    from .core.base.errors import BakeError, Cancelled  # deferred (start-up)
    from .core.base.memory import MemoryLimitError, large_frees_to_os  # deferred (start-up)
    from .core.io.jobfile import JobFile  # deferred (start-up)
    from .core.model.scene import SceneError, validate  # deferred (start-up)
    from .core.texels.unwrap import UnwrapError  # deferred (start-up)

    large_frees_to_os()      # this process bakes and exits: freed arrays go back to the OS at once
    try:
        with JobFile(job_path) as job:
            settings = dict(job.settings())
            settings.update(overrides or {})
            st = BakeSettings.from_dict(settings).validate()
            light = job_light(job.extra, light_override)
            sun = job_sun(job.extra)
            lamps = job_lamps(job.extra)
            check_job_memory(job, st, resolution=resolution,
                             bouncing=light is not None and st.bounces > 0 and st.textures)
            emit({"type": "progress", "stage": "load", "fraction": 0.0})
            sc = job.load(cancel)
            extra = job.extra
        if resolution is not None:
            sc.set_resolution[:] = resolution
            validate(sc)
        if cancel.is_set():
            raise Cancelled()
        emit({"type": "start", "pid": os.getpid(), "sets": sc.set_names,
              "resolutions": [[int(w), int(h)] for w, h in sc.set_resolution],
              "triangles": sc.n_triangles, "settings": st.as_dict(),
              "light": None if light is None else (extra.get("light") or {}).get("description", "given")})
        source = extra.get("blend") if isinstance(extra.get("blend"), str) and extra.get("blend") else None
        bake_scene(sc, out_dir, st, light=light, progress=emit, cancel=cancel, skip_if_unchanged=not force,
                   job=os.path.abspath(job_path), source=source, dask=dask, sun=sun, lamps=lamps)
    except Cancelled:
        emit({"type": "cancelled"})
        return EXIT_CANCELLED
    except (SceneError, BakeError, MemoryLimitError, UnwrapError, ValueError, OSError) as exc:
        emit({"type": "error", "error": type(exc).__name__, "message": str(exc)})
        return EXIT_FAILED
    except MemoryError as exc:
        # The estimate passed but the memory ran out (another process took it, or a
        # limit the estimate could not see): the staged files are already removed.
        emit({"type": "error", "error": "MemoryError",
              "message": f"out of memory during the bake ({exc or 'allocation failed'}); the previous outputs in "
                         f"{out_dir} are unchanged. Free memory, or lower --resolution, --bands or the bounces"})
        return EXIT_FAILED
    except Exception as exc:  # report, never die silently
        emit({"type": "error", "error": type(exc).__name__, "message": str(exc),
              "traceback": traceback.format_exc()})
        return EXIT_FAILED
    return EXIT_OK


class Watchdog:
    """SIGINT/SIGTERM stop the process within ~1.2 s, whatever it is doing.

    The signal sets ``cancel``; the bake stops at its next check (between
    chunks, patterns, rasteriser chunks, files) and exits 3 the normal way.
    If it has not finished within :attr:`grace` seconds (a long native call:
    a BVH build, an EXR being compressed), this watchdog deletes the
    process's staged temporaries and exits 3 itself (os._exit), except while
    a bake commits its outputs (atomic.COMMIT_LOCK, renames and manifest:
    fast), which it waits for; a bake that did commit exits 0.

    Python runs signal handlers only in the main thread, between bytecodes,
    so a handler alone could wait for a native call to return. The watchdog
    thread therefore waits on the signal wakeup fd (written by the C-level
    handler at once) and needs only the GIL, which embreex, numpy, OpenEXR
    and file I/O release (and which raytrace.py builds in short pieces).
    """

    grace = 1.2

    def __init__(self, cancel: threading.Event, announce=None):
        self.cancel = cancel
        self.announce = announce          # announce(event) for the final "cancelled" line
        self.finished = threading.Event()  # the normal path returned
        self._rfd = None

    def install(self) -> "Watchdog":
        """Install the handlers and start the thread (call from the main thread)."""
        import socket

        def handler(signum, frame):
            self.cancel.set()

        try:
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, handler)
        except ValueError:                # not the main thread: the caller cancels
            return self
        try:
            r, w = socket.socketpair()
            w.setblocking(False)
            signal.set_wakeup_fd(w.fileno(), warn_on_full_buffer=False)
        except (OSError, ValueError, AttributeError):
            return self                   # no wakeup fd (not the main thread): handlers only
        self._rfd, self._wfd = r, w       # keep both ends alive
        threading.Thread(target=self._watch, name="prtt-watchdog", daemon=True).start()
        return self

    def _watch(self) -> None:
        wanted = {int(signal.SIGINT), int(signal.SIGTERM)}
        while True:
            try:
                data = self._rfd.recv(64)
            except OSError:
                return
            if not data:
                return
            if wanted & set(data):
                break
        self.cancel.set()
        if self.finished.wait(self.grace):
            return
        self.hard_exit()

    def hard_exit(self) -> None:
        # Never between a commit's renames and its manifest; the lock is held for
        # milliseconds (files were hashed and synced before it was taken).
        atomic.COMMIT_LOCK.acquire(timeout=30)
        if atomic.commits():
            # The outputs are the new ones: the normal path only has to report
            # "done" (with the manifest's path); give it that time.
            atomic.COMMIT_LOCK.release()
            if not self.finished.wait(5.0):
                os._exit(EXIT_OK)
            return
        atomic.remove_own_temporaries()
        self._say({"type": "cancelled"})
        os._exit(EXIT_CANCELLED)

    def _say(self, event: dict) -> None:
        """Announce on a helper thread, waiting at most 0.3 s (stdout may be a
        full pipe, or its lock held by the main thread mid-write)."""
        if self.announce is None:
            return
        t = threading.Thread(target=self._say_now, args=(event,), daemon=True)
        t.start()
        t.join(0.3)

    def _say_now(self, event: dict) -> None:
        try:
            self.announce(event)
            sys.stdout.flush()
        except Exception:
            pass


def install_cancel_handlers(cancel: threading.Event, announce=None) -> Watchdog:
    """SIGINT/SIGTERM set ``cancel``, with a :class:`Watchdog` as the backstop."""
    return Watchdog(cancel, announce).install()


def finish(code: int, watchdog: Watchdog) -> int:
    """End of a bake command: mark it finished for the watchdog. A cancelled run
    exits at once (os._exit after flushing): helper threads still inside a native
    call must not hold the process past the promised time."""
    watchdog.finished.set()
    if code == EXIT_CANCELLED:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:
                pass
        os._exit(code)
    return code


def main(argv=None) -> int:
    import argparse
    p = argparse.ArgumentParser(prog="python -m prtt_addon.worker",
                                description="Bake a PRTT job, reporting JSON lines on stdout.")
    p.add_argument("job", help="job file (.npz, see docs/format.md)")
    p.add_argument("out_dir", help="folder for the textures and manifest.json")
    p.add_argument("--force", action="store_true", help="bake even if the outputs are up to date")
    p.add_argument("--dask", metavar="local[:N]|tcp://HOST:PORT|env",
                   help="trace on a Dask cluster (docs/distributed.md)")
    cancel = threading.Event()
    emit = JsonLines(cancel=cancel)
    watchdog = install_cancel_handlers(cancel, emit)       # first: a signal may come at once
    try:
        args = p.parse_args(argv)
    except SystemExit as exc:
        return EXIT_USAGE if exc.code else EXIT_OK
    return finish(run_job(args.job, args.out_dir, emit, cancel, force=args.force, dask=args.dask), watchdog)


if __name__ == "__main__":
    sys.exit(main())
