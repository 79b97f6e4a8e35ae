"""The policy contract: one object per role that turns observations into actions.

A policy may keep per-episode memory (keyed by ``episode_id``); the service calls
:meth:`Policy.end_episode` when an episode's result is seen so memory does not grow.
Policies never see ground truth: only :class:`~agos.runtime.schemas.Observation`.

Over the bus, the agent service delivers an observation as its compiled mirror
(:mod:`agos.runtime.structs`): the same fields and nested values, read the same way, but without
the pydantic methods. In-process runs pass the model itself. Read observations; do not rely on
``model_dump``/``model_copy`` (``structs.to_model`` gives the model when one is needed).
:func:`action_for` answers in the same kind (a mirror action for a mirror observation), so a
decision over the bus touches no pydantic code; a policy may also return an :class:`Action` model.
"""

from __future__ import annotations

from typing import Protocol

import msgspec

from agos.runtime.schemas import Action, Observation, Role
from agos.runtime.settings import VlmOptions
from agos.runtime.structs import mirror

_MIRROR_ACTION = mirror(Action)


class Policy(Protocol):
    """What an agent service serves. Optional extras: ``act_async`` (a coroutine the service awaits:
    remote models), ``inline = True`` (``act`` takes microseconds and does no I/O, so the service
    answers on the thread that received the observation instead of handing it to a worker),
    ``preflight`` (checked before serving)."""

    role: Role
    name: str

    def act(self, obs: Observation) -> Action:
        """Return a legal action for ``obs`` (the world turns an illegal one into WAIT)."""
        ...

    def end_episode(self, episode_id: str) -> None:
        """Forget what was kept about an episode."""
        ...


ABLATIONS = {"": (True, True), "no_e2a": (False, True), "no_rgpp": (True, False), "no_both": (False, False)}
KNOWN = ("heuristic[:no_e2a|no_rgpp|no_both], agos-agent[:no_e2a|no_rgpp|no_both], baseline, oracle, random, "
         "standin-<N>ms")
VLM_POLICIES = ("agos-agent", "baseline")
"""Policies that ask a vision-language model over an OpenAI-compatible endpoint."""
NO_CANDIDATES = ("baseline",)
"""Policies that coordinate through text messages only: no ANNOTATE_CANDIDATE / GO_TO_CANDIDATE."""


def needs_vlm(name: str) -> bool:
    return split_name(name)[0] in VLM_POLICIES


def split_name(name: str) -> tuple[str, str]:
    """``heuristic:no_rgpp`` -> ("heuristic", "no_rgpp"); raises ValueError for unknown variants."""
    base, _, variant = name.partition(":")
    if variant not in ABLATIONS:
        raise ValueError(f"unknown policy variant {variant!r} in {name!r}; variants: no_e2a, no_rgpp, no_both")
    if variant and base in NO_CANDIDATES:
        raise ValueError(f"{base} has no candidate tools, so it has no {variant} ablation")
    return base, variant


def tools_for(policies: dict[str, str]) -> dict[str, bool]:
    """The world-side tools a run's policies use: structured candidates (off for the Baseline), E2A and
    RGPP (off in ablations), oracle hints."""
    e2a = rgpp = candidates = True
    for name in policies.values():
        base, variant = split_name(name)
        e2a, rgpp = e2a and ABLATIONS[variant][0], rgpp and ABLATIONS[variant][1]
        candidates = candidates and base not in NO_CANDIDATES
    return {"candidates": candidates, "e2a": e2a, "rgpp": rgpp,
            "oracle": any(split_name(n)[0] == "oracle" for n in policies.values())}


def make_policy(name: str, role: Role, *, vlm: VlmOptions | None = None) -> Policy:
    """Build a policy by name (see ``KNOWN``); ablation variants change only world-side tools.

    VLM policies (``agos-agent``, ``baseline``) need ``vlm``: the endpoint, model and client options."""
    base, _ = split_name(name)
    if base in VLM_POLICIES:
        if vlm is None or not vlm.base_url or not vlm.model:
            raise ValueError(f"policy {name!r} asks a VLM: give --vlm-base-url URL and --model NAME "
                             "(offline: start `agos vlm-standin` and use its URL)")
        from agos.agents.vlm.agent import VlmAgent

        return VlmAgent(role, name, vlm)
    if base == "heuristic":
        from agos.agents.heuristic.uav import HeuristicUav
        from agos.agents.heuristic.ugv import HeuristicUgv

        return HeuristicUav() if role == "uav" else HeuristicUgv()
    if base == "oracle":
        from agos.agents.oracle import OracleUav, OracleUgv

        return OracleUav() if role == "uav" else OracleUgv()
    if base == "random":
        from agos.agents.random_policy import RandomPolicy

        return RandomPolicy(role)
    if base.startswith("standin-"):
        from agos.agents.standin import FixedLatencyPolicy, parse_standin

        return FixedLatencyPolicy(role, parse_standin(base))
    raise ValueError(f"unknown policy {name!r}; known: {KNOWN}")


def action_for(obs: Observation, name: str, **fields: object) -> Action:
    """An action answering ``obs`` (run, episode, role and decision index filled in), in the
    observation's kind: the model for a model; for a mirror (over the bus), the mirror of
    :class:`Action`, which is built without checks: the agent service checks its types before
    sending it (``codec.encode_checked``) and answers WAIT for one that fails, as for a policy error."""
    kind = _MIRROR_ACTION if isinstance(obs, msgspec.Struct) else Action
    return kind(run_id=obs.run_id, episode_id=obs.episode_id, role=obs.role,
                decision_index=obs.decision_index, action=name, **fields)
