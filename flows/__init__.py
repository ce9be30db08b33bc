"""Prefect flows. They sequence DVC stages and hold no numerics and no file-format knowledge."""

from binpick.env import configure_environment

# Before any library module loads numba, MLflow or Prefect: they read these settings at import.
configure_environment()
