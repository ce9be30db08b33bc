"""Settings for tests, derived from the project's params.yaml (the one source of values), as the
pipeline runs them: the active profile and the default part's overrides applied."""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel

from binpick.params import Params, load_params

ROOT = Path(__file__).resolve().parents[1]
PARAMS: Params = load_params(ROOT / "params.yaml", "t_joint")

Section = TypeVar("Section", bound=BaseModel)


def changed(section: Section, **changes: Any) -> Section:
    """A copy of a section with some keys changed, validated like the file."""
    return type(section).model_validate({**section.model_dump(by_alias=True), **changes})
