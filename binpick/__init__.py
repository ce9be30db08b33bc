"""binpick: CAD model in, 6D pose of every part in the bin out.

The package holds the kernels (pure functions on arrays) and the file formats. Stages in
`stages/` and flows in `flows/` call into it; nothing here imports Prefect, DVC, MLflow or rerun.
"""

__version__ = "0.1.0"
