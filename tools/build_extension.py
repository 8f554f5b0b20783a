"""Build the installable Blender extension: one zip per platform.

    ./prtt.sh py tools/build_extension.py [--out dist] [--platform linux-x64 ...]
                                          [--stage build/extension] [--wheels build/wheels]

* fetches the runtime wheels pinned in requirements.txt (the lines marked
  "wheel": embreex, OpenEXR, xatlas, threadpoolctl, numba and llvmlite, a
  line's ``python_version`` marker choosing its Pythons) unmodified from
  PyPI, for CPython 3.11 (Blender 4.2-5.0) and 3.13 (Blender 5.1+; not on
  macos-x64, where Blender 4.5 is the last), for every platform asked for
  (default: all of linux-x64, windows-x64, macos-arm64, macos-x64). They are
  cached in ``build/wheels``, so a second build needs no network
  (``--fetch-only`` fills the cache, as tools/bootstrap.sh does; ``--offline``
  never downloads, as the tests build);
* stages the extension's source tree in ``build/extension``: the manifest
  (plus ``platforms`` and ``wheels``), ``LICENSE``, the package's files,
  ``shaders/`` and ``wheels/``, leaving out what the manifest's
  ``[build] paths_exclude_pattern`` names (the demo, the benchmarks, caches).
  That tree is what ``blender --command extension validate`` and
  ``blender --command extension build --split-platforms --source-dir`` take;
* writes, as that ``--split-platforms`` build does, one zip per platform,
  ``dist/prtt_addon-<version>-<platform>.zip`` (``linux_x64`` ...), each
  declaring its one platform and holding only its own wheels;
* checks every zip and the staged tree with Blender's extension validator
  when the bpy module (which carries it) is installed.

A platform whose wheels are not all on PyPI gets no zip (an older zip of that
name is deleted): the build says which wheel is missing and exits 1. Blender
ships numpy, so it is not bundled.
"""
from __future__ import annotations

import argparse
import fnmatch
import glob
import importlib.util
import json
import os
import platform as host
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
import zipfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MANIFEST = "blender_manifest.toml"
#: Blender 4.2-5.0 embed CPython 3.11, Blender 5.1+ CPython 3.13.
PYTHONS = ("3.11", "3.13")
#: The newest Python a platform's Blenders embed, where that is not the
#: newest of PYTHONS: Blender 4.5 LTS is the last with Intel Mac builds, so
#: no Blender on macos-x64 runs Python 3.13 (and numba has no such wheel).
LAST_PYTHON = {"macos-x64": "3.11"}
#: Marks a folder this tool staged, so --stage never deletes anything else.
STAGE_MARK = ".prtt-extension-stage"


def _linux_tags() -> list[str]:
    # Blender's Linux builds need glibc 2.28 (VFX reference platform 2024), so
    # wheels for manylinux up to 2_28 run wherever Blender does. Oldest
    # first: pip takes the first tag a wheel matches, so it prefers the wheel
    # that runs on the most systems.
    tags = ["manylinux1_x86_64", "manylinux2010_x86_64", "manylinux2014_x86_64"]
    return tags + [f"manylinux_2_{m}_x86_64" for m in range(5, 29)]


def _macos_tags(arch: str) -> list[str]:
    # pip widens each macOS tag to the older versions and to universal2 (for
    # one version, the architecture's own wheel first: half the size). Oldest
    # first, as for Linux. arm64 Macs start at macOS 11. A wheel built for a
    # newer macOS than Blender's own 11.2 (embreex: 13.0) raises the minimum,
    # which the build reports.
    versions = [f"10_{m}" for m in range(9, 16)] if arch == "x86_64" else []
    versions += [f"{m}_0" for m in range(11, 16)]
    return [f"macosx_{v}_{arch}" for v in versions]


#: Blender platform name -> pip --platform tags, in pip's order of preference.
PLATFORMS = {
    "linux-x64": _linux_tags(),
    "windows-x64": ["win_amd64"],
    "macos-arm64": _macos_tags("arm64"),
    "macos-x64": _macos_tags("x86_64"),
}


