"""Memory limits: what is available, the check every layer makes before it
allocates (:func:`check_fits`; the bake's own estimates are
core/bake/pipeline/memory_plan.py), the choice of page size for numpy arrays
(:func:`numpy_hugepage_advice`), and returning freed memory to the OS
(:func:`release_free_memory`).

A request that cannot fit gets a clear error naming the set and the numbers,
instead of the kernel's OOM killer taking the worker (and its partial work).
"""
from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
import os

GiB = 1024 ** 3
MiB = 1024 ** 2


class MemoryLimitError(RuntimeError):
    """The bake would need more memory than is available."""


def available_bytes() -> int | None:
    """Bytes this process can still allocate: the least of the machine's
    MemAvailable (/proc/meminfo; else its free physical pages), its cgroup's
    memory.max less memory.current (a container's or systemd unit's limit)
    and its address-space limit (RLIMIT_AS, ``ulimit -v``) less what it has
    mapped (VmSize). None where nothing is known."""
    limits = [v for v in (_machine_available(), _cgroup_available(), _address_space_available()) if v is not None]
    return max(0, min(limits)) if limits else None


def _cgroup_available() -> int | None:
    """memory.max - memory.current of this process's cgroup (v2), or None (no limit, not Linux)."""
    try:
        with open("/proc/self/cgroup", encoding="ascii") as f:
            path = next((line.strip().split("::", 1)[1] for line in f if line.startswith("0::")), None)
        if path is None:
            return None
        base = os.path.join("/sys/fs/cgroup", path.lstrip("/"))
        with open(os.path.join(base, "memory.max"), encoding="ascii") as f:
            top = f.read().strip()
        if top == "max":
            return None
        with open(os.path.join(base, "memory.current"), encoding="ascii") as f:
            return int(top) - int(f.read().strip())
    except (OSError, ValueError):
        return None


def _address_space_available() -> int | None:
    """RLIMIT_AS less this process's mapped bytes (VmSize), or None without a limit."""
    try:
        import resource
        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    except (ImportError, OSError, ValueError):
        return None
    if soft == resource.RLIM_INFINITY:
        return None
    size = _status_mb("VmSize:")
    return int(soft - (size or 0) * 1024 * 1024)


def _machine_available() -> int | None:
    """MemAvailable from /proc/meminfo (Linux), else physical pages, else None."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def check_fits(needed: int, what: str, *, fraction: float = 0.8, advice: str | None = None) -> None:
    """Raise MemoryLimitError if ``needed`` exceeds ``fraction`` of available
    memory (the least of the machine's and this process's limits:
    :func:`available_bytes`); the message names both and ``advice``."""
    avail = available_bytes()
    if avail is not None and needed > fraction * avail:
        raise MemoryLimitError(
            f"{what} needs about {needed / GiB:.1f} GiB but only {avail / GiB:.1f} GiB is "
            f"available (at most {fraction:.0%} of it is used); "
            f"{advice or 'lower the resolution or the bands, or bake fewer sets at once'}")


def _numpy_hugepage_switch():
    """numpy's setter of its huge-page advice (returns the previous value), or None."""
    import importlib
    import warnings
    for name in ("numpy._core.multiarray", "numpy.core.multiarray"):   # numpy 2.x, then 1.x
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)
                fn = getattr(importlib.import_module(name), "_set_madvise_hugepage", None)
        except ImportError:
            continue
        if fn is not None:
            return fn
    return None


@contextlib.contextmanager
def numpy_hugepage_advice(enabled: bool):
    """Within the block, numpy advises (or not) transparent huge pages for the
    arrays it allocates; the previous setting comes back afterwards.

    Why the bake switches it off around some stages and not others, measured on
    the 2-core VM we benchmark on (THP mode "madvise"):

    * The G-buffer, the channel planes, dilation and the EXR channels are fresh
      arrays, filled once and streamed. There, first touch of memory numpy had
      advised as huge pages cost up to 2.3 ms/MB mid-bake against 0.35 ms/MB
      for normal pages: ~0.2 s of a 7.3 s transfer bake, and 0.3 s of a bounce
      level's dilate + write.
    * The bounce stage looks texels up at random in resident textures, where
      huge pages' TLB reach pays: with normal pages its trace + shade took
      19-21 s instead of 17 s. So the textures it reads are allocated with the
      advice on (numpy's default).

    The likely cause of the slow faults is the hypervisor backing each fresh
    2 MiB page; it is not measured on bare metal, where huge pages are
    usually cheap. It is a process-wide numpy switch (every thread's new
    arrays; harmless for correctness): enter it from one thread, the bake's
    main thread, so that nested blocks restore in order.
    """
    fn = _numpy_hugepage_switch()
    if fn is None:
        yield
        return
    previous = fn(bool(enabled))
    try:
        yield
    finally:
        fn(previous)


def release_free_memory() -> bool:
    """Give memory that is freed but kept by the C allocator back to the OS
    (glibc's ``malloc_trim``; elsewhere nothing happens). Returns whether it ran.

    The G-buffer's two row bands are rasterised on two helper threads, and
    glibc keeps what each thread's temporaries freed in that thread's arena,
    out of reach of the main thread's later allocations: measured +55-85 MB of
    peak RSS at 1024^2 (plants 314 MB trimmed against 375 MB, room 428 against
    463) until this is called after the G-buffer is built.
    """
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True


#: Allocations from this size up get pages of their own (glibc mallopt M_MMAP_THRESHOLD).
LARGE_ALLOCATION = 1 << 20


