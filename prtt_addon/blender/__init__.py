"""The Blender side of PRTT: thin glue between Blender and ``prtt_addon.core``.

Everything here may import bpy; nothing in ``core`` does. Packages and modules:
ui (properties stored in the .blend, operators, panels), export (the evaluated
scene as a bake job: scene_objects, job, material_nodes, uv_maps for the
"PRTT" UV map, world), bake (worker_job: the bake process; run: one bake code
path for the UI and headless), preview (the viewport's draw handler, offscreen
renders, the scene's colour management), gltf (export: Blender's glTF
exporter with PRTT's hooks), and the modules every folder shares: shared,
rna_arrays, blendfile (opening and saving .blend files headless), versions
(what differs between the Blender versions claimed); commands
(``blender -c prtt``) and registration.
"""
