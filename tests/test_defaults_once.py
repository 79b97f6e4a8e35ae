"""Each default is written once (docs/ARCHITECTURE.md §4a): a settings model's default, the default town
and policy, the agent concurrency and the dataset's capture spacing are never typed again as a literal
default elsewhere in the package, and the roles and difficulties are spelled out only in their home.

A scan of the package's syntax trees. What counts as a default: a parameter's default, an argparse
``default=`` (or a ``set_defaults`` keyword) and a module-level constant. Any other use of the same
literal (a comparison, a call's argument, a docstring) is not a default and is left alone.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

from pydantic import BaseModel

from agos.deploy.dataset import DEFAULT_CAPTURE_EVERY_M
from agos.deploy.run.children import AGENT_CONCURRENCY
from agos.runtime.keys import ROLES
from agos.runtime.schemas import DIFFICULTIES
from agos.runtime.settings import DEFAULTS, AgosConfig

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ("runtime", "world", "agents", "evaluator", "deploy", "agos")

GENERIC = {"all", "jpeg", "none", "normal", "off", "record"}
"""Setting values that are ordinary words with other meanings elsewhere: matched only by name (below)."""

NAMED: dict[str, object] = {
    "agent_wait_s": DEFAULTS.run.agent_wait_s, "max_infra_attempts": DEFAULTS.run.max_infra_attempts,
    "infra_wait_s": DEFAULTS.run.infra_wait_s, "reconnect_grace_s": DEFAULTS.run.reconnect_grace_s,
    "timeout_s": DEFAULTS.vlm.timeout_s, "max_retries": DEFAULTS.vlm.max_retries,
    "max_tokens": DEFAULTS.vlm.max_tokens, "reasks": DEFAULTS.vlm.reasks, "images": DEFAULTS.vlm.images,
    "cache_mode": DEFAULTS.vlm.cache_mode, "rgb_encoding": DEFAULTS.world.cameras.rgb_encoding,
    "capture_every_m": DEFAULT_CAPTURE_EVERY_M,
}
"""Defaults matched by the name they are given under as well as their value (numbers and ordinary words
are too common to match on the value alone). A name matches without its unit suffix (``--agent-wait``)."""
NAMED_TWICE = {"concurrency": (DEFAULTS.vlm.concurrency, AGENT_CONCURRENCY)}
"""Names with two defaults: the VLM client's requests in flight and the agent service's decisions."""

HOMES = {("runtime/settings.py", "DEFAULT_TOWN"), ("runtime/settings.py", "DEFAULT_POLICY"),
         ("runtime/episode_config.py", "DEFAULT_LOOK"), ("deploy/run/children.py", "AGENT_CONCURRENCY"),
         ("deploy/dataset/__init__.py", "DEFAULT_CAPTURE_EVERY_M")}
"""The one place each constant is written (module, name)."""


def _setting_strings(model: BaseModel, out: set[str]) -> set[str]:
    """The distinctive string defaults of ``model`` and its sections, walked through their values."""
    for name in type(model).model_fields:
        value = getattr(model, name)
        if isinstance(value, BaseModel):
            _setting_strings(value, out)
        elif isinstance(value, str) and len(value) > 2 and value not in GENERIC:
            out.add(value)
    return out


STRINGS = _setting_strings(AgosConfig(), set())


def _bare(name: str) -> str:
    name = name.lstrip("-").replace("-", "_").lower()
    for unit in ("_s", "_m"):
        name = name.removesuffix(unit)
    return name


def _literal(node: ast.expr | None) -> object:
    if isinstance(node, ast.Constant) and not isinstance(node.value, bool) and node.value is not None:
        return node.value
    return None


def _defaults(tree: ast.Module) -> Iterator[tuple[str, ast.expr]]:
    """(name, default expression) of every parameter, argparse default and module-level constant."""
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            args = node.args
            positional = [*args.posonlyargs, *args.args]
            yield from zip((a.arg for a in positional[len(positional) - len(args.defaults):]), args.defaults, strict=True)
            yield from ((a.arg, d) for a, d in zip(args.kwonlyargs, args.kw_defaults, strict=True) if d is not None)
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            if node.func.attr == "set_defaults":
                yield from ((k.arg, k.value) for k in node.keywords if k.arg)
            elif node.func.attr == "add_argument":
                dest = next((k.value.value for k in node.keywords
                             if k.arg == "dest" and isinstance(k.value, ast.Constant)), None)
                flags = [a.value for a in node.args if isinstance(a, ast.Constant) and isinstance(a.value, str)]
                name = dest or next((f for f in flags if f.startswith("--")), flags[0] if flags else "")
                yield from ((str(name), k.value) for k in node.keywords if k.arg == "default")
    for stmt in tree.body:
        if isinstance(stmt, ast.Assign):
            yield from ((t.id, stmt.value) for t in stmt.targets if isinstance(t, ast.Name))
        elif isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name) and stmt.value is not None:
            yield stmt.target.id, stmt.value


def _sources() -> Iterator[tuple[str, ast.Module]]:
    for folder in PACKAGE:
        for path in sorted((ROOT / folder).rglob("*.py")):
            yield path.relative_to(ROOT).as_posix(), ast.parse(path.read_text(encoding="utf-8"), filename=str(path))


def _retyped(name: str, value: object) -> bool:
    if isinstance(value, str) and value in STRINGS:
        return True
    bare = _bare(name)
    named = {_bare(k): (v,) for k, v in NAMED.items()} | NAMED_TWICE
    return any(value == v for v in named.get(bare, ()))


def test_a_default_is_written_once() -> None:
    found, homes = [], set()
    for module, tree in _sources():
        for name, node in _defaults(tree):
            value = _literal(node)
            if value is not None and (module, name) in HOMES:
                homes.add((module, name))
            elif value is not None and _retyped(name, value):
                found.append(f"{module}:{node.lineno}: {name} = {value!r}")
    assert not found, "defaults written again (take them from runtime/settings.py's DEFAULTS or the constant):\n" + \
        "\n".join(found)
    assert homes == HOMES  # each home still holds its constant, so the allowances above cannot rot


def _spelled(node: ast.AST, words: tuple[str, ...]) -> bool:
    """``node`` is a tuple or list literal of exactly ``words``, in order."""
    return isinstance(node, (ast.Tuple, ast.List)) and [_literal(e) for e in node.elts] == list(words)


def test_roles_and_difficulties_are_spelled_out_at_home_only() -> None:
    homes = {ROLES: "runtime/keys.py", DIFFICULTIES: "runtime/schemas.py"}
    found = [f"{module}:{getattr(node, 'lineno', '?')}: {list(words)}"
             for module, tree in _sources() for node in ast.walk(tree)
             for words, home in homes.items() if module != home and _spelled(node, words)]
    assert not found, "import ROLES (runtime/keys.py) or DIFFICULTIES (runtime/schemas.py) instead:\n" + "\n".join(found)


def test_the_scan_sees_defaults() -> None:
    """The scan finds a default of each kind it looks for (a scan that finds nothing passes everything)."""
    tree = ast.parse('T = "grid-s7"\ndef f(reconnect_grace_s=10.0): ...\np.add_argument("--agent-wait", default=30.0)\n'
                     'p.add_argument("--concurrency", default=32)\n')
    assert {name for name, node in _defaults(tree) if _retyped(name, _literal(node))} == \
        {"reconnect_grace_s", "--agent-wait", "--concurrency", "T"}
    assert not _retyped("decision_timeout_s", 10.0) and not _retyped("which", "all")
    assert _spelled(ast.parse('("uav", "ugv")', mode="eval").body, ROLES)
