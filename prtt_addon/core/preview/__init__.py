"""The preview without Blender: texture packing, the numpy reference renderer and the GLSL assembly."""
