"""Policy names: ``base[:variant]`` with the ablation variants, which policies ask a VLM, and the
world-side tools a run's policies use. Pure names, no policy code, so any layer above may read them.
"""

from __future__ import annotations

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
    """``heuristic:no_rgpp`` -> ("heuristic", "no_rgpp"); raises ValueError for an unknown policy or
    variant, so a misspelt name fails before any process starts."""
    base, _, variant = name.partition(":")
    if base.startswith("standin-"):
        parse_standin(base)
    elif base not in (*VLM_POLICIES, *SCRIPTED, HUMAN):
        raise ValueError(f"unknown policy {name!r}; known: {KNOWN}")
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
