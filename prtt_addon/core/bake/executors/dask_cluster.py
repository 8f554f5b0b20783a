"""Running a bake's ray chunks on a Dask cluster (``--dask``; docs/distributed.md).

The bake is already a deterministic plan of independent chunks: a chunk's
result depends only on the chunk (its points, pattern, seed), never on the
thread or machine that traces it. So a cluster can run the very chunks the
local thread pool runs, and the outputs are the same bits. What goes where:

* The *client* (the process that runs bake_scene) does everything but the
  ray work: planning, G-buffers, exit radiance, planes, dilation, EXR writes,
  the manifest. It plans the chunks exactly as a local bake does.
* The *workers* trace chunks: transfer and vertex passes
  (transfer.ChunkKernel.run) and bounce levels (bounce.trace_chunk plus the
  level's projection, bounce.BakedProjection / relight.RelightProjection).
* **Work units.** Consecutive chunks (biggest first, the local order) are
  grouped into one task of up to :data:`UNIT_RAYS` rays, but each pass is cut
  into at least :data:`UNITS_PER_THREAD` tasks per worker thread so the last
  ones finish together. A task costs the scheduler ~1 ms; a unit is
  ~0.3-1 s of a core (bench bake --dask prints the measured overhead).
* **Shipped once.** What every task of a pass reads is scattered to every
  worker once (``broadcast``), not sent with each task: the scene (once per
  bake), a set's points (once per pass), a level's exit radiance (once per
  level). Each worker builds the Embree BVH once per scene and keeps it
  (:class:`WorkerState`, keyed by the scene's hashes), so a second bake of
  the same scene on the same cluster reuses it.
* **Streaming.** Results (the rows of a unit's texels) are written into the
  client's arrays as units finish, and their futures released at once: the
  client never holds more than the finished units' rows in flight.
* **Faults.** A worker that dies takes only its running units with it: Dask
  runs them again elsewhere (up to its ``allowed-failures``), and since a
  chunk's result is a function of the chunk, the outputs are still the same
  bits. A scheduler whose connection breaks ends the bake at once (within
  :data:`PEER_CONNECT_TIMEOUT`, or ``$PRTT_DASK_PEER_TIMEOUT`` for a
  scheduler address, when a fetch was opening a connection to it),
  with a BakeError, as does a client Dask keeps disconnected for
  :data:`SCHEDULER_LOST_AFTER` seconds. A scheduler that hangs with its
  connection open is not detected (Dask's own timeouts apply). Nothing is written (the bake's staging keeps the
  previous outputs). Cancellation (SIGTERM, Esc in Blender) cancels the
  cluster's pending tasks and closes a local cluster.
* **Same code.** Every task first checks that the worker runs the client's
  PRTT core, numpy and embreex (:func:`code_identity`); a worker that does not
  fails the bake with a clear error instead of different bits.

Bit-identity also needs the same CPU kernels on every machine (OpenBLAS picks
its kernels by CPU; set ``OPENBLAS_CORETYPE`` alike on a mixed farm).

dask and distributed are optional: without ``--dask`` nothing imports them.
"""
from __future__ import annotations

import copy
import dataclasses
import logging
import time
import uuid
import weakref

import numpy as np

from ...base.errors import BakeError, Cancelled
from ...base.memory import (
    MemoryLimitError,
    release_free_memory,
)
from .dask_spec import DaskSpec
from .dask_worker import (
    FORGET_TIMEOUT,
    UnitResult,
    WorkerMismatch,
    WorkerNeed,
    check_worker_memory,
    code_identity,
    forget_bake,
    level_task,
    quiet_loggers,
    quiet_shutdown,
    transfer_task,
    worker_memory,
)