def large_frees_to_os() -> bool:
    """Make glibc give every allocation of LARGE_ALLOCATION bytes or more its
    own mapping, returned to the OS when freed (mallopt M_MMAP_THRESHOLD;
    elsewhere nothing happens). Returns whether it was set. Process-wide: the
    worker and ``bake-job`` call it before baking, Blender's process never.

    Why: glibc raises its mmap threshold (up to 32 MiB) each time a mapped
    block is freed, after which the bake's arrays of a few MB (ray chunks,
    rows of a band) come from the heap arenas, and what they free stays in
    the process: measured 1.27 GB still resident after a 2048^2 demo bake had
    freed everything (0.33 GB at 1024^2 with this set, against 0.62), and
    every stage's peak RSS carried it (peak 936 -> 855 MB at 1024^2, same
    seconds).
    """
    mallopt = _libc_function("mallopt", [ctypes.c_int, ctypes.c_int])
    if mallopt is None:
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, LARGE_ALLOCATION))


_M_MMAP_THRESHOLD = -3
_MADV_DONTNEED = 4


def discard_pages(a) -> int:
    """Give the whole pages inside C-contiguous array ``a``'s buffer back to
    the OS (madvise MADV_DONTNEED): resident memory drops now, not when the
    array is freed, and the array then reads as zeros there. For an array
    that is done with but cannot be freed yet, a part at a time (e.g. the
    float32 planes of a texture as each band of rows is written:
    exr_io.write_sh_planes' ``consume``). Returns the bytes given
    back (0 where madvise is missing or the array spans no whole page)."""
    import mmap
    if not a.flags.c_contiguous or a.nbytes == 0:
        return 0
    madvise = _libc_function("madvise", [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int])
    if madvise is None:
        return 0
    page = mmap.PAGESIZE
    start = -(-a.ctypes.data // page) * page
    end = (a.ctypes.data + a.nbytes) // page * page
    if end <= start or madvise(start, end - start, _MADV_DONTNEED) != 0:
        return 0
    return end - start


def _libc_function(name: str, argtypes):
    lib = _libc()
    fn = getattr(lib, name, None) if lib is not None else None
    if fn is not None:
        fn.argtypes, fn.restype = argtypes, ctypes.c_int
    return fn


@functools.lru_cache(maxsize=1)
def _libc():
    """The C library (glibc on Linux), or None (looked up once: find_library may run ldconfig)."""
    name = ctypes.util.find_library("c")
    if not name:
        return None
    try:
        return ctypes.CDLL(name)
    except OSError:
        return None


@functools.lru_cache(maxsize=1)
def _malloc_trim():
    """glibc's malloc_trim, or None."""
    lib = _libc()
    trim = getattr(lib, "malloc_trim", None) if lib is not None else None
    if trim is not None:
        trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim


def _status_mb(key: str) -> float | None:
    """A "VmHWM:"/"VmRSS:" line of /proc/self/status in MiB (Linux), else None."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith(key):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def peak_resident_bytes() -> int | None:
    """This process's peak resident memory so far (VmHWM, bytes; Linux), else None."""
    mb = _status_mb("VmHWM:")
    return None if mb is None else int(mb * 1024 * 1024)


def resident_bytes() -> int | None:
    """This process's resident memory now (VmRSS, bytes; Linux), else None."""
    mb = _status_mb("VmRSS:")
    return None if mb is None else int(mb * 1024 * 1024)


class StagePeaks:
    """Peak resident memory (RSS, MiB) of this process per stage of a bake.

    ``enter(stage)`` closes the stage before it with the kernel's high-water
    mark (VmHWM) and resets that mark (writing 5 to /proc/self/clear_refs,
    Linux >= 4.0), so each stage's peak is its own, including what earlier
    stages still hold. A stage entered twice keeps its larger peak; what ran
    before the first stage is "setup". Where the mark cannot be read or
    reset (not Linux), :meth:`peaks` is empty and ``process`` None.
    """

    def __init__(self):
        self.stage = "setup"
        self._peaks: dict[str, float] = {}
        self.process: float | None = None
        self.estimate_mb: float | None = None     # what the bake said it would need (memory_check.check_memory)
        self.held_extra: int | None = None        # bytes held beyond a bare worker at the first check
        self.dask_workers: dict | None = None      # the Dask workers' peaks and estimate (DaskBake.worker_report)
        # Not reset here: "setup" keeps what the process held before the bake (its job, imports).
        self.resettable = _status_mb("VmHWM:") is not None and os.access("/proc/self/clear_refs", os.W_OK)

    @staticmethod
    def _reset() -> bool:
        try:
            with open("/proc/self/clear_refs", "w", encoding="ascii") as f:
                f.write("5")
            return True
        except OSError:
            return False

    def enter(self, stage: str) -> None:
        """Start ``stage`` (nothing happens when it is the current one)."""
        if stage == self.stage:
            return
        self._close()
        self.stage = stage

    def _close(self) -> None:
        hwm = _status_mb("VmHWM:")
        if hwm is None or not self.resettable:
            return
        self._peaks[self.stage] = max(self._peaks.get(self.stage, 0.0), hwm)
        self.process = max(self.process or 0.0, hwm)
        self._reset()

    def peaks(self) -> dict[str, float]:
        """{stage: peak RSS MiB} so far (the current stage's up to now), in the order first entered."""
        self._close()
        return {k: round(v, 1) for k, v in self._peaks.items()}
