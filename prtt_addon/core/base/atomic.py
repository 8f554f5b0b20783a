"""Atomic file writes: write a temporary file beside the target, then rename.

An interrupted bake (crash, kill, cancel) therefore never leaves a half-written
texture and never destroys the previous one: the target either keeps its old
content or gets the complete new one (``os.replace`` is atomic on POSIX and
Windows within one directory).

Temporaries are named ``.prtt-tmp-<pid>-<stem>...`` so that a later bake can
tell those of a dead writer (removed: :func:`remove_stale_temporaries`) from
those of a live one (kept). Every temporary this process creates is also
registered here, so that a hard exit on cancellation (the worker's watchdog,
worker.py) can delete them: :func:`remove_own_temporaries`. The
:data:`COMMIT_LOCK` is held while a bake renames its outputs into place and
writes its manifest; the watchdog waits for it instead of exiting half-way.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
import threading
import time

#: Prefix of temporary files, so leftovers of a killed process are recognisable.
TMP_PREFIX = ".prtt-tmp-"
#: A temporary older than this (seconds since its last change) is stale even if
#: its pid is alive: pids are reused, and no PRTT write takes an hour.
STALE_AGE = 3600.0
#: Held while a bake commits (renames + manifest); see worker.py's watchdog.
COMMIT_LOCK = threading.Lock()

_registry_lock = threading.Lock()
_own_paths: set[str] = set()
_commits = 0


def mark_committed() -> None:
    """Record that a bake renamed its outputs into place (call under COMMIT_LOCK)."""
    global _commits
    _commits += 1


def commits() -> int:
    """How many bakes of this process committed (the watchdog then reports done, not cancelled)."""
    return _commits


def _process_umask() -> int:
    # os.umask can only be read by setting it; done once, at import, before threads.
    old = os.umask(0o022)
    os.umask(old)
    return old


_UMASK = _process_umask()


def _final_mode(path: str) -> int:
    """The permissions a plain open() would give: the old file's, else 0666 & ~umask
    (mkstemp makes its file 0600, which would hide textures from other users)."""
    try:
        return os.stat(path).st_mode & 0o7777
    except OSError:
        return 0o666 & ~_UMASK


def temp_prefix(stem: str) -> str:
    """``.prtt-tmp-<pid>-<stem>-``: the pid first, so it parses whatever the stem holds."""
    return f"{TMP_PREFIX}{os.getpid()}-{stem}-"


def register(path: str) -> None:
    """Remember ``path`` as a file this process must delete if it exits hard."""
    with _registry_lock:
        _own_paths.add(os.path.abspath(path))


def unregister(path: str) -> None:
    with _registry_lock:
        _own_paths.discard(os.path.abspath(path))


def remove_own_temporaries() -> int:
    """Delete every registered file of this process (hard exit). Returns how many.
    Called from the watchdog thread while the main thread may still write:
    deleting a file being written is harmless on POSIX (the writer keeps an
    unlinked inode that disappears at exit)."""
    with _registry_lock:
        paths = list(_own_paths)
        _own_paths.clear()
    n = 0
    for p in paths:
        with contextlib.suppress(OSError):
            os.remove(p)
            n += 1
    return n


@contextlib.contextmanager
def atomic_write(path):
    """Yield a temporary path; on clean exit fsync it and rename it to ``path``.

    The temporary keeps ``path``'s extension (writers such as OpenEXR choose
    the format by it). On an exception the temporary is removed and ``path``
    is untouched.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    base, ext = os.path.splitext(os.path.basename(path))
    fd, tmp = tempfile.mkstemp(prefix=temp_prefix(base), suffix=ext, dir=folder)
    os.close(fd)
    register(tmp)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, _final_mode(path))
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise
    finally:
        unregister(tmp)


def temporary_pid(name: str) -> int | None:
    """The writer's pid in a temporary's name, or None (not a temporary, or one
    named by an older PRTT without a pid). ``.prtt-tmp-<pid>-...`` and the
    Blender side's job files ``.prtt-tmp-job-<pid>-...`` both carry one."""
    if not name.startswith(TMP_PREFIX):
        return None
    parts = name[len(TMP_PREFIX):].split("-", 2)
    if parts[0] == "job" and len(parts) > 1:
        parts = parts[1:]
    head = parts[0]
    return int(head) if head.isdigit() and len(head) <= 10 else None


def pid_alive(pid: int) -> bool:
    """Is process ``pid`` running on this machine? (True when unsure.)"""
    if pid <= 0:
        return False
    if os.name == "nt":
        return _pid_alive_windows(pid)
    try:
        os.kill(pid, 0)          # signal 0: existence check only
    except ProcessLookupError:
        return False
    except PermissionError:      # someone else's live process
        return True
    except OSError:
        return True
    return True


def _pid_alive_windows(pid: int) -> bool:
    # os.kill(pid, 0) would *terminate* the process on Windows.
    import ctypes
    kernel32 = ctypes.windll.kernel32
    handle = kernel32.OpenProcess(0x1000, False, pid)       # PROCESS_QUERY_LIMITED_INFORMATION
    if not handle:
        return kernel32.GetLastError() == 5                 # access denied: it exists
    try:
        code = ctypes.c_ulong()
        ok = kernel32.GetExitCodeProcess(handle, ctypes.byref(code))
        return not ok or code.value == 259                  # STILL_ACTIVE
    finally:
        kernel32.CloseHandle(handle)


def remove_stale_temporaries(folder, *, max_age: float = STALE_AGE) -> list[str]:
    """Delete temporaries that dead writers left in ``folder``; returns their names.

    A temporary is stale when the pid in its name is not running on this
    machine, or when it has not changed for ``max_age`` seconds (pid reuse;
    temporaries of older PRTT versions carry no pid and go by age alone).
    A live process's temporaries are never touched. Our own are skipped too.
    """
    removed = []
    now = time.time()
    try:
        names = os.listdir(folder)
    except OSError:
        return removed
    for name in names:
        if not name.startswith(TMP_PREFIX):
            continue
        path = os.path.join(folder, name)
        pid = temporary_pid(name)
        if pid == os.getpid():
            continue
        try:
            age = now - os.stat(path).st_mtime
        except OSError:
            continue
        if (pid is not None and not pid_alive(pid)) or age > max_age:
            with contextlib.suppress(OSError):
                os.remove(path)
                removed.append(name)
    return removed
