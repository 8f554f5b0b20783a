"""The worker side of a bake on a Dask cluster (docs/distributed.md;
executors/dask_cluster.py says how the bake is shared out): what each worker
process keeps between tasks (:class:`WorkerState`: scenes and their BVHs,
points, shaders), its memory, the tasks it runs (:func:`transfer_task`,
:func:`level_task`) and letting a finished bake go (:func:`forget_bake`).
The code identity every task checks first (:func:`code_identity`) is here too.
"""
from __future__ import annotations

import collections
import copy
import ctypes
import dataclasses
import hashlib
import importlib.metadata
import logging
import os
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from ...base.memory import (
    GiB,
    MemoryLimitError,
    available_bytes,
    peak_resident_bytes,
    release_free_memory,
    resident_bytes,
)
from ..estimators import hit_kernel
from ..estimators.bounce import trace_chunk
from ..estimators.raytrace import RayScene
from ..estimators.transfer import SWITCH_INTERVAL, ChunkKernel

_IDENTITY: str | None = None


class WorkerMismatch(RuntimeError):
    """A Dask worker runs other PRTT code (or numpy/embreex) than the client."""


def code_identity() -> str:
    """sha256 of the PRTT core's source files, numpy's and embreex's versions
    and numba's (None when off: the compiled loops' sums round differently
    from numpy's): equal on client and worker or the bits may differ."""
    global _IDENTITY
    if _IDENTITY is None:
        try:
            embree = importlib.metadata.version("embreex")
        except Exception:               # no metadata (a vendored wheel): the module's own
            embree = "?"
        h = hashlib.sha256(f"numpy {np.__version__} embreex {embree} numba {hit_kernel.numba_version()}".encode())
        core = Path(__file__).resolve().parents[2]          # prtt_addon/core
        for p in sorted(core.rglob("*.py")):
            h.update(p.relative_to(core).as_posix().encode())
            h.update(p.read_bytes())
        _IDENTITY = h.hexdigest()
    return _IDENTITY


class WorkerState:
    """What one worker process keeps between tasks, thread-safe (a worker may
    run several tasks at once, of one bake or of two):

    * scenes and their BVHs by scene token (the scene's hashes), the
      :data:`KEEP_SCENES` most recent: tasks of two bakes of one scene running
      side by side share its BVH; a bake that ends drops its scene;
    * per slot (a pass's kernel, a level's shader and tables) the
      :data:`KEEP_PER_SLOT` most recent objects by token (tokens start with
      the bake's run id: :meth:`forget` drops a finished bake's).

    Each object is built once, outside the state's lock (a BVH of a million
    triangles takes seconds; other threads look theirs up meanwhile)."""

    def __init__(self):
        self.lock = threading.Lock()
        self.scenes: collections.OrderedDict = collections.OrderedDict()    # token -> RayScene
        self.slots: dict[str, collections.OrderedDict] = {}                 # slot -> token -> object
        self.building: dict[tuple, threading.Lock] = {}
        self.ready = False

    def setup(self, identity: str) -> None:
        """Check the code and, once, set BLAS to one thread and the GIL switch
        interval the local bake traces with."""
        if identity != code_identity():
            raise WorkerMismatch(f"Dask worker {worker_name()} runs other PRTT code or numpy/embreex versions "
                                 f"than the client (identity {code_identity()[:12]} vs {identity[:12]}); "
                                 f"install the same PRTT on every worker")
        if not self.ready:
            with self.lock:
                if not self.ready:
                    # A worker process does nothing else: one BLAS thread per task
                    # thread, as the local bake's single_threaded_blas.
                    self._blas = threadpool_limits(limits=1, user_api="blas")
                    sys.setswitchinterval(SWITCH_INTERVAL)
                    heap_like_a_normal_process()
                    self.ready = True

    def _get(self, store: collections.OrderedDict, key, build, keep: int):
        """(store[key], seconds spent building it here: 0 when it was there)."""
        with self.lock:
            if key in store:
                store.move_to_end(key)
                return store[key], 0.0
            lock = self.building.setdefault((id(store), key), threading.Lock())
        with lock:
            with self.lock:
                if key in store:
                    return store[key], 0.0
            t0 = time.perf_counter()
            obj = build()
            t = time.perf_counter() - t0
            with self.lock:
                store[key] = obj
                while len(store) > keep:
                    store.popitem(last=False)
                self.building.pop((id(store), key), None)
            return obj, t

    def ray_scene(self, scene, token: str):
        """(the BVH of ``scene``, seconds this call spent building it: 0 but
        on the first task of a scene)."""
        return self._get(self.scenes, token, lambda: RayScene(scene.positions), KEEP_SCENES)

    def slot(self, name: str, token: str, build):
        """The object ``build()`` made for ``token`` in slot ``name``."""
        with self.lock:
            store = self.slots.setdefault(name, collections.OrderedDict())
        return self._get(store, token, build, KEEP_PER_SLOT)[0]

    def forget(self, prefix: str, scene_token: str = "") -> int:
        """Drop the slot objects whose token starts with ``prefix`` (a finished
        bake's run id) and the scene ``scene_token`` with its BVH; returns how
        many objects (scenes included)."""
        with self.lock:
            n = 0
            for store in self.slots.values():
                for k in [k for k in store if k.startswith(prefix)]:
                    del store[k]
                    n += 1
            if scene_token and self.scenes.pop(scene_token, None) is not None:
                n += 1
            return n


