"""MkDocs hook: the reference pages' generated parts, made from the code at every build
(flows/docs_reference.py), so that they cannot drift from it. A page asks for one with a line
holding only its marker, e.g. `<!-- generated: params -->`."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

MARKER = "<!-- generated: {} -->"


def on_page_markdown(markdown: str, page, config, files) -> str:
    if "<!-- generated: " not in markdown:
        return markdown
    from flows import docs_reference

    makers = {
        "params": docs_reference.params_reference,
        "cli": docs_reference.cli_reference,
        "openapi": docs_reference.openapi_reference,
    }
    for name, make in makers.items():
        if MARKER.format(name) in markdown:
            markdown = markdown.replace(MARKER.format(name), make())
    return markdown
