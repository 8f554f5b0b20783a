"""The Blender side of PRTT: thin glue between Blender and ``prtt_addon.core``.

Everything here may import bpy; nothing in ``core`` does. Packages and modules:
ui (properties stored in the .blend, operators, panels), export (evaluated
scene -> core Scene + light: scene, scene_objects, materials, world, unwrap
into the "PRTT" UV map), bake (worker_job: the bake process; run: one bake
code path for the UI and headless), preview (the viewport's draw handler and
offscreen renders), blendfile (opening and saving .blend files headless), cli
(``blender -c prtt``), registration.
"""