#: Scenes (with their BVH) a worker keeps, and objects per slot.
KEEP_SCENES = 2
KEEP_PER_SLOT = 2
STATE = WorkerState()

#: glibc mallopt parameters, and what a process that never set them grows to:
#: its mmap threshold follows the largest freed block up to 32 MiB (64-bit),
#: its trim threshold twice that.
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
HEAP_MMAP_THRESHOLD = 32 << 20


def heap_like_a_normal_process() -> bool:
    """Undo Dask's ``MALLOC_TRIM_THRESHOLD_`` in a worker process (glibc only).

    Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536 so they give
    memory back to the OS. Setting it also freezes glibc's mmap threshold at
    128 KiB: every temporary array above that is mapped fresh and zeroed by
    the kernel, and unmapped when freed. The bounce shading makes dozens of
    such temporaries per chunk and ran 1.6x slower per ray on a worker than
    in the local bake (bench bake --dask). Returns whether mallopt took."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None)
        ok = libc.mallopt(M_MMAP_THRESHOLD, HEAP_MMAP_THRESHOLD) == 1
        return libc.mallopt(M_TRIM_THRESHOLD, 2 * HEAP_MMAP_THRESHOLD) == 1 and ok
    except (OSError, AttributeError, TypeError):     # not glibc (musl has no mallopt)
        return False


def worker_memory(dask_worker=None) -> dict:
    """Run on every worker (DaskBake.check_workers, close): this process's
    memory in bytes: ``available`` (what it can still allocate: the least of
    core.base.memory.available_bytes, which reads the machine, its cgroup and
    ``ulimit -v``, and the Dask worker's own ``--memory-limit`` less what it
    holds; None where nothing is known), ``rss`` and ``peak`` (VmRSS, VmHWM),
    ``numba``: whether numba is imported; ``held``: the objects and scenes
    its WorkerState keeps (none between bakes). ``dask_worker``: the Worker,
    which Dask's ``Client.run`` passes to a function taking that argument."""
    rss = resident_bytes()
    avail = available_bytes()
    limit = getattr(getattr(dask_worker, "memory_manager", None), "memory_limit", None)
    if limit and rss is not None:
        avail = limit - rss if avail is None else min(avail, limit - rss)
    with STATE.lock:
        held = {"objects": sum(len(s) for s in STATE.slots.values()), "scenes": len(STATE.scenes)}
    return {"available": avail, "rss": rss, "peak": peak_resident_bytes(), "numba": "numba" in sys.modules,
            "held": held}


def host_of(address: str) -> str:
    """The host part of a worker's address (``tcp://10.0.0.5:40123`` -> ``10.0.0.5``)."""
    return address.split("://", 1)[-1].rsplit(":", 1)[0]


@dataclasses.dataclass
class WorkerNeed:
    """What one worker will hold during a pass beyond what it holds now
    (bytes): the pass's data it receives (every worker gets a copy), a ray
    chunk per thread, and ``code``: numba and the compiled hit kernels, which
    a worker that has not imported numba yet loads for its first bounce pass."""

    data: int
    chunks: int
    code: int = 0


