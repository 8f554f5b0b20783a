"""The add-on's version, read once from blender_manifest.toml (its one source).

A module of its own so that any part of the package (the bake's manifest, the
CLI) can import it without importing the package's ``register`` machinery."""
import os
import re

#: The package folder (prtt_addon/).
_HERE = os.path.dirname(os.path.abspath(__file__))


def _read_version() -> str:
    # One source for the version: the manifest (beside this file inside the
    # extension zip, one folder up in a source checkout).
    for path in (os.path.join(_HERE, "blender_manifest.toml"),
                 os.path.join(os.path.dirname(_HERE), "blender_manifest.toml")):
        try:
            with open(path, encoding="utf-8") as f:
                m = re.search(r'^version\s*=\s*"([^"]+)"', f.read(), re.M)
            if m:
                return m.group(1)
        except OSError:
            continue
    return "0+unknown"


__version__ = _read_version()
