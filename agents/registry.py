"""The policy registry: a policy name (see :mod:`agos.agents.names`) to a policy object for one role.

Three kinds of names, each resolved lazily, so a process imports just the policy it serves:

* agos's own (``heuristic``, ``oracle``, ``agos-agent`` ...): the table of builders below, each
  importing its policy's module only when called;
* ``package.module:Class``: a :class:`~agos.agents.contract.Policy` subclass of your own, imported
  when the policy is built; the module is looked up on the Python path and then in the current
  folder (so ``examples.my_policy:Explorer`` works from the repository root, even through the
  ``agos`` script, whose own folder is not the current one);
* a name another installed package registers in the ``agos.policies`` entry-point group, e.g. in
  its pyproject.toml ``[project.entry-points."agos.policies"] my-agent = "my_pkg.agent:MyAgent"``.

Classes of one's own are built with ``Class.from_settings(role, vlm=...)`` (default ``Class(role)``).
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
from collections.abc import Callable
from importlib.metadata import entry_points
from pathlib import Path
from types import ModuleType

from agos.agents.contract import Policy
from agos.agents.names import ENTRY_POINT_GROUP, VLM_POLICIES, is_builtin, is_class_spec, parse_standin, split_name
from agos.runtime.schemas import Role
from agos.runtime.settings import VlmOptions

Builder = Callable[[Role, str, VlmOptions | None], Policy]
"""Builds one of agos's own policies: (role, the full policy name, the ``[vlm]`` settings or None)."""
_BUILDERS: dict[str, Builder] = {}


def _builds(*bases: str) -> Callable[[Builder], Builder]:
    """Register a builder of agos's own policies under the base names ``bases``."""

    def register(builder: Builder) -> Builder:
        for base in bases:
            _BUILDERS[base] = builder
        return builder

    return register


@_builds(*VLM_POLICIES)
def _vlm(role: Role, name: str, vlm: VlmOptions | None) -> Policy:
    if vlm is None or not vlm.model or not (vlm.base_url or vlm.replaying):  # a replay needs no endpoint
        raise ValueError(f"policy {name!r} asks a VLM: give --vlm-base-url URL and --model NAME "
                         "(offline: start `agos vlm-standin` and use its URL)")
    from agos.agents.vlm.agent import VlmAgent

    return VlmAgent(role, name, vlm)


@_builds("heuristic", "paint-only")
def _heuristic(role: Role, name: str, vlm: VlmOptions | None) -> Policy:
    """``paint-only``: the heuristic with every cue but the paint switched off, one cue's floor."""
    from agos.agents.heuristic.uav import HeuristicUav
    from agos.agents.heuristic.ugv import HeuristicUgv

    paint_only = split_name(name)[0] == "paint-only"
    return HeuristicUav(paint_only=paint_only) if role == "uav" else HeuristicUgv(paint_only=paint_only)


@_builds("oracle")
def _oracle(role: Role, name: str, vlm: VlmOptions | None) -> Policy:
    from agos.agents.oracle import OracleUav, OracleUgv

    return OracleUav() if role == "uav" else OracleUgv()


@_builds("expert")
def _expert(role: Role, name: str, vlm: VlmOptions | None) -> Policy:
    from agos.agents.expert import ExpertPolicy

    return ExpertPolicy(role)


@_builds("random")
def _random(role: Role, name: str, vlm: VlmOptions | None) -> Policy:
    from agos.agents.random_policy import RandomPolicy

    return RandomPolicy(role)


@_builds("standin")
def _standin(role: Role, name: str, vlm: VlmOptions | None) -> Policy:
    from agos.agents.standin_policy import FixedLatencyPolicy

    return FixedLatencyPolicy(role, parse_standin(split_name(name)[0]))


@_builds("human")
def _human(role: Role, name: str, vlm: VlmOptions | None) -> Policy:
    raise ValueError("the human policy is a person at a browser: serve the role with `agos human --role ROLE "
                     "--connect EP --run RUN` instead of `agos agent` (docs/HUMAN.md)")


