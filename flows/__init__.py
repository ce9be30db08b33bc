"""Prefect flows. They sequence DVC stages and hold no numerics and no file-format knowledge."""