def host_platform() -> str:
    """This machine in Blender's platform names (``linux-x64``, ``macos-arm64`` ...)."""
    system = {"darwin": "macos"}.get(host.system().lower(), host.system().lower())
    machine = {"x86_64": "x64", "amd64": "x64", "aarch64": "arm64"}.get(host.machine().lower(),
                                                                        host.machine().lower())
    return f"{system}-{machine}"


class PlatformError(Exception):
    """A platform's zip cannot be built (a wheel is missing)."""


# --- the manifest ---------------------------------------------------------------------------

def read_manifest(root: str = ROOT) -> tuple[str, dict]:
    """The repository's manifest: its text and its parsed table."""
    with open(os.path.join(root, MANIFEST), encoding="utf-8") as f:
        text = f.read()
    data = tomllib.loads(text)
    # The tool owns these keys: a second copy would make the TOML invalid.
    for key in ("platforms", "wheels"):
        if key in data:
            raise SystemExit(f"{MANIFEST} must not declare {key!r}: the build adds it per platform")
    return text, data


def manifest_with(text: str, platforms, wheels) -> str:
    """The manifest text with ``platforms`` and ``wheels`` added as top-level keys."""
    extra = "platforms = [" + ", ".join(f'"{p}"' for p in platforms) + "]\n"
    extra += "wheels = [\n" + "".join(f'  "./wheels/{w}",\n' for w in wheels) + "]\n"
    # Top-level keys must come before the first [table] header.
    m = re.search(r"^\[", text, re.M)
    i = m.start() if m else len(text)
    return text[:i] + extra + "\n" + text[i:]


# --- which files go in -----------------------------------------------------------------------

def exclude_matcher(patterns):
    """A test ``excluded(rel_path, is_dir)`` for the manifest's paths_exclude_pattern.

    Blender's builder reads those patterns as .gitignore lines. This supports
    the part of that syntax whose meaning is plain: ``name`` (a file or folder
    at any depth), ``/name`` (at the root only), a trailing ``/`` (folders
    only), with ``*?[]`` globs inside one name. Anything else (``!``, ``**``,
    ``a/b``) is refused rather than read differently from Blender.
    """
    rules = []
    for p in patterns:
        body = p.strip("/")
        if not body or "/" in body or "**" in body or p.startswith("!") or "\\" in p:
            raise SystemExit(f"{MANIFEST}: paths_exclude_pattern {p!r} is not supported by this build")
        rules.append((p.startswith("/"), p.endswith("/"), body))

    def excluded(rel: str, is_dir: bool) -> bool:
        depth = rel.count("/")
        name = rel.rsplit("/", 1)[-1]
        return any(fnmatch.fnmatchcase(name, body) for anchored, dir_only, body in rules
                   if (is_dir or not dir_only) and (depth == 0 or not anchored))
    return excluded


def extension_files(sources, patterns) -> list[tuple[str, str]]:
    """(absolute path, path in the extension) of every file to ship.

    ``sources``: (folder, prefix in the extension) pairs walked recursively, or
    (file, name) pairs. A folder an exclude pattern names is skipped whole,
    as in .gitignore.
    """
    excluded = exclude_matcher(patterns)
    files = []
    for src, prefix in sources:
        if os.path.isfile(src):
            if not excluded(prefix, False):
                files.append((src, prefix))
            continue
        for base, dirs, names in os.walk(src):
            rel_base = os.path.relpath(base, src).replace(os.sep, "/")
            rel_base = prefix + ("" if rel_base == "." else rel_base + "/")
            dirs[:] = sorted(d for d in dirs if not excluded(rel_base + d, True))
            files += [(os.path.join(base, n), rel_base + n) for n in sorted(names)
                      if not excluded(rel_base + n, False)]
    return files


def repository_sources(root: str = ROOT):
    """Where the extension's files are in this repository: the package is the
    extension's root; shaders/ sits beside it in a checkout, inside it in the zip."""
    return [(os.path.join(root, "prtt_addon"), ""), (os.path.join(root, "shaders"), "shaders/"),
            (os.path.join(root, "LICENSE"), "LICENSE")]


