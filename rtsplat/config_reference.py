"""The configuration reference (``docs/configuration.md``), written from the pipeline's JSON schema.

Every key of ``config.yaml`` with its type, default and description comes from the config dataclasses
(:mod:`rtsplat.config`, the trainer's :mod:`rtsplat.train_config` and the model's settings) through
:func:`rtsplat.config.json_schema`, so the page cannot say anything the schema does not.
``tests/test_config_reference.py`` checks that the committed page is this module's output.

    python -m rtsplat.config_reference --out docs/configuration.md
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from rtsplat.config import json_schema
from rtsplat.errors import run_command
from rtsplat.io.outputs import write_page

OUTPUT = Path(__file__).resolve().parent.parent / "docs" / "configuration.md"
PROGRAM = "python -m rtsplat.config_reference"
COMMAND = PROGRAM + " --out docs/configuration.md"
MARKER = f"Written by `{PROGRAM} "  # in the page's introduction: how --out knows a page of its own
TRAINER_OPTIONS = "defaults.train.options"  # the trainer's config tree inside the pipeline config

INTRO = f"""# Configuration reference

Written by `{COMMAND}`
from the config dataclasses (`rtsplat/config.py`, `rtsplat/train_config.py`, `rtsplat/model/settings.py`):
do not edit by hand. `config.yaml` is checked against the same schema (`workflow/schemas/config.schema.json`)
when the workflow starts; an unknown key or a wrong type is an error that names the key.
How the sections fit together: [the guide](guide/configuration.md).

- `methods.<name>` takes `role` and `of` (below), `budget` (a number > 0 that multiplies every iteration
  count of the method's schedule, e.g. `rtsplat_x4: {{budget: 4}}`) and any key of the trainer's tree
  (`{TRAINER_OPTIONS}`, the same keys), as overrides of that method.
- `overrides.<scene>` takes every key of `defaults`; a scene's settings are the defaults with its
  overrides merged over them.
- `rtsplat train --config FILE` reads a file whose `train:` tree holds the keys of `{TRAINER_OPTIONS}`.
"""


def type_text(schema: dict[str, Any]) -> str:
    """A schema's type in a few words: ``integer``, ``string or null``, ``one of orbit, spiral``, ..."""
    if "anyOf" in schema:
        return " or ".join(type_text(option) for option in schema["anyOf"])
    if "enum" in schema:
        return "one of " + ", ".join(json.dumps(v) for v in schema["enum"])
    kind = schema.get("type")
    if kind == "array":
        items = type_text(schema.get("items", {}))
        count = schema.get("minItems") if schema.get("minItems") == schema.get("maxItems") else None
        return f"list of {count} {items}" if count else f"list of {items}"
    if kind == "object":
        extra = schema.get("additionalProperties")
        if "properties" in schema:
            return "section"
        if isinstance(extra, dict):
            return f"map of name to {type_text(extra)}"
        return "map"
    return kind or "any"


def _limits(schema: dict[str, Any]) -> str:
    words = {"minimum": ">=", "maximum": "<=", "exclusiveMinimum": ">", "exclusiveMaximum": "<"}
    return ", ".join(f"{op} {schema[key]}" for key, op in words.items() if key in schema)


def _cell(text: str) -> str:
    """Prose for a Markdown table cell: ``<data>`` stays visible text rather than an HTML tag."""
    return text.replace("&", "&amp;").replace("<", "&lt;").replace("|", "\\|").replace("\n", " ")


def _object_of(schema: dict[str, Any]) -> dict[str, Any] | None:
    """The object schema with properties that ``schema`` is, or allows besides null."""
    if "properties" in schema:
        return schema
    for option in schema.get("anyOf", []):
        if "properties" in option:
            return option
    return None


def sections(schema: dict[str, Any], path: str = "") -> list[tuple[str, str, list[list[str]]]]:
    """(dotted path, description, rows [key, type, default, description]) of every section of ``schema``,
    depth first; ``overrides.<scene>`` (the keys of ``defaults``) is not repeated."""
    obj = _object_of(schema)
    out: list[tuple[str, str, list[list[str]]]] = []
    if obj is None:
        return out
    rows, nested = [], []
    for key, prop in obj["properties"].items():
        limits = _limits(prop) or next((_limits(o) for o in prop.get("anyOf", []) if _limits(o)), "")
        kind = type_text(prop) + (f" ({limits})" if limits else "")
        default = json.dumps(prop["default"]) if "default" in prop else ""
        rows.append([f"`{key}`", kind, f"`{default}`" if default else "", _cell(prop.get("description", ""))])
        child = f"{path}.{key}" if path else key
        if child == "overrides":
            continue
        if _object_of(prop) is not None:
            nested.append((child, prop))
        elif isinstance(prop.get("additionalProperties"), dict) and "properties" in prop["additionalProperties"]:
            nested.append((f"{child}.<name>", prop["additionalProperties"]))
    out.append((path, obj.get("description", ""), rows))
    for child, prop in nested:
        out.extend(sections(prop, child))
    return out


def markdown() -> str:
    """The whole reference page."""
    lines = [INTRO]
    for path, description, rows in sections(json_schema()):
        lines += [f"## `{path}`" if path else "## Top level", ""]
        if description:
            lines += [_cell(description), ""]
        lines += ["| key | type | default | description |", "|---|---|---|---|"]
        lines += ["| " + " | ".join(row) + " |" for row in rows]
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rtsplat.config_reference", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, help="write the page here (default: print it)")
    args = parser.parse_args(argv)
    return run_command("rtsplat.config_reference", lambda: write_page(markdown(), args.out, PROGRAM, MARKER))


if __name__ == "__main__":
    sys.exit(main())
