"""The reference shading model: materials (Lambert + normalised Phong) and the numpy shading the viewport must match."""
