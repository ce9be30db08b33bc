"""The documentation's reference pages, generated from the code so that they cannot drift from it:
params.yaml section by section (from the typed params models, with the shipped values and their
comments), the `binpick` command line (from the Typer app) and the pick service's OpenAPI schema.
docs/hooks.py puts them into the pages at `mkdocs build`."""

from __future__ import annotations

import json
import types
import typing
from pathlib import Path
from typing import Any

from pydantic import BaseModel

ROOT = Path(__file__).resolve().parent.parent


def _type_name(annotation: Any) -> str:
    """A field's type as a reader of params.yaml thinks of it."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Literal:
        return " \\| ".join(json.dumps(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        return " \\| ".join("null" if a is type(None) else _type_name(a) for a in args)
    if origin is list:
        return f"list of {_type_name(args[0])}" if args else "list"
    if origin is tuple:
        return f"list of {len(args)} {_type_name(args[0])}s" if args and args[-1] is not Ellipsis else "list"
    if annotation is typing.Any:
        return "any"
    if annotation is Path:
        return "path"
    if origin is dict:
        return f"map of {_type_name(args[1])}" if len(args) == 2 else "map"
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return "section"
    return {int: "integer", float: "number", str: "text", bool: "true \\| false"}.get(annotation, str(annotation))


def _comment(node: Any, key: str) -> str:
    """The end-of-line comment after `key` in the shipped params.yaml (ruamel keeps them)."""
    items = getattr(getattr(node, "ca", None), "items", {})
    token = (items.get(key) or [None, None, None])[2]
    if token is None:
        return ""
    return token.value.strip().splitlines()[0].lstrip("#").strip() if token.value.strip() else ""


def _cell(text: Any) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _short(value: Any) -> str:
    if isinstance(value, dict | list):
        text = json.dumps(value, default=str)
    elif value is None:
        text = "null"
    else:
        text = str(value)
    return f"`{text}`" if len(text) <= 60 else f"`{text[:57]}...`"


def _model(cls: type[BaseModel], shipped: Any, prefix: str, rows: list[str]) -> None:
    for name, field in cls.model_fields.items():
        key = field.alias or name
        path = f"{prefix}{key}"
        annotation = field.annotation
        value = shipped.get(key) if hasattr(shipped, "get") else None
        nested = _nested_model(annotation)
        described = field.description or ""
        comment = _comment(shipped, key) if hasattr(shipped, "get") else ""
        text = described or comment
        if nested is not None and typing.get_origin(annotation) is dict:
            rows.append(f"| `{path}` | map of entries | | {_cell(text or (nested.__doc__ or '').strip())} |")
            _model(nested, None, f"{path}.<name>.", rows)
        elif nested is not None:
            doc = (nested.__doc__ or "").strip().split("\n\n")[0]
            rows.append(f"| `{path}` | section | | {_cell(text or doc)} |")
            _model(nested, value, f"{path}.", rows)
        else:
            shown = _short(value) if value is not None or (hasattr(shipped, "get") and key in shipped) else ""
            rows.append(f"| `{path}` | {_type_name(annotation)} | {_cell(shown)} | {_cell(text)} |")


def _nested_model(annotation: Any) -> type[BaseModel] | None:
    """The params model a field holds (itself, optional, or as the values of a map)."""
    candidates = [annotation, *typing.get_args(annotation)]
    for c in candidates:
        if isinstance(c, type) and issubclass(c, BaseModel):
            return c
    return None


def params_reference(params_path: Path = ROOT / "params.yaml") -> str:
    """Markdown: every section of params.yaml with every key, its type, the shipped value, what it means."""
    from ruamel.yaml import YAML

    from binpick.params import Params

    shipped = YAML().load(Path(params_path).read_text())
    out = []
    for name, field in Params.model_fields.items():
        key = field.alias or name
        cls = _nested_model(field.annotation)
        out.append(f"## `{key}`\n")
        comment = _comment(shipped, key)
        if cls is None:
            out += [
                f"{_type_name(field.annotation)}; in params.yaml: {_short(shipped.get(key))}. "
                f"{field.description or comment}\n"
            ]
            continue
        doc = " ".join((cls.__doc__ or "").split())
        out.append(f"{doc} {comment}".strip() + "\n")
        rows = ["| key | type | params.yaml | meaning |", "|---|---|---|---|"]
        if typing.get_origin(field.annotation) is dict:
            _model(cls, None, f"{key}.<name>.", rows)
        else:
            _model(cls, shipped.get(key), f"{key}.", rows)
        out += ["\n".join(rows), ""]
    return "\n".join(out)


def cli_reference() -> str:
    """Markdown: every `binpick` command with its help and options, from the Typer app."""
    import typer.main

    from flows.cli import app

    root = typer.main.get_command(app)
    out: list[str] = []

    # Typer builds on a click of its own: commands and parameters are read by what they have.
    def walk(command: Any, path: list[str]) -> None:
        commands = getattr(command, "commands", None)
        if commands is not None:
            for name in sorted(commands) if path else list(commands):
                walk(commands[name], [*path, name])
            return
        out.append(f"## `binpick {' '.join(path)}`\n")
        out.append(" ".join((command.help or "").split()) + "\n")
        rows = []
        for p in command.params:
            if p.name == "help":
                continue
            annotation = getattr(getattr(p, "type_descriptor", None), "annotation", None)
            kind = _type_name(annotation).replace("<class 'pathlib.Path'>", "path") if annotation else ""
            if "Argument" in type(p).__name__:
                rows.append(f"| `{p.name.upper()}` | {kind} (argument) | | {_cell(p.help or '')} |")
                continue
            names = ", ".join(f"`{n}`" for n in [*p.opts, *p.secondary_opts])
            default = "" if p.default is None or p.default is False else _short(p.default)
            rows.append(f"| {names} | {_cell(kind)} | {_cell(default)} | {_cell(p.help or '')} |")
        if rows:
            out.append("| option | type | default | meaning |\n|---|---|---|---|\n" + "\n".join(rows) + "\n")

    walk(root, [])
    return "\n".join(out)


def openapi_reference() -> str:
    """Markdown: the pick service's endpoints and the full OpenAPI schema (JSON)."""
    from flows.service_http import openapi_schema

    schema = openapi_schema()
    rows = ["| method | path | what |", "|---|---|---|"]
    for path, methods in schema["paths"].items():
        for method, op in methods.items():
            rows.append(f"| {method.upper()} | `{path}` | {_cell(op.get('summary', ''))} |")
    return "\n".join(rows) + "\n\n```json\n" + json.dumps(schema, indent=1) + "\n```\n"
