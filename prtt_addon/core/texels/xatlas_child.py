"""``python -m prtt_addon.core.texels.xatlas_child IN.npz OUT.npz``: one
xatlas unwrap in a process of its own (unwrap._unwrap starts it).

IN holds the meshes (v0, f0, v1, f1 ...) and the options; OUT gets uv0,
uv1 ... (F, 3, 2). Exit 0 when written, unwrap.UNWRAP_ERROR_EXIT with the
message on stderr when xatlas cannot lay them out. The process ends with
os._exit once OUT is written: xatlas's destructors, which have deadlocked
joining its threads, never run.
"""
from __future__ import annotations

import os
import sys

import numpy as np

from .unwrap import UNWRAP_ERROR_EXIT, UnwrapError, unwrap_here


def main(argv: list[str]) -> int:
    inp, out = argv
    with np.load(inp) as z:
        n = int(z["n"])
        meshes = [(np.array(z[f"v{i}"]), np.array(z[f"f{i}"])) for i in range(n)]
        opts = dict(resolution=int(z["resolution"]), padding=int(z["padding"]), max_tries=int(z["max_tries"]),
                    uv_mesh=bool(z["uv_mesh"]))
    keep: list = []
    try:
        uvs = unwrap_here(meshes, opts["resolution"], opts["padding"], opts["max_tries"], opts["uv_mesh"], keep=keep)
    except UnwrapError as exc:
        print(str(exc), file=sys.stderr, flush=True)
        return UNWRAP_ERROR_EXIT
    tmp = out + ".part.npz"
    np.savez(tmp, **{f"uv{i}": u for i, u in enumerate(uvs)})
    os.replace(tmp, out)
    return 0


if __name__ == "__main__":
    code = main(sys.argv[1:])
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