def make_policy(name: str, role: Role, *, vlm: VlmOptions | None = None, dataset_out: Path | None = None) -> Policy:
    """Build a policy by name (agents/names.py); ablation variants change only world-side tools.

    VLM policies (``agos-agent``, ``baseline``) need ``vlm``: the endpoint, model and client options.
    ``dataset_out``: the expert also writes every decision there (agents/dataset/writer.py).
    Raises ValueError, with one line saying what to change, for a name that names no policy here."""
    base, _ = split_name(name)
    if dataset_out is not None:
        if base != "expert":
            raise ValueError(f"--dataset-out writes the expert's decisions; policy {name!r} is not 'expert'")
        from agos.agents.dataset.writer import DatasetWriter

        return DatasetWriter(role, dataset_out)
    if is_builtin(base):
        return _BUILDERS["standin" if base.startswith("standin-") else base](role, name, vlm)
    return policy_class(name).from_settings(role, vlm=vlm or VlmOptions())


def policy_class(name: str) -> type[Policy]:
    """The class of a policy of one's own (``package.module:Class`` or a registered name), imported
    now. Raises ValueError, one line, when it cannot be found or is not a :class:`Policy`; an error
    raised by the module's own code while it is imported propagates as it is."""
    module_name, attribute = _target(name)
    where = f"policy {name!r}"
    module = _import(module_name, where)
    found: object = module
    for part in attribute.split("."):
        if not hasattr(found, part):
            raise ValueError(f"{where}: module {module_name!r} ({module.__file__}) has no {attribute!r}")
        found = getattr(found, part)
    if not (isinstance(found, type) and issubclass(found, Policy)):
        raise ValueError(f"{where}: {attribute} is not a subclass of agos.agents.contract.Policy "
                         "(docs/AGENTS.md, \"Write your own agent\")")
    return found


def locate_policy(name: str) -> None:
    """Check that a policy's code can be found in this Python without running it: agos's own names
    are checked by spelling; a class's module (or its entry point's) must be found on the path
    (its parent packages are imported, the module itself is not). For a command that starts the
    agent processes here (``agos eval``): a wrong module fails before any process starts."""
    base, _ = split_name(name)
    if is_builtin(base):
        return
    module_name, _ = _target(name)
    _add_current_folder()
    try:
        found = importlib.util.find_spec(module_name)
    except ModuleNotFoundError as exc:  # a parent package is missing
        raise ValueError(_not_found(f"policy {name!r}", exc.name or module_name)) from None
    if found is None:
        raise ValueError(_not_found(f"policy {name!r}", module_name))


def _target(name: str) -> tuple[str, str]:
    """(module, attribute path) a policy of one's own names."""
    if is_class_spec(name):
        module_name, _, attribute = name.partition(":")
        return module_name, attribute
    (point,) = entry_points(group=ENTRY_POINT_GROUP, name=name)  # split_name said it is registered
    if not point.attr:
        raise ValueError(f"policy {name!r}: its {ENTRY_POINT_GROUP} entry point {point.value!r} names a module, "
                         "not a class (give it as package.module:Class)")
    return point.module, point.attr


def _import(module_name: str, where: str) -> ModuleType:
    _add_current_folder()
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name is not None and (module_name == exc.name or module_name.startswith(f"{exc.name}.")):
            raise ValueError(_not_found(where, exc.name)) from None
        raise  # the module was found and itself imports something missing: its traceback says what


def _not_found(where: str, module_name: str) -> str:
    return (f"{where}: no module {module_name!r} on the Python path or in the current folder {os.getcwd()} "
            "(run from the folder that holds it, or add that folder to PYTHONPATH)")


def _add_current_folder() -> None:
    """Look for modules of one's own in the current folder too, after the installed packages, as
    ``python -m`` would (the ``agos`` script's path starts at its own folder instead)."""
    here = os.getcwd()
    if here not in sys.path and "" not in sys.path:
        sys.path.append(here)