# --- wheels ---------------------------------------------------------------------------------

def runtime_pins(root: str = ROOT) -> list[tuple[str, str]]:
    """('name==version', marker) of every requirements.txt line marked 'wheel';
    marker is the line's environment marker (``python_version < "3.13"``) or ''."""
    pins = []
    with open(os.path.join(root, "requirements.txt"), encoding="utf-8") as f:
        for line in f:
            m = re.match(r"^([A-Za-z0-9_.-]+==[^\s;]+)\s*(?:;\s*([^#]*?))?\s+#\s*wheel\b", line)
            if m:
                pins.append((m.group(1), m.group(2) or ""))
    if not pins:
        raise SystemExit("requirements.txt marks no runtime wheels")
    return pins


def _version(text: str) -> tuple[int, ...]:
    return tuple(int(x) for x in text.split("."))


_COMPARE = {"<": lambda a, b: a < b, "<=": lambda a, b: a <= b, ">": lambda a, b: a > b,
            ">=": lambda a, b: a >= b, "==": lambda a, b: a == b, "!=": lambda a, b: a != b}


def marker_holds(marker: str, python: str) -> bool:
    """Whether a requirements marker holds for a Python ("3.11"). Only the one
    form the pins use, ``python_version <op> "X.Y"``, is read: anything else
    is refused rather than read differently from pip."""
    if not marker:
        return True
    m = re.fullmatch(r'python_version\s*(<=|>=|==|!=|<|>)\s*["\'](\d+\.\d+)["\']', marker.strip())
    if m is None:
        raise SystemExit(f"requirements.txt: marker {marker!r} on a wheel pin is not supported by this build")
    return _COMPARE[m.group(1)](_version(python), _version(m.group(2)))


def pins_for(pins, python: str) -> list[str]:
    """The 'name==version' pins of ``runtime_pins()`` that hold for one Python."""
    return [pin for pin, marker in pins if marker_holds(marker, python)]


def pythons_for(plat: str) -> list[str]:
    """The Pythons of PYTHONS that Blender embeds on ``plat``."""
    last = LAST_PYTHON.get(plat)
    return [p for p in PYTHONS if last is None or _version(p) <= _version(last)]


def _normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "_", name).lower()


def wheel_is_of(filename: str, pin: str) -> bool:
    """Whether a wheel file name is the distribution and version of 'name==version'."""
    parts = filename[:-len(".whl")].split("-")
    name, version = pin.split("==")
    return (filename.endswith(".whl") and len(parts) in (5, 6)
            and _normalise(parts[0]) == _normalise(name) and parts[1] == version)


# Which file pip picked for (pin, Python, platform) is recorded beside the
# wheels: an offline rebuild then takes the same files, whatever else the
# cache holds (an arm64 build's universal2 wheel is not the x64 build's choice).
INDEX = "index.json"


def _index_key(pin: str, python: str, plat: str) -> str:
    return f"{pin} cp{python.replace('.', '')} {plat}"


def read_index(cache: str) -> dict:
    """The cache's record of pip's choices ({} when there is none or it is unreadable)."""
    try:
        with open(os.path.join(cache, INDEX), encoding="utf-8") as f:
            return json.load(f)
    except (OSError, ValueError):
        return {}


def record_choices(cache: str, choices: dict) -> None:
    """Add pip's choices to the record, replacing the file whole (a reader never
    sees half of it; a build beside this one at worst loses an entry and downloads again)."""
    index = read_index(cache) | choices
    tmp = os.path.join(cache, f".{INDEX}.{os.getpid()}")
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(index, f, indent=1, sort_keys=True)
    os.replace(tmp, os.path.join(cache, INDEX))


def cached_wheel(cache: str, pin: str, python: str, plat: str) -> str | None:
    """The recorded wheel for (pin, Python, platform) if it is in the cache whole, else None."""
    name = read_index(cache).get(_index_key(pin, python, plat))
    return name if name and zipfile.is_zipfile(os.path.join(cache, name)) else None


