"""The viewport and offscreen preview: GPU shaders, the renderer, draw handler and render command."""