def check_worker_memory(what: str, need: WorkerNeed, workers: dict, *, fraction: float = 0.8) -> dict:
    """MemoryLimitError unless each host's workers fit ``need`` (with their
    threads' chunks: ``workers`` maps address -> {"nthreads", and
    worker_memory()'s keys}) in ``fraction`` of what the host's most limited
    worker can still allocate: the workers of one machine share its memory,
    so their needs add up. Returns {address: estimated peak bytes} (what the
    worker holds now plus its need)."""
    by_host: dict[str, list] = collections.defaultdict(list)
    for addr, w in workers.items():
        by_host[host_of(addr)].append((addr, w))
    out = {}
    for host, ws in sorted(by_host.items()):
        per = {addr: need.data + int(w.get("nthreads", 1)) * need.chunks + (0 if w.get("numba") else need.code)
               for addr, w in ws}
        total = sum(per.values())
        known = [w["available"] for _, w in ws if w.get("available") is not None]
        if known and total > fraction * min(known):
            avail = min(known)
            raise MemoryLimitError(
                f"the {what} pass needs about {total / GiB:.2f} GiB on Dask host {host} ({len(ws)} "
                f"worker{'s' if len(ws) > 1 else ''}: {need.data / GiB:.2f} GiB of the pass's data each, "
                f"{need.chunks / 2 ** 20:.0f} MiB a thread for its rays) but only {max(avail, 0) / GiB:.2f} GiB "
                f"is available there (at most {fraction:.0%} of it is used); nothing was written, the previous "
                f"outputs are intact. Lower the resolution or the bands, bake the bounce on a coarser grid "
                f"(--bounce-downscale), or run fewer workers a machine or workers with more memory")
        for addr, w in ws:
            out[addr] = int(w.get("rss") or 0) + per[addr]
    return out


#: Seconds the client waits for the workers to drop a finished bake.
FORGET_TIMEOUT = 30.0


def forget_bake(prefix: str, scene_token: str = "") -> int:
    """Run on every worker of a shared cluster when a bake ends
    (DaskBake.close): drop its kernels, shaders and tables and its scene's
    BVH, and give what that freed back to the system (malloc_trim), so that a
    farm's workers are back where they were before it. Returns how many
    objects were dropped."""
    n = STATE.forget(prefix, scene_token)
    release_free_memory()
    return n


def quiet_loggers(prefix: str) -> dict:
    """Set ``prefix`` and every logger under it to CRITICAL; returns {logger: old level}."""
    names = [prefix] + [n for n in list(logging.Logger.manager.loggerDict) if n.startswith(prefix + ".")]
    old = {}
    for n in names:
        lg = logging.getLogger(n)
        old[lg] = lg.level
        lg.setLevel(logging.CRITICAL)
    return old


def quiet_shutdown() -> None:
    """Run on a local cluster's workers before it is closed: their shutdown
    races (a heartbeat to a scheduler already stopping logs a traceback,
    CI 2026-11-24) are not the bake's errors; errors during it were logged."""
    quiet_loggers("distributed")


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


@dataclasses.dataclass
class UnitResult:
    """What a task returns: one entry per chunk, the seconds it computed (BVH
    build included), who ran it, and the seconds it spent building the BVH."""

    items: list
    seconds: float
    worker: str
    bvh_seconds: float = 0.0


def transfer_task(identity: str, scene, scene_token: str, pts, pts_token: str, st, G: int, chunks) -> UnitResult:
    """A unit of a transfer (or vertex) pass: [(rows (n, K), counts)] per chunk."""
    t0 = time.perf_counter()
    STATE.setup(identity)
    rs, bvh_s = STATE.ray_scene(scene, scene_token)
    kernel = STATE.slot("points", pts_token, lambda: ChunkKernel(rs, pts, st, G))
    items = [kernel.run(c) for c in chunks]
    return UnitResult(items, time.perf_counter() - t0, f"{worker_name()}:{threading.get_ident()}", bvh_s)


def level_task(identity: str, scene, scene_token: str, shader, shader_token: str, lr, lr_token: str,
               project, chunks) -> UnitResult:
    """A unit of a bounce level: [(texels, columns, projection, hits)] per chunk.
    ``project`` arrives without its shader (the level's, scattered once)."""
    t0 = time.perf_counter()
    STATE.setup(identity)
    rs, bvh_s = STATE.ray_scene(scene, scene_token)

    def with_scene():
        sh = copy.copy(shader)
        sh.sc = scene                 # this task's scene (another bake's may be cached too)
        return sh

    sh = STATE.slot("shader", shader_token, with_scene)
    tables = STATE.slot("tables", lr_token, lr.tables)
    proj = copy.copy(project)
    proj.shader = sh
    items = []
    for c in chunks:
        ch = trace_chunk(rs, lr, tables, c)
        items.append((ch.n, ch.cols, proj(ch), int(ch.hit.size)))
    return UnitResult(items, time.perf_counter() - t0, f"{worker_name()}:{threading.get_ident()}", bvh_s)
