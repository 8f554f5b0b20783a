"""The demo's default bake through the installed extension, against the
development venv's source tree: ``./prtt.sh compat --bench [VERSION ...]``.

For the development venv and each Blender (tools/compat.py's venvs and zip):

1. the demo's scene (bench/scene_build.demo_scene: 21K triangles, one atlas)
   is built in that Blender from the source tree and saved as a .blend;
2. a second process, which cannot import the source tree (the installed zip
   only; the development venv registers the source tree instead), opens it,
   unwraps (Smart UV Project, one atlas) and runs Bake Transfer with the
   add-on's defaults (1024², 256 rays, one relightable bounce) ``ROUNDS``
   times with force: the first round loads or compiles numba's kernels into
   a fresh cache, the others are timed.

Prints per Blender the fastest timed bake (as the user waits for it, and
the worker's own total from the bake's manifest), the hit shading each
bake's manifest records ("compiled": numba's loops; "numpy"), numba's
version, and the ratios to the development venv's bake in the same run.

Run as a child: ``python tools/compat_bench.py scene OUT.blend`` (step 1, with
PYTHONPATH at the checkout) or ``python tools/compat_bench.py bake BLEND WORK
[ZIP]`` (step 2; without ZIP, the source tree).
"""
from __future__ import annotations

import json
import os
import sys
import time

#: Bakes per Blender: the first warms numba's cache, the fastest of the rest counts.
ROUNDS = 4


def build_scene(out_blend: str) -> None:
    """Step 1, in the Blender under test, from the source tree."""
    import bpy

    from prtt_addon.dev.bench.scene_build import demo_scene
    bpy.ops.wm.read_factory_settings(use_empty=True)
    demo_scene()
    bpy.ops.wm.save_as_mainfile(filepath=out_blend)


def bake(blend: str, work: str, zip_path: str | None) -> dict:
    """Step 2: open ``blend``, unwrap, bake ROUNDS times; the record."""
    import bpy
    if zip_path:
        import importlib.util
        if importlib.util.find_spec("prtt_addon") is not None:
            raise RuntimeError("a prtt_addon outside the installed extension is importable")
        bpy.ops.wm.read_factory_settings(use_empty=True)
        bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    else:
        import prtt_addon
        prtt_addon.register()
    bpy.ops.wm.open_mainfile(filepath=blend)
    sc = bpy.context.scene
    st = sc.prtt
    st.texture_sets, st.unwrap_method = "ATLAS", "SMART"
    meshes = [o for o in sc.objects if o.type == "MESH"]
    for o in sc.objects:
        o.select_set(o.type == "MESH")
    bpy.context.view_layer.objects.active = meshes[0]
    if bpy.ops.prtt.unwrap() != {"FINISHED"}:
        raise RuntimeError("unwrap failed")
    rec = {"blender": bpy.app.version_string, "python": sys.version.split()[0], "bakes": []}
    try:
        import numba
        rec["numba"] = numba.__version__
    except ImportError:
        rec["numba"] = None
    for i in range(ROUNDS):
        st.output_dir = os.path.join(work, f"bake{i}")
        t = time.perf_counter()
        if bpy.ops.prtt.bake_transfer(force=True) != {"FINISHED"}:
            raise RuntimeError("bake_transfer failed")
        secs = time.perf_counter() - t
        with open(os.path.join(st.output_dir, "manifest.json"), encoding="utf-8") as f:
            man = json.load(f)
        shading = sorted({s.get("hit_shading", "?") for s in (man.get("bounce") or {}).get("sets", [])})
        rec["bakes"].append({"seconds": round(secs, 2), "worker_seconds": round(man["seconds"]["total"], 2),
                             "hit_shading": shading})
    rec["settings"] = {k: getattr(st, k) for k in ("resolution", "rays", "bounces", "bounce_mode")}
    return rec


def main(argv: list[str]) -> int:
    if argv[:1] == ["scene"]:
        build_scene(argv[1])
        return 0
    if argv[:1] == ["bake"]:
        rec = bake(argv[1], argv[2], argv[3] if len(argv) > 3 else None)
        print("BENCH " + json.dumps(rec), flush=True)
        return 0
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
