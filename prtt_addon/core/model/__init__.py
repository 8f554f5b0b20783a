"""The domain types: the scene to bake and its materials (the job file format is core/io/jobfile)."""
