"""Build the installable Blender extension zip.

    ./prtt.sh py tools/build_extension.py [--out dist] [--platform linux-x64 ...]

* fetches the runtime wheels pinned in requirements.txt (the lines marked
  "wheel": embreex, OpenEXR, xatlas) unmodified from PyPI, for CPython 3.11
  (Blender 4.2-5.0) and 3.13 (Blender 5.1+), for each platform asked for;
* writes ``dist/prtt_addon-<version>.zip`` with, at its root, the manifest
  (plus ``platforms`` and ``wheels``), the package's files, ``shaders/`` and
  ``wheels/``. Blender ships numpy, so it is not bundled.

Wheels are downloaded into ``build/wheels`` (a cache, never committed).
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import zipfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PYTHONS = ("3.11", "3.13")
# Blender platform name -> pip --platform tags (pip matches tags exactly).
PLATFORMS = {
    "linux-x64": ["manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64",
                  "manylinux2014_x86_64"],
    "windows-x64": ["win_amd64"],
    "macos-arm64": ["macosx_11_0_arm64", "macosx_12_0_arm64", "macosx_14_0_arm64"],
    "macos-x64": ["macosx_10_9_x86_64", "macosx_10_15_x86_64", "macosx_11_0_x86_64", "macosx_13_0_x86_64"],
}
EXCLUDE_DIRS = {"__pycache__", "bench"}
#: Development-only modules (they import bench/).
EXCLUDE_FILES = {"demo.py"}


def runtime_pins() -> list[str]:
    """'name==version' of every requirements.txt line marked 'wheel'."""
    pins = []
    with open(os.path.join(ROOT, "requirements.txt"), encoding="utf-8") as f:
        for line in f:
            m = re.match(r"^([A-Za-z0-9_.-]+==\S+)\s+#\s*wheel\b", line)
            if m:
                pins.append(m.group(1))
    if not pins:
        raise SystemExit("requirements.txt marks no runtime wheels")
    return pins


def fetch_wheels(pins, platforms, dest) -> list[str]:
    os.makedirs(dest, exist_ok=True)
    for py in PYTHONS:
        for plat in platforms:
            tags = [a for t in PLATFORMS[plat] for a in ("--platform", t)]
            cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--disable-pip-version-check",
                   "--no-deps", "--only-binary=:all:", "--python-version", py, "--implementation", "cp",
                   *tags, "-d", dest, *pins]
            r = subprocess.run(cmd, capture_output=True, text=True)
            if r.returncode:
                raise SystemExit(f"could not fetch wheels for Python {py} on {plat}:\n{r.stderr.strip()}")
    names = {os.path.basename(p) for p in os.listdir(dest) if p.endswith(".whl")}
    wanted = []
    for pin in pins:
        name, ver = pin.split("==")
        stem = name.lower().replace("-", "_")
        for py in PYTHONS:
            tag = "cp" + py.replace(".", "")
            for plat in platforms:
                hits = sorted(n for n in names if n.lower().startswith(f"{stem}-{ver.lower()}-")
                              and f"-{tag}-" in n and any(t in n for t in PLATFORMS[plat]))
                if not hits:
                    raise SystemExit(f"no {pin} wheel for Python {py} on {plat} in {dest}")
                wanted.append(hits[-1])
    return sorted(set(wanted))


def manifest_with_wheels(wheels, platforms) -> str:
    with open(os.path.join(ROOT, "blender_manifest.toml"), encoding="utf-8") as f:
        text = f.read()
    extra = "platforms = [" + ", ".join(f'"{p}"' for p in platforms) + "]\n"
    extra += "wheels = [\n" + "".join(f'  "./wheels/{w}",\n' for w in wheels) + "]\n"
    # Top-level keys must precede the first [table].
    i = text.index("\n[")
    return text[:i + 1] + extra + text[i + 1:]


def build(out_dir, platforms) -> str:
    sys.path.insert(0, ROOT)
    from prtt_addon import __version__
    wheel_dir = os.path.join(ROOT, "build", "wheels")
    wheels = fetch_wheels(runtime_pins(), platforms, wheel_dir)
    os.makedirs(out_dir, exist_ok=True)
    path = os.path.join(out_dir, f"prtt_addon-{__version__}.zip")
    tmp = path + ".tmp"
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("blender_manifest.toml", manifest_with_wheels(wheels, platforms))
        pkg = os.path.join(ROOT, "prtt_addon")
        for base, dirs, files in os.walk(pkg):
            dirs[:] = sorted(d for d in dirs if d not in EXCLUDE_DIRS)
            for f in sorted(files):
                if f.endswith((".py", ".glsl", ".json")) and f not in EXCLUDE_FILES:
                    full = os.path.join(base, f)
                    z.write(full, os.path.relpath(full, pkg))
        shader_dir = os.path.join(ROOT, "shaders")
        for f in sorted(os.listdir(shader_dir)) if os.path.isdir(shader_dir) else []:
            z.write(os.path.join(ROOT, "shaders", f), f"shaders/{f}")
        for w in wheels:
            z.write(os.path.join(wheel_dir, w), f"wheels/{w}")
    os.replace(tmp, path)
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=os.path.join(ROOT, "dist"))
    p.add_argument("--platform", action="append", choices=sorted(PLATFORMS),
                   help="Blender platform(s) to bundle wheels for (default: linux-x64)")
    args = p.parse_args(argv)
    path = build(args.out, args.platform or ["linux-x64"])
    print(f"built {path} ({os.path.getsize(path) / 1e6:.1f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
