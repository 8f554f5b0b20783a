"""The output folder of a bake: one bake at a time, and outputs that can be verified.

* :class:`FolderLock`: ``.prtt-lock`` in the output folder, held with
  ``fcntl.flock`` for the whole bake. The kernel drops the lock when its
  process dies (even by SIGKILL), so a lock left by a dead bake is simply
  taken over; a live one makes a second bake fail with a message naming the
  first (its pid, host, job file and the .blend it came from). The file holds
  JSON ``{"pid", "host", "job", "source", "started"}`` for that message. Where ``fcntl`` is
  missing (Windows) the file is created with O_CREAT | O_EXCL instead, and a
  lock whose pid is not running on this host is taken over.
* :func:`file_info` / :func:`verify_files`: each output's size and sha256, as
  the manifest records them (``file_info``), so that a missing, truncated or
  replaced texture is noticed and re-baked instead of being reported "up to date".
"""
from __future__ import annotations

import contextlib
import datetime
import hashlib
import json
import os
import socket

from ..base import atomic

LOCK_FILE = ".prtt-lock"
#: Bytes read per hash update (large reads keep the per-call overhead negligible).
HASH_BLOCK = 1 << 22


class FolderBusyError(RuntimeError):
    """Another live bake holds the output folder."""


def _describe(info: dict) -> str:
    job = info.get("job") or "?"
    source = f" (from {info['source']})" if info.get("source") else ""
    return (f"pid {info.get('pid', '?')} on {info.get('host', '?')}, job {job}{source}, "
            f"started {info.get('started', '?')}")


class FolderLock:
    """Exclusive lock of an output folder (see the module doc). Use as a context
    manager or acquire()/release(); release() also runs on every exit path of
    the bake, and a hard exit (worker watchdog) removes the file through
    atomic.remove_own_temporaries."""

    def __init__(self, folder: str, job: str | None = None, source: str | None = None):
        self.folder = os.path.abspath(folder)
        self.path = os.path.join(self.folder, LOCK_FILE)
        self.job = os.path.abspath(job) if job else None
        self.source = source            # what the job was made from (a .blend), for the message
        self.fd: int | None = None
        self.taken_over: dict | None = None     # the dead bake's record, if any

    def record(self) -> dict:
        return {"pid": os.getpid(), "host": socket.gethostname(), "job": self.job, "source": self.source,
                "started": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}

    def acquire(self) -> "FolderLock":
        try:
            import fcntl
        except ImportError:
            fcntl = None
        if fcntl is None:
            self._acquire_exclusive_create()
        else:
            self._acquire_flock(fcntl)
        atomic.register(self.path)
        return self

    def _acquire_flock(self, fcntl) -> None:
        for _ in range(20):
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                other = _read_json_fd(fd)
                os.close(fd)
                raise FolderBusyError(f"output folder {self.folder} is in use by another bake "
                                      f"({_describe(other)}); wait for it to finish or cancel it") from None
            # The holder before us may have unlinked the file between our open()
            # and flock(): then we locked an orphan inode; try again.
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except OSError:
                same = False
            if not same:
                os.close(fd)
                continue
            old = _read_json_fd(fd)
            if old:
                self.taken_over = old
            _write_json_fd(fd, self.record())
            self.fd = fd
            return
        raise FolderBusyError(f"could not lock {self.path}: it keeps being replaced")

    def _acquire_exclusive_create(self) -> None:
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                other = read_lock(self.folder) or {}
                pid, host = other.get("pid"), other.get("host")
                dead = (isinstance(pid, int) and host == socket.gethostname()
                        and not atomic.pid_alive(pid))
                if not dead:
                    raise FolderBusyError(
                        f"output folder {self.folder} is in use by another bake ({_describe(other)}); "
                        f"if that bake is gone, delete {self.path}") from None
                self.taken_over = other
                with contextlib.suppress(OSError):
                    os.remove(self.path)
                continue
            _write_json_fd(fd, self.record())
            self.fd = fd
            return
        raise FolderBusyError(f"could not lock {self.path}")

    def release(self) -> None:
        if self.fd is None:
            return
        # Unlink while still holding the lock: a waiter that opened the old inode
        # sees it is no longer the file at the path and retries (_acquire_flock).
        with contextlib.suppress(OSError):
            os.remove(self.path)
        atomic.unregister(self.path)
        with contextlib.suppress(OSError):
            os.close(self.fd)
        self.fd = None

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()


def _read_json_fd(fd: int) -> dict:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        raw = os.read(fd, 1 << 16)
        d = json.loads(raw.decode("utf-8", "replace")) if raw.strip() else {}
        return d if isinstance(d, dict) else {}
    except (OSError, ValueError):
        return {}


def _write_json_fd(fd: int, record: dict) -> None:
    data = json.dumps(record).encode()
    os.ftruncate(fd, 0)
    os.lseek(fd, 0, os.SEEK_SET)
    os.write(fd, data)


def read_lock(folder) -> dict | None:
    """The JSON record in ``folder``'s lock file, or None (no readable lock file)."""
    try:
        with open(os.path.join(folder, LOCK_FILE), encoding="utf-8") as f:
            d = json.load(f)
        return d if isinstance(d, dict) else None
    except (OSError, ValueError):
        return None


# --- verifiable outputs ----------------------------------------------------------------

def file_info(path) -> dict:
    """{"bytes": size, "sha256": hex digest} of a file (read in 4 MB blocks;
    hashlib releases the GIL, ~1.5 GB/s with the CPU's SHA extensions)."""
    h = hashlib.sha256()
    n = 0
    with open(path, "rb") as f:
        while True:
            block = f.read(HASH_BLOCK)
            if not block:
                break
            h.update(block)
            n += len(block)
    return {"bytes": n, "sha256": h.hexdigest()}


def verify_files(folder, names, info: dict | None) -> str | None:
    """Why the files ``names`` in ``folder`` do not match ``info`` (the manifest's
    file_info), or None when every one is present with its recorded size and
    hash. A manifest without file_info (older PRTT) cannot be verified."""
    if not isinstance(info, dict):
        return "the manifest records no file sizes and hashes (made by an older PRTT)"
    for name in names:
        rec = info.get(name)
        path = os.path.join(folder, name)
        if not isinstance(rec, dict):
            return f"{name}: not in the manifest's file_info"
        try:
            size = os.path.getsize(path)
        except OSError:
            return f"{name}: missing"
        if size != rec.get("bytes"):
            return f"{name}: {size} bytes, the manifest says {rec.get('bytes')}"
        if file_info(path)["sha256"] != rec.get("sha256"):
            return f"{name}: content differs from the manifest's sha256"
    return None
