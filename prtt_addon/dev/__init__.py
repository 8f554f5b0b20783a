"""Development tools, fenced off from the add-on: the demo (``demo``), the
benchmarks (``bench``: their scenes, procedural meshes and figures) and the
fuzz harnesses (``fuzz``). The extension zip leaves this package out
(blender_manifest.toml's paths_exclude_pattern) and nothing shipped imports
it (tests/test_layout.py); it imports the add-on, never the reverse."""
