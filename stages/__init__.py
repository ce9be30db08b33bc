"""DVC stages: one module per stage, `python -m stages.<name> ...`, each with main() -> run()."""