def pip_download(pins, python: str, plat: str, cache: str) -> tuple[dict, str]:
    """Download ``pins``' wheels for one Python and platform into the cache:
    ({pin: wheel file}, pip's error output or "")."""
    tags = [a for t in PLATFORMS[plat] for a in ("--platform", t)]
    # Into a private folder first, then moved in whole: a build running beside
    # this one never sees half a wheel, and what pip chose is plain.
    with tempfile.TemporaryDirectory(dir=cache, prefix=".download-") as tmp:
        cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--disable-pip-version-check",
               "--no-deps", "--only-binary=:all:", "--python-version", python, "--implementation", "cp",
               *tags, "-d", tmp, *pins]
        r = subprocess.run(cmd, capture_output=True, text=True)
        got = {}
        for f in sorted(os.listdir(tmp)):
            os.replace(os.path.join(tmp, f), os.path.join(cache, f))
            got.update({pin: f for pin in pins if wheel_is_of(f, pin)})
    errors = [line for line in r.stderr.splitlines() if line.startswith("ERROR")]
    return got, ("" if r.returncode == 0 else "\n".join(errors) or r.stderr.strip())


def platform_wheels(pins, plat: str, cache: str, log, *, offline: bool = False) -> list[str]:
    """The wheel files of every pin (``runtime_pins()``) that holds for each of
    ``plat``'s Pythons (a pure-Python wheel once), downloading what the cache lacks; PlatformError naming what
    PyPI does not have, or, ``offline``, what the cache does not."""
    found = []
    for python in pythons_for(plat):
        wanted = pins_for(pins, python)
        missing = [p for p in wanted if cached_wheel(cache, p, python, plat) is None]
        if missing and offline:
            raise PlatformError(f"{', '.join(missing)} for Python {python} on {plat} not in the wheel cache "
                                f"{cache} (tools/bootstrap.sh fetches them; or build without --offline)")
        if missing:
            log(f"  downloading {', '.join(missing)} for Python {python} on {plat}")
            got, error = pip_download(missing, python, plat, cache)
            record_choices(cache, {_index_key(p, python, plat): f for p, f in got.items()})
            if len(got) < len(missing):
                still = [p for p in missing if p not in got]
                raise PlatformError(f"no {', '.join(still)} wheel for Python {python} on {plat}"
                                    + (f" ({error})" if error else ""))
        found += [cached_wheel(cache, p, python, plat) for p in wanted]
    return list(dict.fromkeys(found))


#: manylinux's legacy names and the glibc each stands for.
_LEGACY_GLIBC = {"manylinux1": (2, 5), "manylinux2010": (2, 12), "manylinux2014": (2, 17)}


def _wheel_floor(wheel: str, plat: str) -> tuple[int, int] | None:
    """The oldest OS version (macOS or glibc) one wheel runs on, None if unbounded.
    A wheel with several platform tags runs where any of them does."""
    versions = []
    for tag in wheel[:-len(".whl")].split("-")[-1].split("."):
        if plat.startswith("macos") and (m := re.match(r"macosx_(\d+)_(\d+)_", tag)):
            versions.append((int(m[1]), int(m[2])))
        elif plat.startswith("linux") and (m := re.match(r"manylinux_(\d+)_(\d+)_", tag)):
            versions.append((int(m[1]), int(m[2])))
        elif plat.startswith("linux") and tag.split("_")[0] in _LEGACY_GLIBC:
            versions.append(_LEGACY_GLIBC[tag.split("_")[0]])
    return min(versions) if versions else None


def minimum_os(plat: str, wheels) -> str:
    """The oldest OS all of a platform's wheels run on ('' when they set no bound)."""
    floors = [f for w in wheels if (f := _wheel_floor(w, plat))]
    if not floors:
        return ""
    return ("macOS {}.{}" if plat.startswith("macos") else "glibc {}.{}").format(*max(floors))


