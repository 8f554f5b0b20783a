"""Light: environment maps (images, built-in HDRIs, Blender Worlds' settings) projected to SH."""
