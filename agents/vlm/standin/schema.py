"""The JSON Schema subset a strict ``response_format`` may use with the stand-in, and whether a reply
conforms to it.

A real endpoint with structured outputs either constrains its answer to the caller's schema or refuses
the request; it never answers with something else. The stand-in cannot bend its responder's answer to
an arbitrary schema, so for a strict ``json_schema`` it checks the schema's keywords when the request
arrives (:func:`check_schema`: an unknown keyword is refused, as OpenAI refuses what its strict mode
does not support) and the responder's answer before it is sent (:func:`violation`): an answer that
does not conform is refused with a 400 saying where it fails, never sent.

The subset is what OpenAI's strict mode accepts: ``type`` (one or a list), ``enum``, ``const``,
``properties``, ``required``, ``additionalProperties``, ``items``, ``anyOf``/``oneOf``/``allOf``,
``$ref`` into ``$defs``/``definitions``, ``pattern``, ``minLength``/``maxLength``,
``minimum``/``maximum``/``exclusiveMinimum``/``exclusiveMaximum``, ``minItems``/``maxItems``; and the
annotations ``title``, ``description``, ``default``, ``examples``, ``format``, ``$schema``, ``$id``,
``$comment`` (not checked).
"""

from __future__ import annotations

import math
import re
from typing import Any

CHECKED = frozenset({"type", "enum", "const", "properties", "required", "additionalProperties", "items", "anyOf", "oneOf",
                     "allOf", "$ref", "$defs", "definitions", "pattern", "minLength", "maxLength", "minimum", "maximum",
                     "exclusiveMinimum", "exclusiveMaximum", "minItems", "maxItems"})
ANNOTATIONS = frozenset({"title", "description", "default", "examples", "format", "$schema", "$id", "$comment"})
TYPES = frozenset({"object", "array", "string", "number", "integer", "boolean", "null"})


class SchemaError(ValueError):
    """A schema outside the subset (or not a schema); the message names the place and the keyword."""


def check_schema(schema: Any, where: str = "schema") -> None:
    """Raise :class:`SchemaError` unless ``schema`` uses only the subset's keywords, well typed."""
    if isinstance(schema, bool):
        return
    if not isinstance(schema, dict):
        raise SchemaError(f"{where} must be an object, not {type(schema).__name__}")
    for key, value in schema.items():
        here = f"{where}.{key}"
        if key in ANNOTATIONS:
            continue
        if key not in CHECKED:
            raise SchemaError(f"{here}: keyword {key!r} is not supported by agos vlm-standin's strict mode "
                              f"(supported: {', '.join(sorted(CHECKED))})")
        if key == "type":
            names = value if isinstance(value, list) else [value]
            if not names or any(n not in TYPES for n in names):
                raise SchemaError(f"{here}: {value!r} is not a JSON type (or a list of them)")
        elif key in ("properties", "$defs", "definitions"):
            if not isinstance(value, dict):
                raise SchemaError(f"{here} must be an object")
            for name, sub in value.items():
                check_schema(sub, f"{here}.{name}")
        elif key in ("items", "additionalProperties"):
            check_schema(value, here)
        elif key in ("anyOf", "oneOf", "allOf"):
            if not isinstance(value, list) or not value:
                raise SchemaError(f"{here} must be a non-empty list of schemas")
            for i, sub in enumerate(value):
                check_schema(sub, f"{here}[{i}]")
        elif key in ("required", "enum"):
            if not isinstance(value, list) or (key == "required" and not all(isinstance(v, str) for v in value)):
                raise SchemaError(f"{here} must be a list" + (" of property names" if key == "required" else ""))
        elif key == "$ref":
            if not isinstance(value, str) or not re.fullmatch(r"#/(\$defs|definitions)/[^/]+", value):
                raise SchemaError(f"{here}: only references into #/$defs or #/definitions are supported, not {value!r}")
        elif key == "pattern":
            try:
                re.compile(value)
            except (re.error, TypeError) as exc:
                raise SchemaError(f"{here}: not a regular expression ({exc})") from None
        elif key != "const" and (not isinstance(value, int | float) or isinstance(value, bool)):
            raise SchemaError(f"{here} must be a number")


