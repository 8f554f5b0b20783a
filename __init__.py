"""The repository root as a Blender extension folder.

Blender's validator (``blender_ext.py validate .``) and ``extension build``
look for ``__init__.py`` beside ``blender_manifest.toml``; the add-on itself is
the ``prtt_addon`` package below (the built zips carry that package at their
root, not this file). Loaded from here, it registers that package.
"""
from .prtt_addon import register, unregister  # noqa: F401
