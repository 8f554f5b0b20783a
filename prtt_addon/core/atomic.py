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
