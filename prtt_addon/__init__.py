"""PRTT: precomputed radiance transfer textures for Blender.

This package is both the Blender extension (``register``/``unregister``) and a
plain Python package (``python -m prtt_addon ...``, the bake worker). Importing
it must never import ``bpy``: the worker and the numerical core run without
Blender. Blender-side code lives in ``prtt_addon.blender`` and is imported only
by ``register``.
"""
from .version import __version__  # noqa: F401  (the package's public version)


def register():
    """Blender extension entry point (imports bpy only now)."""
    from .blender import registration  # bpy-dependent: only inside Blender
    registration.register()


class glTF2ExportUserExtension:  # noqa: N801 (the name Blender's glTF exporter looks for)
    """Blender's glTF exporter instantiates this on every export of an enabled
    add-on; its hooks act only while ``prtt export`` runs
    (blender/gltf/export.hook), so the user's own glTF exports are untouched."""

    def __getattr__(self, name):
        from .blender.gltf import export  # bpy-dependent: only inside Blender, only on a glTF export
        return export.hook(name)


def unregister():
    from .blender import registration  # bpy-dependent: only inside Blender
    registration.unregister()
