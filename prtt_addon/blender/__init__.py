"""The Blender side of PRTT: thin glue between Blender and ``prtt_addon.core``.

Everything here may import bpy; nothing in ``core`` does. Modules:
properties (settings stored in the .blend), export (evaluated scene ->
core Scene + light), world (World -> SH light), unwrap (the "PRTT" UV map),
worker_job (the bake process), bake_run (one bake code path for the UI and
headless), operators, panels, cli (``blender -c prtt``).
"""
