"""Running a bake from Blender: the job, the worker child process, and bringing results back."""
