"""PRTT's numerical core. Never imports bpy: everything here runs in plain Python
(the bake worker, tests, scripts) as well as inside Blender."""
