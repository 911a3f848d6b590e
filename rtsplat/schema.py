"""Settings as dataclasses: one mechanism for every config tree of the project.

A field made with :func:`setting` carries its help text and extra JSON-schema keywords (``minimum``,
``maxItems``, ...). From the dataclasses :func:`dataclass_schema` generates a JSON schema;
:func:`check` validates a parsed YAML/JSON dict against it and raises one
:class:`~rtsplat.errors.ConfigError` whose lines name each wrong key (``train.schedule.iteratons``)
and the fix; :func:`build` turns a checked dict into the dataclasses. The pipeline config
(:mod:`rtsplat.config`), the trainer's (:mod:`rtsplat.train_config`), the model's settings
(:mod:`rtsplat.model.settings`) and the rasterizer's (:class:`rtsplat.raster.RasterSettings`) are
built this way. This module imports nothing else from rtsplat but the error type.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import functools
import json
import math
import types
import typing
from collections.abc import Callable, Iterable, Iterator
from dataclasses import field
from typing import Any, Literal

from rtsplat.errors import ConfigError


def setting(default: Any = dataclasses.MISSING, *, help: str, factory: Any = None,
            schema_of: type | Callable[[], type] | None = None, **schema: Any):
    """A dataclass field with a description and extra JSON-schema keywords (minimum, ...).

    ``schema_of``: the value is kept as a dict but must be a (partial) tree of that dataclass
    (e.g. trainer options that are merged before they are built); a function returning the class
    defers its import until a schema is needed."""
    meta = {"description": help, "schema": schema}
    if schema_of is not None:
        meta["schema_of"] = schema_of
    if factory is not None:
        return field(default_factory=factory, metadata=meta)
    return field(default=default, metadata=meta)


# ----------------------------------------------------------------------------------------------
# JSON schema generated from the dataclasses


def type_schema(tp: Any) -> dict[str, Any]:
    """The JSON schema of a type annotation (dataclasses, unions with None, Literal, list, tuple, dict)."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        return dataclass_schema(tp)
    if origin in (typing.Union, types.UnionType):
        non_null = [a for a in args if a is not type(None)]
        options = [type_schema(a) for a in non_null]
        if len(non_null) < len(args):
            options.append({"type": "null"})
        return options[0] if len(options) == 1 else {"anyOf": options}
    if origin is Literal:
        kinds = {bool: "boolean", int: "integer", str: "string", float: "number"}
        return {"type": kinds[type(args[0])], "enum": list(args)}
    if origin is list:
        return {"type": "array", "items": type_schema(args[0])}
    if origin is tuple:
        if len(set(args)) != 1:
            raise TypeError(f"no JSON schema for type {tp!r} (only tuples of one element type)")
        return {"type": "array", "items": type_schema(args[0]), "minItems": len(args), "maxItems": len(args)}
    if origin is dict:
        value = args[1]
        return {"type": "object", "additionalProperties": True if value is Any else type_schema(value)}
    if tp is bool:
        return {"type": "boolean"}
    if tp is int:
        return {"type": "integer"}
    if tp is float:
        return {"type": "number"}
    if tp is str:
        return {"type": "string"}
    if tp is Any:
        return {}
    raise TypeError(f"no JSON schema for type {tp!r}")


def dataclass_schema(cls: type) -> dict[str, Any]:
    """The JSON schema of a dataclass: one property per field with its description, default and
    keywords; unknown keys are not allowed; no key is required (defaults fill them in)."""
    return copy.deepcopy(_cached_schema(cls))


@functools.cache
def _cached_schema(cls: type) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    props = {}
    for f in dataclasses.fields(cls):
        if "schema_of" in f.metadata:
            target = f.metadata["schema_of"]
            schema = dataclass_schema(target if isinstance(target, type) else target())
            schema.pop("description", None)
        else:
            schema = type_schema(hints[f.name])
        extra = dict(f.metadata.get("schema", {}))
        if extra and "anyOf" in schema:  # constraints apply to the non-null alternative
            schema["anyOf"][0].update(extra)
        else:
            schema.update(extra)
        schema["description"] = f.metadata.get("description", "")
        if f.default is not dataclasses.MISSING and not dataclasses.is_dataclass(f.default):
            schema["default"] = plain(f.default)
        props[f.name] = schema
    return {
        "type": "object",
        "description": (cls.__doc__ or "").strip().splitlines()[0],
        "properties": props,
        "additionalProperties": False,
    }


