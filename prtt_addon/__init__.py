"""PRTT: precomputed radiance transfer textures for Blender.

This package is both the Blender extension (``register``/``unregister``) and a
plain Python package (``python -m prtt_addon ...``, the bake worker). Importing
it must never import ``bpy``: the worker and the numerical core run without
Blender. Blender-side code lives in ``prtt_addon.blender`` and is imported only
by ``register``.
"""
import os
import re

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


def register():
    """Blender extension entry point (imports bpy only now)."""
    from .blender import registration
    registration.register()


def unregister():
    from .blender import registration
    registration.unregister()
