"""Blender -> core: the evaluated scene, materials, UV unwraps and the World as a core scene and light."""