def plain(value: Any) -> Any:
    """``value`` as JSON data (dataclasses to dicts, tuples to lists)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    return json.loads(json.dumps(value))


# ----------------------------------------------------------------------------------------------
# validation with readable messages


def _key(path: Iterable[Any]) -> str:
    return ".".join(str(p) for p in path) or "<top level>"


def error_message(error: Any, source: str, root: tuple[str, ...] = ()) -> str:
    """One schema violation as ``<source>: config key '<key>' ... Fix: ...``; keys start with ``root``."""
    path = [*root, *error.absolute_path]
    where = _key(path)
    if error.validator == "anyOf" and error.instance is not None and error.context:
        # "X or null": report what is wrong inside X rather than "not X or null"
        inner = [e for e in error.context if e.relative_schema_path[0] == 0]
        if inner:
            return "\n".join(error_message(e, source, root) for e in inner)
    if error.validator == "additionalProperties":
        allowed = sorted(error.schema.get("properties", {}))
        unknown = sorted(set(error.instance) - set(allowed))
        lines = []
        for key in unknown:
            full = f"{where}.{key}" if path else key
            close = difflib.get_close_matches(key, allowed, n=1)
            hint = f"did you mean '{close[0]}'? " if close else ""
            lines.append(
                f"{source}: config key '{full}' does not exist. Fix: {hint}remove or rename it; "
                f"valid keys under '{where}': {', '.join(allowed)}"
            )
        return "\n".join(lines)
    if error.validator == "enum":
        options = error.validator_value
        return (f"{source}: config key '{where}' is {error.instance!r}. Fix: use one of {options}"
                + _yaml_boolean_hint(error.instance, where, options))
    if error.validator in ("type", "anyOf"):
        kinds = ([error.schema["type"]] if "type" in error.schema
                 else [s.get("type") for s in error.schema.get("anyOf", [])])
        expected = " or ".join(str(k) for k in kinds)
        hint = _yaml_boolean_hint(error.instance, where, error.schema.get("enum", [])) if "string" in kinds else ""
        return f"{source}: config key '{where}' is {error.instance!r}. Fix: it must be of type {expected}{hint}"
    return f"{source}: config key '{where}': {error.message}. Fix: see the description in config.yaml"


YAML_BOOLEANS = {True: ("on", "yes", "true"), False: ("off", "no", "false")}  # what YAML 1.1 reads as booleans


def _yaml_boolean_hint(value: Any, where: str, options) -> str:
    """For a boolean where text is expected: that YAML reads unquoted on/off/yes/no/true/false as booleans,
    and the value quoted (the option among ``options`` that the boolean was probably written as)."""
    if not isinstance(value, bool):
        return ""
    meant = next((word for word in YAML_BOOLEANS[value] if word in options), "the text")
    return (f"; YAML reads an unquoted on, off, yes, no, true or false as a boolean, so write the text in quotes: "
            f"{where.rsplit('.', 1)[-1]}: \"{meant}\"")


@functools.cache
def _validator(cls: type):
    import jsonschema

    return jsonschema.Draft202012Validator(_cached_schema(cls))


def check(cls: type, data: Any, *, source: str = "config", root: str = "") -> None:
    """Raise :class:`ConfigError` listing every problem of ``data`` (a dict tree) as a ``cls``;
    keys in the messages are prefixed with ``root`` (e.g. ``train``)."""
    prefix = tuple(root.split(".")) if root else ()
    data = plain(data)
    non_finite = dict(_non_finite(data, ()))
    lines = [f"{source}: config key '{_key([*prefix, *path])}' is {value!r}. Fix: use a finite number"
             for path, value in non_finite.items()]
    errors = [e for e in _validator(cls).iter_errors(data) if tuple(e.absolute_path) not in non_finite]
    listed = {tuple(e.absolute_path) for e in errors if e.validator == "enum"}  # its options say the type too
    errors = sorted((e for e in errors if e.validator != "type" or tuple(e.absolute_path) not in listed),
                    key=lambda e: list(map(str, e.absolute_path)))
    lines += [error_message(e, source, prefix) for e in errors]
    if lines:
        raise ConfigError("\n".join(lines))


def _non_finite(data: Any, path: tuple) -> Iterator[tuple[tuple, float]]:
    """(key path, value) of every NaN or infinite number in a JSON tree: no setting takes one."""
    if isinstance(data, float) and not math.isfinite(data):
        yield path, data
    elif isinstance(data, dict):
        for key, value in data.items():
            yield from _non_finite(value, (*path, key))
    elif isinstance(data, list):
        for i, value in enumerate(data):
            yield from _non_finite(value, (*path, i))


# ----------------------------------------------------------------------------------------------
# construction


def build(cls: type, data: dict[str, Any]) -> Any:
    """``cls`` from a checked dict tree; missing keys take the field defaults."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        kwargs[f.name] = _convert(hints[f.name], data[f.name])
    return cls(**kwargs)


def _convert(tp: Any, value: Any) -> Any:
    if dataclasses.is_dataclass(tp):
        return build(tp, value or {})
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None:
            return None
        return _convert(next(a for a in args if a is not type(None)), value)
    if origin is dict and dataclasses.is_dataclass(args[1]):
        return dict(value)  # per-scene fragments stay dicts: they are merged, not built
    if origin is tuple:
        return tuple(_convert(a, v) for a, v in zip(args, value, strict=True))
    if tp is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if tp is int and isinstance(value, float):
        return int(value)
    return copy.deepcopy(value)


def from_dict(cls: type, data: dict[str, Any] | None, *, source: str = "config", root: str = "") -> Any:
    """:func:`check` then :func:`build`."""
    data = {} if data is None else data
    check(cls, data, source=source, root=root)
    return build(cls, data)


# ----------------------------------------------------------------------------------------------
# comparison


def differences(old: Any, new: Any, path: tuple = ()) -> Iterator[tuple[str, Any, Any]]:
    """(dotted key, old value, new value) of every leaf where two config trees differ; a key that
    one tree lacks has the value ``"<absent>"`` there. Trees are compared as JSON data (:func:`plain`)."""
    old, new = plain(old), plain(new)
    if isinstance(old, dict) and isinstance(new, dict):
        for key in [*old, *(k for k in new if k not in old)]:
            yield from differences(old.get(key, "<absent>"), new.get(key, "<absent>"), (*path, key))
    elif old != new:
        yield _key(path), old, new
