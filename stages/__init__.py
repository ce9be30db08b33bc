"""DVC stages: one module per stage, `python -m stages.<name> ...`, each with main() -> run()."""

from binpick.env import configure_environment

# Before any library module loads numba, MLflow or Prefect: they read these settings at import.
configure_environment()
