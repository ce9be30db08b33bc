"""6D pose of a part on scene points: PPF matching and ICP refinement."""
