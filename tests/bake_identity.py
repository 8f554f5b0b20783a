"""Byte identity of the bake's outputs across changes to how it holds memory
(issue #35): a few small bakes covering every bake mode, and the SHA-256 of
each file they write (manifest.json aside: it records seconds).

``python tests/bake_identity.py --record`` writes tests/data/bake_identity.json
from the code as it is; it was recorded from the bake before the bake was
reorganised in bands of texels (commit named in the file), and
tests/test_bake_identity.py checks that today's code still writes those bytes.
"""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

RECORD = os.path.join(ROOT, "tests", "data", "bake_identity.json")

#: guiding=False, texel_validity=False: the record predates guided rays and
#: texel validity (issue 53), which change the transfer of texels that see the
#: sky through openings and of texels inside geometry; without them every byte
#: must stay as recorded (tests/test_guided.py and tests/test_contact_profile.py
#: check what they change).
_COMMON = dict(rays=32, bounce_rays=16, seed=3, threads=2, guiding=False, texel_validity=False)

#: name -> (scene resolution, one atlas or one set per object, settings); small
#: enough for CI, large enough that every set is traced in several chunks.
CASES = {
    "relightable-auto-1": (96, True, dict(bounces=1, bounce_mode="relightable", tuning="auto")),
    "relightable-fixed-2": (64, False, dict(bounces=2, bounce_mode="relightable", tuning="fixed")),
    "baked-fixed-1": (96, True, dict(bounces=1, bounce_mode="baked", tuning="fixed")),
    "baked-auto-2-sets": (64, False, dict(bounces=2, bounce_mode="baked", tuning="auto")),
    "transfer-mips-vertex-float": (96, True, dict(bounces=0, mips=True, vertex_mode=True, half=False,
                                                  dilate=4)),
}


def bake_case(name: str, out_dir: str) -> dict:
    """Bake case ``name`` into ``out_dir``; {file name: sha256} of its outputs."""
    from prtt_addon.core.bake.pipeline.context import BakeSettings
    from prtt_addon.core.bake.pipeline.runner import bake_scene
    from prtt_addon.core.light.envmap import builtin_environment_path, environment_light
    from prtt_addon.dev.bench.scene_library import room_scene

    res, atlas, settings = CASES[name]
    sc = room_scene(res, atlas=atlas, materials=True)
    light = environment_light(builtin_environment_path("forest"), 5)
    bake_scene(sc, out_dir, BakeSettings(**_COMMON, **settings), light=light, skip_if_unchanged=False)
    return file_hashes(out_dir)


def file_hashes(out_dir: str) -> dict:
    out = {}
    for f in sorted(os.listdir(out_dir)):
        if f == "manifest.json" or f.startswith("."):
            continue
        with open(os.path.join(out_dir, f), "rb") as fh:
            out[f] = hashlib.sha256(fh.read()).hexdigest()
    return out


def main() -> int:
    import tempfile
    if sys.argv[1:] != ["--record"]:
        print(__doc__)
        return 2
    commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    cases = {}
    for name in CASES:
        with tempfile.TemporaryDirectory() as d:
            cases[name] = bake_case(name, d)
        print(name, cases[name])
    with open(RECORD, "w", encoding="utf-8") as f:
        json.dump({"recorded_at_commit": commit, "cases": cases}, f, indent=1, sort_keys=True)
        f.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
