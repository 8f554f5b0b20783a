"""The UV-space texel grid: rasterisation, the G-buffer, dilation, texture lookups, the atlas unwrap."""