def _is_type(value: Any, name: str) -> bool:
    if name == "null":
        return value is None
    if name == "boolean":
        return isinstance(value, bool)
    if name == "integer":
        return (isinstance(value, int) and not isinstance(value, bool)) or (isinstance(value, float) and value.is_integer())
    if name == "number":
        return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    return isinstance(value, {"string": str, "array": list, "object": dict}[name])


def _equal(a: Any, b: Any) -> bool:
    """JSON equality: 1 == 1.0, but True != 1."""
    if isinstance(a, bool) or isinstance(b, bool):
        return isinstance(a, bool) and isinstance(b, bool) and a == b
    return bool(a == b)


def violation(value: Any, schema: Any, root: Any = None, where: str = "$") -> str | None:
    """None when ``value`` conforms to ``schema`` (checked with :func:`check_schema` before), else where
    and why it does not, e.g. ``$.action: 'GO' is not one of ['WAIT']``."""
    root = schema if root is None else root
    if schema is True:
        return None
    if schema is False:
        return f"{where}: no value is allowed here"
    if "$ref" in schema:
        _, section, name = schema["$ref"].split("/", 2)
        target = root.get(section, {}).get(name)
        if target is None:
            return f"{where}: the reference {schema['$ref']} names nothing"
        problem = violation(value, target, root, where)
        if problem:
            return problem
    if "type" in schema:
        names = schema["type"] if isinstance(schema["type"], list) else [schema["type"]]
        if not any(_is_type(value, n) for n in names):
            return f"{where}: {value!r} is not of type {' or '.join(names)}"
    if "enum" in schema and not any(_equal(value, option) for option in schema["enum"]):
        return f"{where}: {value!r} is not one of {schema['enum']!r}"
    if "const" in schema and not _equal(value, schema["const"]):
        return f"{where}: {value!r} is not {schema['const']!r}"
    for key in ("allOf", "anyOf", "oneOf"):
        if key in schema:
            problems = [violation(value, sub, root, where) for sub in schema[key]]
            passed = sum(p is None for p in problems)
            if key == "allOf" and passed < len(problems):
                return next(p for p in problems if p)
            if key == "anyOf" and not passed:
                return f"{where}: matches none of anyOf ({problems[0]})"
            if key == "oneOf" and passed != 1:
                return f"{where}: matches {passed} of oneOf's schemas, not exactly one"
    if isinstance(value, str):
        if "pattern" in schema and not re.search(schema["pattern"], value):
            return f"{where}: {value!r} does not match {schema['pattern']!r}"
        if len(value) < schema.get("minLength", 0) or len(value) > schema.get("maxLength", math.inf):
            return f"{where}: a string of {len(value)} characters is outside its length bounds"
    low, high = schema.get("minimum", -math.inf), schema.get("maximum", math.inf)
    above, below = schema.get("exclusiveMinimum", -math.inf), schema.get("exclusiveMaximum", math.inf)
    if _is_type(value, "number") and not (low <= value <= high and above < value < below):
        return f"{where}: {value!r} is outside its bounds"
    if isinstance(value, list):
        if len(value) < schema.get("minItems", 0) or len(value) > schema.get("maxItems", math.inf):
            return f"{where}: a list of {len(value)} items is outside its length bounds"
        if "items" in schema:
            for i, item in enumerate(value):
                problem = violation(item, schema["items"], root, f"{where}[{i}]")
                if problem:
                    return problem
    if isinstance(value, dict):
        missing = [name for name in schema.get("required", []) if name not in value]
        if missing:
            return f"{where}: required {', '.join(map(repr, missing))} missing"
        properties = schema.get("properties", {})
        extra = schema.get("additionalProperties", True)
        for name, item in value.items():
            sub = properties.get(name, extra)
            problem = violation(item, sub, root, f"{where}.{name}")
            if problem:
                return (f"{where}: property {name!r} is not allowed" if sub is False else problem)
    return None
