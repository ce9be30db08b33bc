"""Synthetic bin scenes: bin geometry, object placement, virtual 3D camera."""
