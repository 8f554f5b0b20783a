"""Files: the scene/job format, EXR and image reading/writing, atomic writes, output folders, procedural and OBJ meshes."""
