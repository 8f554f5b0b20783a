"""Atomic file writes: write a temporary file beside the target, then rename.

An interrupted bake (crash, kill, cancel) therefore never leaves a half-written
texture and never destroys the previous one: the target either keeps its old
content or gets the complete new one (``os.replace`` is atomic on POSIX and
Windows within one directory).
"""
from __future__ import annotations

import contextlib
import os
import tempfile

#: Prefix of temporary files, so leftovers of a killed process are recognisable.
TMP_PREFIX = ".prtt-tmp-"


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
    fd, tmp = tempfile.mkstemp(prefix=TMP_PREFIX + base + "-", suffix=ext, dir=folder)
    os.close(fd)
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


def remove_stale_temporaries(folder) -> int:
    """Delete temporaries a killed writer left in ``folder``; returns how many."""
    n = 0
    with contextlib.suppress(OSError):
        for name in os.listdir(folder):
            if name.startswith(TMP_PREFIX):
                with contextlib.suppress(OSError):
                    os.remove(os.path.join(folder, name))
                    n += 1
    return n