# --- staging and zips -----------------------------------------------------------------------

def prepare_stage(stage: str) -> None:
    """Empty the staging folder, refusing to touch a folder this tool did not make."""
    if os.path.isdir(stage) and os.listdir(stage):
        if not os.path.exists(os.path.join(stage, STAGE_MARK)):
            raise SystemExit(f"--stage {stage} is not empty and was not staged by this tool")
        shutil.rmtree(stage)
    os.makedirs(stage, exist_ok=True)
    with open(os.path.join(stage, STAGE_MARK), "w", encoding="utf-8") as f:
        f.write("staged by tools/build_extension.py; deleted by the next build\n")


def stage_tree(stage: str, text: str, files, platforms, wheels, cache: str) -> None:
    """Write the extension's source tree: manifest, files, wheels/ (all platforms')."""
    prepare_stage(stage)
    with open(os.path.join(stage, MANIFEST), "w", encoding="utf-8") as f:
        f.write(manifest_with(text, platforms, wheels))
    for src, rel in files:
        dst = os.path.join(stage, *rel.split("/"))
        os.makedirs(os.path.dirname(dst), exist_ok=True)
        shutil.copy2(src, dst)
    os.makedirs(os.path.join(stage, "wheels"), exist_ok=True)
    for w in wheels:
        shutil.copy2(os.path.join(cache, w), os.path.join(stage, "wheels", w))


def zip_name(ext_id: str, version: str, plat: str) -> str:
    """Blender's --split-platforms name: <id>-<version>-<platform, '-' as '_'>.zip."""
    return f"{ext_id}-{version}-{plat.replace('-', '_')}.zip"


def write_zip(path: str, text: str, files, plat: str, wheels, cache: str) -> None:
    """One platform's zip: its manifest, the files, its wheels; written whole or not at all."""
    tmp = path + ".tmp"
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr(MANIFEST, manifest_with(text, [plat], wheels))
        for src, rel in files:
            z.write(src, rel)
        for w in wheels:
            # Wheels are zips already: storing them is as small and much faster.
            z.write(os.path.join(cache, w), f"wheels/{w}", compress_type=zipfile.ZIP_STORED)
    os.replace(tmp, path)


# --- Blender's validator --------------------------------------------------------------------

def blender_scripts() -> str | None:
    """The scripts folder of the installed bpy module, found without importing it."""
    spec = importlib.util.find_spec("bpy")
    for loc in (spec.submodule_search_locations or []) if spec else []:
        hits = sorted(glob.glob(os.path.join(loc, "*", "scripts", "addons_core", "bl_pkg")))
        if hits:
            return os.path.dirname(os.path.dirname(hits[-1]))
    return None


def validator_command() -> list[str] | None:
    """``blender --command extension validate`` as a plain command line, or None without bpy.

    blender_ext.py is the script behind that command; Blender passes it its
    list of valid tags, so this does too (standalone it would check none).
    """
    scripts = blender_scripts()
    if scripts is None:
        return None
    cli = os.path.join(scripts, "addons_core", "bl_pkg", "cli", "blender_ext.py")
    tags = os.path.join(scripts, "modules", "_bpy_internal", "extensions", "tags.py")
    return [sys.executable, cli, "validate", "--valid-tags", tags]


def validate(path: str) -> tuple[int, str]:
    """Run Blender's validator on a source folder or a zip: (exit status, output)."""
    cmd = validator_command()
    if cmd is None:
        return -1, "Blender's extension validator not found (no bpy module)"
    r = subprocess.run([*cmd, path], capture_output=True, text=True)
    return r.returncode, (r.stdout + r.stderr).strip()


# --- the build ------------------------------------------------------------------------------

