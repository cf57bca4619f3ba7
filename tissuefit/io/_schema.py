"""The file formats' JSON Schemas (`scene.schema.json`, `stack.schema.json`) and the sentences
their errors become.

Every message names the field (a path such as `layers[0].absorbers[1].mua`), the value, its unit and
the allowed range, in the words of data_spec/; `validate_scene_dict` and `validate_document` prefix the file.
"""

from __future__ import annotations

import functools
import importlib.resources
import json
import math
from collections.abc import Iterable

import jsonschema

SCENE_SCHEMA = "scene.schema.json"
STACK_SCHEMA = "stack.schema.json"


@functools.cache
def _schema_text(name: str = SCENE_SCHEMA) -> str:
    return importlib.resources.files(__package__).joinpath(name).read_text(encoding="utf-8")


def scene_schema() -> dict:
    """The JSON Schema of the scene format (a fresh copy of the package's `scene.schema.json`)."""
    return json.loads(_schema_text())


def stack_schema() -> dict:
    """The JSON Schema of a stack's sidecar (a fresh copy of the package's `stack.schema.json`)."""
    return json.loads(_schema_text(STACK_SCHEMA))


def _finite_type(validator, types, instance, schema):
    """JSON Schema's `type`, plus: numbers must be finite (TOML has nan and inf; JSON has neither).

    +inf passes where the node carries the annotation `x-allow-inf`.
    """
    yield from jsonschema.Draft202012Validator.VALIDATORS["type"](validator, types, instance, schema)
    if isinstance(instance, float) and not math.isfinite(instance):
        if not (instance > 0 and schema.get("x-allow-inf")):
            yield jsonschema.ValidationError("number is not finite", validator="finite")


_Validator = jsonschema.validators.extend(jsonschema.Draft202012Validator, {"type": _finite_type})


@functools.cache
def schema_cached(name: str = SCENE_SCHEMA) -> dict:
    """A schema, parsed once (do not modify; `scene_schema()` returns a copy to keep)."""
    return json.loads(_schema_text(name))


def scene_schema_cached() -> dict:
    """The scene schema, parsed once (do not modify)."""
    return schema_cached(SCENE_SCHEMA)


@functools.cache
def _validator(name: str = SCENE_SCHEMA):
    return _Validator(schema_cached(name))


def _path(parts: Iterable) -> str:
    text = ""
    for part in parts:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text or "(top level)"


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, (str, list, dict)):
        return json.dumps(v)
    return str(v)


def _interval(node: dict) -> str:
    """The allowed interval of a numeric schema node, with its unit, e.g. '[0, inf) 1/cm'."""
    integer = "integer" in _types(node)

    def bound(key):
        return str(int(node[key])) if integer else _value(float(node[key]))

    if "exclusiveMinimum" in node:
        lo = f"({bound('exclusiveMinimum')}"
    elif "minimum" in node:
        lo = f"[{bound('minimum')}"
    else:
        lo = "(-inf"
    if "exclusiveMaximum" in node:
        hi = f"{bound('exclusiveMaximum')})"
    elif "maximum" in node:
        hi = f"{bound('maximum')}]"
    else:
        hi = "inf]" if node.get("x-allow-inf") else "inf)"
    text = f"{lo}, {hi}" + (" (integer)" if integer else "")
    unit = node.get("x-unit", "-")
    return text if unit == "-" else f"{text} {unit}"


def _types(node: dict) -> list[str]:
    t = node.get("type", [])
    return [t] if isinstance(t, str) else list(t)


def _resolve(node, root: dict):
    """Follow local `$ref`s (`#/$defs/...`) in `root` to the node they name."""
    while isinstance(node, dict) and "$ref" in node:
        target = root
        for part in node["$ref"].removeprefix("#/").split("/"):
            target = target[part]
        node = target
    return node