#: Rays of one task (a unit of chunks): ~0.3-1 s of one core at 10-30 Mrays/s.
UNIT_RAYS = 1 << 23
#: Tasks per worker thread a pass is cut into at least (the tail's balance: at
#: 4, a bounce pass of 9 tasks on 2 threads left one idle for 11 % of the pass;
#: a task costs ~4 ms of a worker's time).
UNITS_PER_THREAD = 8
#: Seconds a client that is not connected (and has not been told why) waits for
#: its scheduler before the bake fails. A connection Dask sees break ends the
#: bake at once: Dask cancels every future then.
SCHEDULER_LOST_AFTER = 10.0
#: Times a pass sends its inputs again after Dask lost their only copy.
RESHIP_TRIES = 3
#: Seconds to reach a scheduler, and to wait for its first worker.
CONNECT_TIMEOUT = 20.0
WORKERS_TIMEOUT = 60.0




def units_of(chunks: list, rays_per_point: int, threads: int, unit_rays: int = UNIT_RAYS) -> list[list]:
    """Consecutive ``chunks`` grouped into tasks of up to ``unit_rays`` rays,
    at least UNITS_PER_THREAD tasks per worker thread (where there are chunks enough)."""
    if not chunks:
        return []
    total = sum(c.idx.size for c in chunks) * rays_per_point
    cap = max(1, min(unit_rays, total // max(1, UNITS_PER_THREAD * threads)))
    units, cur, cur_rays = [], [], 0
    for c in chunks:
        r = c.idx.size * rays_per_point
        if cur and cur_rays + r > cap:
            units.append(cur)
            cur, cur_rays = [], 0
        cur.append(c)
        cur_rays += r
    units.append(cur)
    return units


#: Finished units' results a worker holds at once (the one it builds, one the client has not fetched yet).
HELD_RESULTS = 2


def held_results(units: list, bytes_per_point: int) -> int:
    """What a worker holds of its units' results: HELD_RESULTS of the largest unit's."""
    return HELD_RESULTS * bytes_per_point * max((sum(c.idx.size for c in u) for u in units), default=0)


def result_channels(project) -> int:
    """float32 values a bounce projection returns per texel (BakedProjection: 3 K;
    relight.RelightProjection: 3 K and, with glossy rows, C (Kg - 1) Kg)."""
    n = 3 * project.K
    if getattr(project, "glossy_out", False):
        n += (1 if project.shared_colour else 3) * (project.kg - 1) * project.kg
    return n


def payload_bytes(obj, _depth: int = 0) -> int:
    """Bytes of the numpy arrays in ``obj`` (dataclasses, objects, dicts, lists,
    tuples; what pickling it ships, to within its small fields)."""
    if isinstance(obj, np.ndarray):
        return int(obj.nbytes)
    if _depth > 6 or obj is None or isinstance(obj, (str, bytes, int, float, bool)):
        return 0
    if isinstance(obj, dict):
        return sum(payload_bytes(v, _depth + 1) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(payload_bytes(v, _depth + 1) for v in obj)
    fields = getattr(obj, "__dict__", None)
    if fields is None and hasattr(obj, "__slots__"):
        fields = {k: getattr(obj, k, None) for k in obj.__slots__}
    return payload_bytes(fields, _depth + 1) if fields else 0


@dataclasses.dataclass
class PassStats:
    """One pass on the cluster (DaskBake.passes): tasks, summed task seconds,
    wall seconds, the worker threads it had, the rays it traced, the bytes
    scattered to each worker for it and the bytes of results sent back."""

    what: str
    tasks: int
    task_seconds: float
    wall_seconds: float
    threads: int
    rays: int = 0
    sent_bytes: int = 0
    result_bytes: int = 0

    @property
    def overhead(self) -> float:
        """Share of the cluster's thread time not spent in tasks (scheduling,
        transfers, the client's assembly, idle threads at the tail)."""
        avail = self.wall_seconds * max(self.threads, 1)
        return max(0.0, 1.0 - self.task_seconds / avail) if avail > 0 else 0.0


class DaskBake:
    """A bake's connection to a Dask cluster (runner.bake_scene opens it after
    planning; BakeContext.close closes it). Passed as ``remote`` to
    transfer.bake_points and bounce.trace_bounce_level."""

    def __init__(self, spec: DaskSpec, *, emit=None, unit_rays: int | None = None, ray_bytes: int = 0,
                 scene_need: int = 0, kernel_code: int = 0):
        """``ray_bytes``: what a worker thread holds a ray of its chunk;
        ``scene_need``: what the scene's arrays and BVH take on a worker;
        ``kernel_code``: what loading (or compiling) the bounce's numba kernels
        takes (all three for the workers' memory checks, check_workers)."""
        self.spec = spec
        self.ray_bytes, self.scene_need, self.kernel_code = int(ray_bytes), int(scene_need), int(kernel_code)
        self.worker_estimate: dict[str, int] = {}   # address -> largest estimated peak bytes (check_workers)
        # The workers' memory for the manifest (MiB), read by close(): each worker's peak
        # (VmHWM), the largest, and the largest estimate check_workers made; None before.
        self.worker_report: dict | None = None
        self.emit = emit or (lambda **e: None)
        self.unit_rays = unit_rays or UNIT_RAYS
        self.client = self.cluster = None
        self.identity = code_identity()
        self.run_id = uuid.uuid4().hex[:12]
        self.scene_f = None
        self.scene_token = ""
        self.passes: list[PassStats] = []
        self._shader = None                  # (weakref to the level's shader, its scattered future, token)
        self._sources: dict = {}            # scattered future's key -> the object (sent again if Dask loses it)
        self._n = 0
        self._log_levels = None
        self.start_seconds = 0.0            # cluster start or connection, until the first worker
        self.scene_bytes = 0                # the scene as scattered to every worker
        self.bvh_seconds = 0.0              # the longest BVH build on a worker
        self.workers = 0
        self._sent = 0                      # bytes scattered for the current pass

    # -- connection --

    def open(self, scene, scene_token: str) -> "DaskBake":
        """Start the local cluster or connect to the scheduler, wait for a
        worker, and ship the scene. BakeError when any of it fails."""
        try:
            import dask  # optional: only a bake with --dask needs it
            import distributed  # optional, as dask
        except ImportError:
            raise BakeError("--dask needs the optional packages dask and distributed "
                            "(pip install dask distributed)") from None
        t = time.perf_counter()
        # Dask logs a lost connection or a restarted worker as tracebacks on
        # stderr; the bake reports what matters itself (warnings, BakeError).
        self._log_levels = quiet_loggers("distributed")
        try:
            if self.spec.kind == "local":
                self.emit(type="progress", stage="dask", fraction=0.0)
                # Workers without a memory limit: the bake checked its memory need
                # itself, and Dask's limit would kill a worker holding a large scene.
                # No Active Memory Manager: it would drop the broadcast copies
                # between passes (one copy left, refetched by every other worker,
                # and lost with its worker).
                with dask.config.set({"distributed.scheduler.active-memory-manager.start": False}):
                    self.cluster = distributed.LocalCluster(
                        n_workers=self.spec.workers, threads_per_worker=1, processes=True, memory_limit=0,
                        dashboard_address=None, silence_logs=logging.ERROR)
                self.client = distributed.Client(self.cluster, set_as_default=False)
            else:
                self.client = distributed.Client(self.spec.address, timeout=CONNECT_TIMEOUT, set_as_default=False)
            self.client.wait_for_workers(1, timeout=WORKERS_TIMEOUT)
            # Reached: from now on a new connection (a gather through the
            # scheduler, a fetch from a worker) that cannot open is a peer gone,
            # not one starting; Dask would retry it for CONNECT_TIMEOUT.
            self.client.rpc.timeout = self.spec.peer_timeout
            self.start_seconds = time.perf_counter() - t
            self.scene_token = scene_token
            # The scene's arrays and BVH on every worker (a MemoryLimitError passes through).
            self.check_workers("scene", self.scene_need, 0)
            self.scene_f = self._scatter(scene)
            self.scene_bytes, self._sent = self._sent, 0
            workers = self.client.scheduler_info().get("workers", {})
        except BaseException as exc:
            self.close()
            if isinstance(exc, (KeyboardInterrupt, SystemExit)):
                raise
            if isinstance(exc, (BakeError, MemoryLimitError)):
                raise
            raise BakeError(f"cannot use {self.spec.describe()}: {type(exc).__name__}: {exc}") from None
        self.workers = len(workers)
        threads = sum(int(w.get("nthreads", 1)) for w in workers.values())
        self.emit(type="info", message=f"Dask: {len(workers)} workers, {threads} threads "
                                       f"({self.spec.describe()}), ready in {time.perf_counter() - t:.1f} s")
        return self

    def check_workers(self, what: str, data: int, chunk_rays: int, code: int = 0) -> None:
        """Before a pass sends ``data`` bytes to every worker and its threads
        trace chunks of ``chunk_rays`` rays: check_worker_memory on what the
        workers report now (MemoryLimitError, before anything is sent); keeps
        each worker's estimated peak for the manifest."""
        self._connected()
        try:
            info = self.client.scheduler_info().get("workers", {})
            mem = self.client.run(worker_memory)
        except Exception as exc:
            self.emit(type="warning", message=f"Dask: could not read the workers' memory before the {what} pass "
                                              f"({type(exc).__name__}: {exc}); not checked")
            return
        workers = {a: dict(mem[a], nthreads=int(w.get("nthreads", 1))) for a, w in info.items() if a in mem}
        est = check_worker_memory(what, WorkerNeed(int(data), int(chunk_rays) * self.ray_bytes, int(code)), workers)
        for a, v in est.items():
            self.worker_estimate[a] = max(self.worker_estimate.get(a, 0), v)

    def _read_worker_peaks(self) -> None:
        try:
            mem = self.client.run(worker_memory)
        except Exception:
            return
        peaks = {a: round(m["peak"] / 2 ** 20, 1) for a, m in sorted(mem.items()) if m.get("peak") is not None}
        if peaks:
            self.worker_report = {
                "peak_rss_mb": peaks, "max_peak_rss_mb": max(peaks.values()),
                "estimate_mb": round(max(self.worker_estimate.values()) / 2 ** 20, 1) if self.worker_estimate else None}

    def close(self) -> None:
        """Cancel what is still pending and disconnect (a local cluster is shut
        down). After passes, says what they cost (an "info" event with the
        numbers as ``dask``) and reads the workers' peak memory (worker_report)."""
        if self.passes and self.client is not None and self.client.status == "running":
            self._read_worker_peaks()
        if self.passes:
            sm = self.summary()
            self.emit(type="info", dask=sm,
                      message=f"Dask: {sm['tasks']} tasks, {sm['task_seconds']:.1f} s of work in "
                              f"{sm['wall_seconds']:.1f} s on {max(p.threads for p in self.passes)} threads "
                              f"(overhead {100 * sm['overhead']:.1f} %)")
            self.passes = []
        client, cluster = self.client, self.cluster
        self.client = self.cluster = None
        self.scene_f = self._shader = None
        self._sources.clear()
        if client is not None and client.status == "running":
            # A shared cluster lives on: its workers drop this bake's kernels and shaders.
            # A local one is shut down: its workers' logs go quiet first.
            try:
                if cluster is None:
                    # Waited for: Dask runs a plain function only so (wait=False is for
                    # coroutines: every worker logged "Combination not supported"); a
                    # worker that does not answer does not hold the bake's end for long.
                    client.run(forget_bake, self.run_id, self.scene_token, on_error="return",
                               callback_timeout=FORGET_TIMEOUT)
                else:
                    client.run(quiet_shutdown)
            except Exception:
                pass
        for obj in (client, cluster):
            if obj is None:
                continue
            try:
                obj.close(timeout=5)
            except Exception:
                pass
        for lg, level in (self._log_levels or {}).items():
            lg.setLevel(level)
        self._log_levels = None

    def threads(self) -> int:
        """Worker threads the scheduler knows now (at least 1)."""
        self._connected()
        try:
            workers = self.client.scheduler_info().get("workers", {})
        except Exception:
            return 1
        return max(1, sum(int(w.get("nthreads", 1)) for w in workers.values()))

    def _release(self, fut) -> None:
        self._sources.pop(fut.key, None)
        fut.release()

    def _connected(self) -> None:
        """BakeError at once when Dask already saw the connection to the
        scheduler break: a call that needs the scheduler (scatter, its worker
        list) would otherwise wait out Dask's reconnect (CONNECT_TIMEOUT)."""
        if self.client is not None and self.client.status != "running":
            raise BakeError(f"lost {self.spec.describe()} (the connection broke, Dask is {self.client.status}); "
                            f"nothing was written, the previous outputs are intact")

    def _scatter(self, obj):
        self._connected()
        self._sent += payload_bytes(obj)
        try:
            fut = self.client.scatter([obj], broadcast=True, hash=False)[0]
            self._sources[fut.key] = obj
            return fut
        except Exception as exc:
            if isinstance(exc, OSError) or self.client.status != "running":
                # The scheduler went away as the data left (Dask had not seen it yet).
                raise BakeError(f"lost {self.spec.describe()} while sending the bake's data ({type(exc).__name__}: "
                                f"{exc}); nothing was written, the previous outputs are intact") from None
            raise BakeError(f"cannot send the bake's data to {self.spec.describe()}: "
                            f"{type(exc).__name__}: {exc}") from None

    # -- passes --

    def trace_points(self, pts, st, chunks, G, sink, on_result, cancel) -> None:
        """A transfer/vertex pass (transfer.bake_points' chunks): ``sink(chunk,
        rows, counts, thread)`` per chunk, then ``on_result(points)`` per unit."""
        units = units_of(chunks, st.rays, self.threads(), self.unit_rays)
        self.check_workers("transfer", payload_bytes(pts) + held_results(units, 4 * st.bands ** 2),
                           min(st.chunk_rays, sum(c.idx.size for c in chunks) * st.rays))
        pts_f = self._scatter(pts)
        token = f"{self.run_id}-p{self._next()}"

        def handle(unit, res: UnitResult):
            n = 0
            for chunk, (rows, counts) in zip(unit, res.items):
                n += sink(chunk, rows, counts, res.worker)
            on_result(n)

        try:
            self._run("transfer", transfer_task, (self.scene_f, self.scene_token, pts_f, token, st, G), units,
                      handle, cancel, st.rays)
        finally:
            self._release(pts_f)

    def trace_level(self, lr, chunks, project, sink, on_result, cancel) -> None:
        """A bounce level of one set (bounce.trace_bounce_level):
        ``sink(texels, cols, result, hits)`` per chunk, ``on_result`` per unit."""
        units = units_of(chunks, lr.st.rays, self.threads(), self.unit_rays)
        shader_bytes = 0
        if self._shader is None or self._shader[0]() is not project.shader:
            # This level's shader is sent with this pass (without its scene).
            shader_bytes = payload_bytes({k: v for k, v in vars(project.shader).items() if k != "sc"})
        self.check_workers("bounce", payload_bytes(lr) + shader_bytes + held_results(units, 4 * result_channels(project)),
                           min(lr.st.chunk_rays, sum(c.idx.size for c in chunks) * lr.st.rays), self.kernel_code)
        shader_f, shader_token = self._level_shader(project.shader)
        lr_f = self._scatter(lr)
        tpl = copy.copy(project)
        tpl.shader = None

        def handle(unit, res: UnitResult):
            for n, cols, result, hits in res.items:
                sink(n, cols, result, hits)
            on_result(None)

        try:
            self._run("bounce", level_task, (self.scene_f, self.scene_token, shader_f, shader_token, lr_f,
                                             f"{self.run_id}-t{self._next()}", tpl), units, handle, cancel,
                      lr.st.rays)
        finally:
            self._release(lr_f)

    def _next(self) -> int:
        self._n += 1
        return self._n

    def _level_shader(self, shader):
        """The level's shader scattered once (without the scene, which the
        workers have): every set of a level shares it."""
        if self._shader is not None and self._shader[0]() is shader:
            return self._shader[1], self._shader[2]
        if self._shader is not None:
            self._release(self._shader[1])
        shipped = copy.copy(shader)
        shipped.sc = None
        fut = self._scatter(shipped)
        # A weak reference: the bake drops a level's shader before the next
        # level's exit radiance is made (memory.check counts one at a time),
        # and its scattered copy (which shares its exit tables) goes with it.
        self._shader = (weakref.ref(shader, self._shader_gone), fut, f"{self.run_id}-s{self._next()}")
        return fut, self._shader[2]

    def forget_shader(self) -> None:
        """The bake is done with the current level's shader: release its
        scattered copy now (the weak reference's callback would wait for
        Python's cycle collector when the shader sits in a reference cycle)."""
        if self._shader is not None:
            self._shader_gone(self._shader[0])

    def _shader_gone(self, ref) -> None:
        """The level's shader was dropped by the bake: release its scattered
        copy, whose exit tables ``_sources`` kept alive (through the texture
        writes: 350 MiB of the client's 794 at 1024², #35)."""
        cur = self._shader
        if cur is None or cur[0] is not ref:
            return
        self._shader = None
        try:
            self._release(cur[1])
        except Exception:
            self._sources.pop(getattr(cur[1], "key", None), None)

    def _run(self, what: str, fn, args: tuple, units: list, handle, cancel, rays_per_point: int) -> None:
        """Submit one task per unit, hand results to ``handle(unit, result)`` in
        the calling thread as they finish; Cancelled / BakeError as promised.

        When Dask cancels the tasks because data they read is gone (the worker
        holding the only copy of a scattered object died), the objects are
        scattered again and the units not yet handled resubmitted, up to
        :data:`RESHIP_TRIES` times (a warning says so)."""
        import distributed  # optional (open() checked that it is there)

        client = self.client
        t0 = time.perf_counter()
        threads = self.threads()
        args = list(args)
        reshipped: list = []                  # futures this pass scattered again (released at its end)

        def submit(todo):
            return {client.submit(fn, self.identity, *args, unit, pure=False,
                                  key=f"prtt-{what}-{self.run_id}-{self._next()}"): unit for unit in todo}

        futures = submit(units)
        pending = set(futures)
        task_s, result_bytes, tries = 0.0, 0, 0
        lost_since = None
        try:
            while pending:
                if cancel is not None and cancel.is_set():
                    raise Cancelled()
                try:
                    try:
                        with client.as_current():
                            done, pending = distributed.wait(pending, timeout=0.25, return_when="FIRST_COMPLETED")
                    except TimeoutError:
                        lost_since = self._check_scheduler(lost_since)
                        continue
                    lost_since = None
                    for f in done:
                        res = f.result()
                        task_s += res.seconds
                        self.bvh_seconds = max(self.bvh_seconds, res.bvh_seconds)
                        result_bytes += payload_bytes(res.items)
                        handle(futures.pop(f), res)
                        f.release()
                except Exception as exc:
                    if not self._data_lost(exc, cancel) or tries >= RESHIP_TRIES:
                        raise self._failure(what, exc, cancel) from None
                    tries += 1
                    self.emit(type="warning", message=f"Dask lost data the {what} tasks read (a worker holding its "
                                                      f"only copy died); sending it again (try {tries})")
                    client.cancel(list(futures), force=True)
                    args = [self._rescatter(a, reshipped) for a in args]
                    futures = submit(list(futures.values()))
                    pending = set(futures)
        except BaseException:
            if client.status == "running":       # else Dask cancelled them, and a call would wait to reconnect
                try:
                    client.cancel(list(pending), force=True)
                except Exception:
                    pass
            raise
        finally:
            for f in reshipped:
                self._release(f)
        # The results were unpickled on Dask's I/O thread: glibc keeps what they
        # freed in that thread's arena unless it is trimmed.
        release_free_memory()
        rays = sum(c.idx.size for u in units for c in u) * rays_per_point
        self.passes.append(PassStats(what, len(units), task_s, time.perf_counter() - t0, threads, rays,
                                     self._sent, result_bytes))
        self._sent = 0

    def _data_lost(self, exc: Exception, cancel) -> bool:
        """Whether ``exc`` is Dask cancelling tasks (not the bake, not a lost
        scheduler): what losing the only copy of their input looks like."""
        import distributed  # optional (open() checked that it is there)
        from distributed.client import FuturesCancelledError  # optional, as distributed
        return (isinstance(exc, (FuturesCancelledError, distributed.CancelledError))
                and "connection" not in str(exc)          # "scheduler-connection-lost": not data
                and not (cancel is not None and cancel.is_set())
                and self.client is not None and self.client.status == "running")

    def _rescatter(self, arg, reshipped: list):
        """``arg`` scattered again when it is one of this bake's scattered
        futures (the scene and the level's shader keep the new one)."""
        obj = self._sources.get(getattr(arg, "key", None))
        if obj is None:
            return arg
        new = self._scatter(obj)
        self._release(arg)
        if arg is self.scene_f:
            self.scene_f = new
        elif self._shader is not None and arg is self._shader[1]:
            self._shader = (self._shader[0], new, self._shader[2])
        else:
            reshipped.append(new)
        return new

    def _failure(self, what: str, exc: Exception, cancel) -> Exception:
        """What a failed wait or task means for the bake: Cancelled when the bake
        was cancelled meanwhile, else a BakeError saying what went wrong."""
        import distributed  # optional (open() checked that it is there)
        if cancel is not None and cancel.is_set():
            return Cancelled()
        if isinstance(exc, WorkerMismatch):
            return BakeError(str(exc))
        if isinstance(exc, distributed.KilledWorker):
            return BakeError(f"a {what} task was on workers that died, too often (Dask's allowed-failures); the "
                             f"cluster's workers keep dying (memory? a crash in native code?); nothing was "
                             f"written, the previous outputs are intact")
        text = str(exc).strip()
        why = text.splitlines()[0][:200] if text else ""
        if isinstance(exc, OSError) or self.client is None or self.client.status != "running":
            return BakeError(f"lost {self.spec.describe()} during the {what} pass ({type(exc).__name__}: {why}); "
                             f"nothing was written, the previous outputs are intact")
        return BakeError(f"a {what} task failed on the Dask cluster ({type(exc).__name__}: {why}); nothing was "
                         f"written, the previous outputs are intact")

    def _check_scheduler(self, lost_since):
        """None while connected; else since when not; BakeError once that is
        longer than SCHEDULER_LOST_AFTER."""
        if self.client.status == "running":
            return None
        now = time.perf_counter()
        if lost_since is None:
            self.emit(type="warning", message=f"lost the connection to {self.spec.describe()}; waiting "
                                              f"{SCHEDULER_LOST_AFTER:.0f} s for it")
            return now
        if now - lost_since > SCHEDULER_LOST_AFTER:
            raise BakeError(f"lost {self.spec.describe()} (no connection for {SCHEDULER_LOST_AFTER:.0f} s); "
                            f"nothing was written, the previous outputs are intact")
        return lost_since

    def summary(self) -> dict:
        """The passes as numbers (the bench prints them)."""
        tasks = sum(p.tasks for p in self.passes)
        task_s = sum(p.task_seconds for p in self.passes)
        wall = sum(p.wall_seconds for p in self.passes)
        avail = sum(p.wall_seconds * p.threads for p in self.passes)
        return {"workers": self.workers, "start_seconds": self.start_seconds, "scene_bytes": self.scene_bytes,
                "bvh_seconds": self.bvh_seconds,
                "tasks": tasks, "task_seconds": task_s, "wall_seconds": wall,
                "rays": sum(p.rays for p in self.passes),
                "sent_bytes": sum(p.sent_bytes for p in self.passes),
                "result_bytes": sum(p.result_bytes for p in self.passes),
                "overhead": max(0.0, 1.0 - task_s / avail) if avail > 0 else 0.0,
                "worker_memory": self.worker_report,
                "passes": [dataclasses.asdict(p) | {"overhead": p.overhead} for p in self.passes]}
