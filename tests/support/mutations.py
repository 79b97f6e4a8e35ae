"""Hypothesis strategies that mutate a valid file, for fuzzing the readers of agos's input files.

A mutation is either structural (the parsed document, TOML tables or JSON lines, with values
replaced by values of any type, keys deleted, unknown keys added, lines duplicated, swapped or
dropped; then written out again) or textual (bytes inserted, deleted, replaced, lines duplicated,
the file cut short), one to three steps of either. Structural mutations reach the readers'
validation; textual ones their parsers.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import tomllib
from typing import Any

from hypothesis import strategies as st

_SCALARS = st.one_of(
    st.none(), st.booleans(),
    st.integers(min_value=-(2**63), max_value=2**63 - 1), st.integers(),  # also beyond 64 bits
    st.sampled_from([0, -1, 1, 2**31, 2**64]),
    st.floats(), st.sampled_from([0.0, -0.0, -1.0, 1e-300, 1e300, math.inf, -math.inf, math.nan]),
    st.text(max_size=12), st.sampled_from(["", " ", "a\nb", "\x00", "é", "..", "-rf", "*", "a/b", "R", "R-1", "U0_0"]),
)
VALUES = st.recursive(_SCALARS, lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner,
                                                                                             max_size=3), max_leaves=6)
"""Any JSON-like value, odd ones weighted in."""
TOML_VALUES = st.one_of(VALUES.filter(lambda v: not _has_none(v)),
                        st.datetimes(), st.dates(), st.times())
"""What TOML can hold: no null, but dates and times."""


def _has_none(value: Any) -> bool:
    if value is None:
        return True
    if isinstance(value, list):
        return any(_has_none(v) for v in value)
    if isinstance(value, dict):
        return any(_has_none(v) for v in value.values())
    return False


def _paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    """Every path (keys and list indices) into ``node``, the root's ``()`` included."""
    out = [prefix]
    if isinstance(node, dict):
        for key, value in node.items():
            out += _paths(value, (*prefix, key))
    elif isinstance(node, list):
        for i, value in enumerate(node):
            out += _paths(value, (*prefix, i))
    return out


def _at(node: Any, path: tuple) -> Any:
    for step in path:
        node = node[step]
    return node


def _mutate_tree(draw: st.DrawFn, doc: Any, values: st.SearchStrategy) -> Any:
    """One structural step on a copy of ``doc``: replace a value, delete a key or item, add a key."""
    doc = _copy(doc)
    paths = [p for p in _paths(doc) if p]
    op = draw(st.sampled_from(["replace", "delete", "add"]))
    if op == "add" or not paths:
        tables = [p for p in _paths(doc) if isinstance(_at(doc, p), dict)]
        if not tables:
            return doc
        table = _at(doc, draw(st.sampled_from(tables)))
        known = sorted({str(p[-1]) for p in paths if p and isinstance(p[-1], str)})
        key = draw(st.sampled_from(known) | st.text(max_size=8)) if known else draw(st.text(max_size=8))
        table[key] = draw(values)
        return doc
    path = draw(st.sampled_from(paths))
    parent = _at(doc, path[:-1])
    if op == "delete":
        del parent[path[-1]]
    else:
        parent[path[-1]] = draw(values)
    return doc


def _copy(node: Any) -> Any:
    if isinstance(node, dict):
        return {k: _copy(v) for k, v in node.items()}
    if isinstance(node, list):
        return [_copy(v) for v in node]
    return node


@st.composite
def byte_mutation(draw: st.DrawFn, data: bytes) -> bytes:
    """One to three textual steps on ``data``."""
    for _ in range(draw(st.integers(1, 3))):
        op = draw(st.sampled_from(["insert", "delete", "replace", "line", "cut"]))
        at = draw(st.integers(0, len(data)))
        if op == "insert":
            data = data[:at] + draw(st.binary(min_size=1, max_size=4) | st.sampled_from(
                [b"\n", b"\"", b"[", b"]", b"{", b"}", b"=", b",", b"#", b"\xff", b"\x00", b"\\", b"'''"])) + data[at:]
        elif op == "delete":
            data = data[:at] + data[at + draw(st.integers(1, 16)):]
        elif op == "replace" and data:
            at = min(at, len(data) - 1)
            data = data[:at] + bytes([draw(st.integers(0, 255))]) + data[at + 1:]
        elif op == "line":
            lines = data.split(b"\n")
            i = draw(st.integers(0, len(lines) - 1))
            lines.insert(draw(st.integers(0, len(lines))), lines[i])
            data = b"\n".join(lines)
        else:
            data = data[:at]
    return data


# ----- TOML ------------------------------------------------------------------------------------
def toml_text(doc: dict[str, Any]) -> str:
    """``doc`` as TOML, every table inline (``tomllib.loads`` gives ``doc`` back)."""
    return "".join(f"{_toml_key(k)} = {_toml_value(v)}\n" for k, v in doc.items())


def _toml_key(key: str) -> str:
    return json.dumps(key)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (dt.datetime, dt.date, dt.time)):
        return value.isoformat()
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(type(value))


@st.composite
def toml_mutation(draw: st.DrawFn, text: str) -> bytes:
    """A mutated copy of a valid TOML file, as bytes."""
    if draw(st.booleans()):
        return draw(byte_mutation(text.encode()))
    doc: Any = tomllib.loads(text)
    for _ in range(draw(st.integers(1, 3))):
        doc = _mutate_tree(draw, doc, TOML_VALUES)
    return toml_text(doc).encode() if isinstance(doc, dict) else b""


# ----- JSON lines ------------------------------------------------------------------------------
@st.composite
def jsonl_mutation(draw: st.DrawFn, lines: list[dict[str, Any]]) -> bytes:
    """A mutated copy of a JSONL file of ``lines`` (one object each), as bytes."""
    text = "".join(json.dumps(line) + "\n" for line in lines).encode()
    if draw(st.booleans()):
        return draw(byte_mutation(text))
    doc: list[Any] = json.loads(json.dumps(lines))
    for _ in range(draw(st.integers(1, 3))):
        op = draw(st.sampled_from(["tree", "tree", "tree", "duplicate", "swap", "drop"]))
        i, j = draw(st.integers(0, len(doc) - 1)) if doc else 0, draw(st.integers(0, len(doc) - 1)) if doc else 0
        if op == "tree" or not doc:
            doc = _mutate_tree(draw, doc, VALUES)
            if not isinstance(doc, list):
                doc = [doc]
        elif op == "duplicate":
            doc.insert(j, json.loads(json.dumps(doc[i])))
        elif op == "swap":
            doc[i], doc[j] = doc[j], doc[i]
        else:
            del doc[i]
    return "".join(json.dumps(line) + "\n" for line in doc).encode()