def _key_description(error: jsonschema.ValidationError, key: str, root: dict) -> str:
    """The description of property `key` for a `required` error: taken from the nearest schema node on
    the error's schema path that declares the property (a kind branch or rule has none of its own)."""
    node, chain = root, []
    for part in list(error.absolute_schema_path)[:-1]:
        if isinstance(node, dict) and part not in node:
            node = _resolve(node, root)  # the path steps through $refs without naming them
        try:
            node = node[part]
        except (KeyError, IndexError, TypeError):
            break
        chain.append(node)
    for candidate in reversed(chain):
        candidate = _resolve(candidate, root)
        props = candidate.get("properties", {}) if isinstance(candidate, dict) else {}
        entry = _resolve(props.get(key), root)
        if isinstance(entry, dict) and entry.get("description"):
            return entry["description"]
    return ""


def _describe(error: jsonschema.ValidationError, root: dict) -> str:
    """One human sentence for a schema error: field path, value, unit and allowed range."""
    where = _path(error.absolute_path)
    node, value, kind = error.schema, error.instance, error.validator
    if kind == "finite" and math.isnan(value):
        return f"{where} = nan is not a number; allowed {_interval(node)}"
    if kind in ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum", "finite"):
        return f"{where} = {_value(value)} is out of range; allowed {_interval(node)}"
    if kind == "type":
        expected = " or ".join({"number": "a number", "integer": "an integer", "string": "a string",
                                "boolean": "true or false", "array": "a list", "object": "a table"}.get(t, t)
                               for t in _types(node))
        detail = f"; allowed {_interval(node)}" if {"number", "integer"} & set(_types(node)) else ""
        return f"{where} = {_value(value)} has the wrong type; expected {expected}{detail}"
    if kind == "required":
        missing = [k for k in error.validator_value if k not in value]
        parts = []
        for key in missing:
            description = _key_description(error, key, root)
            parts.append(f"{key!r}" + (f" ({description.rstrip('.')})" if description else ""))
        return f"{where}: missing required key {', '.join(parts)}"
    if kind == "additionalProperties":
        allowed = list(node.get("properties", {}))
        extra = [k for k in value if k not in allowed]
        return f"{where}: unknown key {', '.join(map(repr, extra))}; allowed keys: {', '.join(allowed)}"
    if kind in ("enum", "const"):
        options = error.validator_value if kind == "enum" else [error.validator_value]
        return f"{where} = {_value(value)} is not allowed; allowed: {', '.join(_value(o) for o in options)}"
    if kind == "not" and "x-forbidden" in node:
        return f"{where} = {_value(value)} is not allowed; {node['x-forbidden']}"
    if kind == "pattern" and node.get("x-allow-inf"):
        return f'{where} = {_value(value)} is not allowed; allowed a number in {_interval(node)} or "inf"'
    if kind == "pattern":
        return f"{where} = {_value(value)} does not match the pattern {node.get('pattern')}"
    if kind == "minItems":
        return f"{where}: needs at least {error.validator_value} entries, found {len(value)}"
    if kind == "maxItems":
        return f"{where}: allows at most {error.validator_value} entries, found {len(value)}"
    if kind == "uniqueItems":
        return f"{where}: entries must be unique; found {_value(value)}"
    if kind == "minLength":
        return f"{where}: must not be empty"
    return f"{where}: {error.message}"


def validate_document(doc: dict, *, schema: str, source_file: str) -> None:
    """Raise `ValueError` listing every violation of `doc` against the package's schema file `schema`,
    one line each, prefixed by the file.

    Errors come in the schema's order (fields as data_spec/ lists them); duplicates are dropped.
    """
    root = schema_cached(schema)
    messages = list(dict.fromkeys(_describe(e, root) for e in _validator(schema).iter_errors(doc)))
    if messages:
        raise ValueError("\n".join(f"{source_file}: {m}" for m in messages))


def validate_scene_dict(doc: dict, *, source_file: str) -> None:
    """`validate_document` against the scene schema (data_spec/scene.md)."""
    validate_document(doc, schema=SCENE_SCHEMA, source_file=source_file)
