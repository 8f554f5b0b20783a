"""A baked scene out of Blender: glTF through Blender's own exporter, PRTT's data added by its hooks."""
