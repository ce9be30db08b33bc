"""The documentation: the generated reference pages cover what the code has, and every link of the
README and the docs leads to a file that exists (the site itself is built in strict mode by
`make docs-build`, which `make test` runs)."""

from __future__ import annotations

import re

from conftest import ROOT

LINK = re.compile(r"\]\(([^)#\s]+)(#[^)]*)?\)")


def _leaf_keys(model, prefix=""):
    from pydantic import BaseModel

    for name, field in model.model_fields.items():
        key = f"{prefix}{field.alias or name}"
        nested = next(
            (a for a in (field.annotation, *getattr(field.annotation, "__args__", ())) if isinstance(a, type)),
            None,
        )
        if nested is not None and issubclass(nested, BaseModel):
            if getattr(field.annotation, "__origin__", None) is dict:
                yield from _leaf_keys(nested, f"{key}.<name>.")
            else:
                yield from _leaf_keys(nested, f"{key}.")
        else:
            yield key


def test_the_params_reference_lists_every_key_with_its_shipped_value():
    from binpick.params import Params
    from flows.docs_reference import params_reference

    page = params_reference()
    missing = [k for k in _leaf_keys(Params) if f"`{k}`" not in page]
    assert not missing, missing
    assert "| `pick.pose_format` | " in page and "`matrix`" in page
    assert "| `service.tcp_port` | integer | `8766` |" in page


def test_the_cli_reference_lists_every_command():
    import typer.main

    from flows.cli import app
    from flows.docs_reference import cli_reference

    page = cli_reference()
    root = typer.main.get_command(app)
    for name, command in root.commands.items():
        subs = getattr(command, "commands", None)
        for path in [f"{name} {s}" for s in subs] if subs else [name]:
            assert f"## `binpick {path}`" in page, path
    assert "| `--out` | path |" in page


def test_the_api_reference_has_the_endpoints():
    from flows.docs_reference import openapi_reference

    page = openapi_reference()
    for path in ("/picks", "/health", "/reload", "/operator/state", "/"):
        assert f"`{path}`" in page, path
    assert '"PicksAnswer"' in page


def test_readme_is_a_quick_start_and_its_links_lead_somewhere():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 150
    for document in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        for target, _ in LINK.findall(document.read_text()):
            if target.startswith(("http://", "https://", "mailto:")):
                continue
            assert (document.parent / target).exists(), f"{document.relative_to(ROOT)}: {target}"
