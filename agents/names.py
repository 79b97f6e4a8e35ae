"""Policy names: ``base[:variant]`` with the ablation variants, which policies ask a VLM, and the
world-side tools a run's policies use. Pure names, no policy code, so any layer above may read them.

Besides agos's own names, a policy may be named by its class, ``package.module:Class``, or by a
name another installed package registers in the ``agos.policies`` entry-point group
(agents/registry.py imports either only when the policy is built). Such a policy gets every
world-side tool (candidates, E2A, RGPP) and has no ablation variants.
"""

from __future__ import annotations

import re
from importlib.metadata import entry_points

ABLATIONS = {"": (True, True), "no_e2a": (False, True), "no_rgpp": (True, False), "no_both": (False, False)}
KNOWN = ("heuristic[:no_e2a|no_rgpp|no_both], agos-agent[:no_e2a|no_rgpp|no_both], baseline, oracle, expert, random, "
         "paint-only, standin-<N>ms, human")
VLM_POLICIES = ("agos-agent", "baseline")
"""Policies that ask a vision-language model over an OpenAI-compatible endpoint."""
NO_CANDIDATES = ("baseline",)
"""Policies that coordinate through text messages only: no ANNOTATE_CANDIDATE / GO_TO_CANDIDATE."""


SCRIPTED = ("heuristic", "oracle", "expert", "random", "paint-only")
"""Policies that answer from the observation alone, in milliseconds of the agent's CPU."""
HUMAN = "human"
"""A person at a browser console (``agos human``, agents/human/): the paper's Human reference."""
ENTRY_POINT_GROUP = "agos.policies"
"""The entry-point group other packages register their policies in: ``name = "package.module:Class"``."""
_CLASS_SPEC = re.compile(r"[A-Za-z_][\w]*(\.[A-Za-z_][\w]*)*:[A-Za-z_][\w]*(\.[A-Za-z_][\w]*)*")


def is_builtin(base: str) -> bool:
    """``base`` (a name without its variant) is one of agos's own policies."""
    return base in (*VLM_POLICIES, *SCRIPTED, HUMAN) or base.startswith("standin-")


def is_class_spec(name: str) -> bool:
    """``name`` names a policy class, ``package.module:Class``: it has a colon and what precedes it
    is not one of agos's own policies (``heuristic:no_rgpp`` is a variant, not a class)."""
    base, sep, _ = name.partition(":")
    return bool(sep) and not is_builtin(base)


def registered_names() -> dict[str, str]:
    """Policies other installed packages register in the ``agos.policies`` entry-point group: name ->
    ``package.module:Class``. Reads package metadata only; imports nothing. agos's own names win over
    a registered name that repeats one."""
    return {ep.name: ep.value for ep in entry_points(group=ENTRY_POINT_GROUP) if not is_builtin(ep.name)}


def known_names() -> str:
    """Every name a policy may be given, for error messages."""
    registered = ", ".join(sorted(registered_names()))
    return KNOWN + (f"; registered: {registered}" if registered else "") + "; or your own as package.module:Class"


def parse_standin(name: str) -> float:
    """``standin-200ms`` -> 0.2 s."""
    suffix = name.removeprefix("standin-")
    if not suffix.endswith("ms") or not suffix[:-2].isdigit():
        raise ValueError(f"stand-in policy {name!r}: use standin-<milliseconds>ms, e.g. standin-200ms")
    return int(suffix[:-2]) / 1000.0


def known_latency_s(name: str) -> float | None:
    """Wall seconds the policy takes per decision, when its name says: ``standin-<N>ms`` N/1000,
    the scripted policies 0; None for the VLM policies, whose latency is the model's (give it with
    ``agos eval --model-latency``)."""
    base, _ = split_name(name)
    if base.startswith("standin-"):
        return parse_standin(base)
    return 0.0 if base in SCRIPTED else None


def is_human(name: str) -> bool:
    """A person decides (``agos human`` serves the role, not ``agos agent``)."""
    return split_name(name)[0] == HUMAN


def needs_vlm(name: str) -> bool:
    return split_name(name)[0] in VLM_POLICIES


def split_name(name: str) -> tuple[str, str]:
    """``heuristic:no_rgpp`` -> ("heuristic", "no_rgpp"); a policy of one's own (``package.module:Class``
    or a registered name) -> (name, ""). Raises ValueError for an unknown policy or variant, or a
    malformed class name, so a misspelt name fails before any process starts (whether a class can
    be imported is the registry's to say: agents/registry.py)."""
    if is_class_spec(name):
        if not _CLASS_SPEC.fullmatch(name):
            raise ValueError(f"policy {name!r}: a policy class is named package.module:Class (dotted Python names)")
        return name, ""
    base, _, variant = name.partition(":")
    if base.startswith("standin-"):
        parse_standin(base)
    elif not is_builtin(base):
        if base in registered_names():  # a name with a colon that is not agos's own is a class
            return base, ""
        raise ValueError(f"unknown policy {name!r}; known: {known_names()}")
    if variant not in ABLATIONS:
        raise ValueError(f"unknown policy variant {variant!r} in {name!r}; variants: no_e2a, no_rgpp, no_both")
    if variant and base in NO_CANDIDATES:
        raise ValueError(f"{base} has no candidate tools, so it has no {variant} ablation")
    return base, variant


def tools_for(policies: dict[str, str]) -> dict[str, bool]:
    """The world-side tools a run's policies use: structured candidates (off for the Baseline), E2A and
    RGPP (off in ablations), oracle hints, the expert's plan."""
    e2a = rgpp = candidates = True
    for name in policies.values():
        base, variant = split_name(name)
        e2a, rgpp = e2a and ABLATIONS[variant][0], rgpp and ABLATIONS[variant][1]
        candidates = candidates and base not in NO_CANDIDATES
    return {"candidates": candidates, "e2a": e2a, "rgpp": rgpp,
            "oracle": any(split_name(n)[0] == "oracle" for n in policies.values()),
            "expert": any(split_name(n)[0] == "expert" for n in policies.values())}
