"""docs/configuration.md is the configuration reference generated from the config schema."""

from __future__ import annotations

import copy

from rtsplat.config import json_schema
from rtsplat.config_reference import COMMAND, OUTPUT, markdown, sections


def test_committed_reference_is_the_generated_one():
    assert OUTPUT.read_text() == markdown(), f"docs/configuration.md is out of date: run `{COMMAND}`"


def _leaves(schema, path=""):
    """Dotted paths of every key of the schema that the reference must list (overrides.<scene> aside)."""
    obj = schema if "properties" in schema else next((o for o in schema.get("anyOf", []) if "properties" in o), None)
    if obj is None:
        return
    for key, prop in obj["properties"].items():
        child = f"{path}.{key}" if path else key
        yield child
        if child != "overrides":
            yield from _leaves(prop, child)
            extra = prop.get("additionalProperties")
            if isinstance(extra, dict):
                yield from _leaves(extra, f"{child}.<name>")


def test_every_schema_key_has_a_row_with_its_default_and_description():
    schema = json_schema()
    rows = {}
    for path, _, table in sections(schema):
        for key, kind, default, description in table:
            rows[f"{path}.{key.strip('`')}" if path else key.strip("`")] = (kind, default, description)
    keys = list(_leaves(schema))
    assert len(keys) > 200  # the trainer's tree is in it, not only the pipeline's top sections
    assert set(keys) == set(rows)
    prepare = schema["properties"]["defaults"]["properties"]["prepare"]["properties"]
    kind, default, description = rows["defaults.prepare.test_every"]
    assert default == f"`{prepare['test_every']['default']}`" and kind.startswith("integer")
    assert description == prepare["test_every"]["description"].replace("<", "&lt;")


def test_a_new_key_shows_up_in_the_reference():
    schema = copy.deepcopy(json_schema())
    schema["properties"]["slurm"]["properties"]["qos"] = {"type": "string", "default": "normal",
                                                           "description": "the jobs' quality of service"}
    rows = dict((path, table) for path, _, table in sections(schema))
    assert ["`qos`", "string", '`"normal"`', "the jobs' quality of service"] in rows["slurm"]