def build(out_dir: str, platforms, stage: str, cache: str, log=print, *,
          offline: bool = False) -> tuple[dict, dict]:
    """Build every platform's zip; ({platform: zip path}, {platform: why not built})."""
    text, manifest = read_manifest()
    files = extension_files(repository_sources(), manifest.get("build", {}).get("paths_exclude_pattern", []))
    if "__init__.py" not in {rel for _, rel in files}:
        raise SystemExit("the package's __init__.py is excluded or missing")
    os.makedirs(cache, exist_ok=True)
    os.makedirs(out_dir, exist_ok=True)
    pins = runtime_pins()
    wheels, failed = {}, {}
    for plat in platforms:
        try:
            wheels[plat] = platform_wheels(pins, plat, cache, log, offline=offline)
        except PlatformError as e:
            failed[plat] = str(e)
    if wheels:
        stage_tree(stage, text, files, list(wheels), sorted({w for ws in wheels.values() for w in ws}), cache)
    built = {}
    for plat in platforms:
        path = os.path.join(out_dir, zip_name(manifest["id"], manifest["version"], plat))
        if plat in failed:
            # An older zip of this name would pass for this build's.
            if os.path.exists(path):
                os.remove(path)
            continue
        write_zip(path, text, files, plat, wheels[plat], cache)
        built[plat] = path
    return built, failed


def _show(path: str) -> str:
    """A path as the user would type it: relative below the current folder, else absolute."""
    rel = os.path.relpath(path)
    return path if rel.startswith("..") else rel


def zip_wheels(path: str) -> list[str]:
    """The wheel file names inside a built zip."""
    with zipfile.ZipFile(path) as z:
        return [n[len("wheels/"):] for n in z.namelist() if n.startswith("wheels/") and n.endswith(".whl")]


def report(built, failed) -> None:
    """Each zip with its size and the oldest OS its wheels run on; each platform not built and why."""
    for plat, path in built.items():
        floor = minimum_os(plat, zip_wheels(path))
        print(f"built {_show(path)}  {os.path.getsize(path) / 1e6:5.1f} MB  "
              f"{plat}{f', needs {floor}+' if floor else ''}")
    for plat, why in failed.items():
        print(f"NOT built: {plat}: {why}", file=sys.stderr)


def check_with_validator(paths) -> bool:
    """Blender's validator on each path; False if it rejects one. Without bpy
    there is no validator: that is said, and it is not a failure."""
    ok = True
    for path in paths:
        rc, out = validate(path)
        if rc == -1:
            print(f"not validated: {out}")
            return True
        print(f"validate {_show(path)}: {'ok' if rc == 0 else 'REJECTED'}")
        if rc:
            print(out, file=sys.stderr)
            ok = False
    return ok


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=os.path.join(ROOT, "dist"), help="folder for the zips (default: dist)")
    p.add_argument("--platform", action="append", choices=list(PLATFORMS),
                   help="build this platform's zip (repeatable; default: all)")
    p.add_argument("--stage", default=os.path.join(ROOT, "build", "extension"),
                   help="folder for the staged source tree (default: build/extension)")
    p.add_argument("--wheels", default=os.path.join(ROOT, "build", "wheels"),
                   help="wheel cache (default: build/wheels)")
    p.add_argument("--no-validate", action="store_true", help="skip Blender's extension validator")
    p.add_argument("--offline", action="store_true",
                   help="never download: a wheel missing from the cache fails that platform (the tests use this)")
    p.add_argument("--fetch-only", action="store_true",
                   help="only fill the wheel cache for the platforms (tools/bootstrap.sh runs this)")
    args = p.parse_args(argv)
    platforms = list(dict.fromkeys(args.platform or PLATFORMS))
    if args.fetch_only:
        os.makedirs(args.wheels, exist_ok=True)
        failed = {}
        for plat in platforms:
            try:
                platform_wheels(runtime_pins(), plat, args.wheels, print)
            except PlatformError as e:
                failed[plat] = str(e)
                print(f"{plat}: {e}", file=sys.stderr)
        return 1 if failed else 0
    built, failed = build(args.out, platforms, args.stage, args.wheels, offline=args.offline)
    report(built, failed)
    ok = args.no_validate or not built or check_with_validator([args.stage, *built.values()])
    return 0 if ok and not failed else 1


if __name__ == "__main__":
    sys.exit(main())
