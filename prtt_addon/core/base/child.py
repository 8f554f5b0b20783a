"""Starting PRTT's own child processes (the bake worker, the xatlas unwrap)
with the interpreter and search path of this one.

The child runs Blender's own interpreter (``sys.executable`` in Blender
4.2+) with a ``PYTHONPATH`` holding the folder above this package (so
``prtt_addon`` imports by that name: the extension's id) and this process's
search path (the extension's wheels live in Blender's user site-packages,
which a plain child would not see).
"""
from __future__ import annotations

import os
import sys

#: The prtt_addon/ folder (this file is prtt_addon/core/base/child.py).
PACKAGE_DIR = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def python_executable() -> str:
    """Blender's bundled Python (sys.executable in Blender 4.2+), or this interpreter."""
    exe = sys.executable
    if os.path.basename(exe).lower().startswith("blender"):
        # Very old Blenders reported their own binary; look beside the stdlib.
        for cand in ("python3", f"python{sys.version_info[0]}.{sys.version_info[1]}", "python.exe"):
            p = os.path.join(sys.prefix, "bin", cand)
            if os.path.isfile(p):
                return p
    return exe


def child_env() -> dict:
    """This process's environment with the PYTHONPATH a child needs."""
    if os.path.basename(PACKAGE_DIR) != "prtt_addon":
        raise RuntimeError(f"PRTT's package folder must be named 'prtt_addon' (it is {PACKAGE_DIR}); "
                           f"reinstall the extension")
    paths = [os.path.dirname(PACKAGE_DIR)] + [p for p in sys.path if p and os.path.isdir(p)]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(paths))
    env["PYTHONUNBUFFERED"] = "1"
    return env
