"""The policy contract: one object per role that turns observations into actions.

A policy may keep per-episode memory (keyed by ``episode_id``); the service calls
:meth:`Policy.end_episode` when an episode's result is seen so memory does not grow.
Policies never see ground truth: only :class:`~agos.runtime.schemas.Observation`.
"""

from __future__ import annotations

from typing import Protocol

from agos.runtime.schemas import Action, Observation, Role


class Policy(Protocol):
    role: Role
    name: str

    def act(self, obs: Observation) -> Action:
        """Return a legal action for ``obs`` (the world turns an illegal one into WAIT)."""
        ...

    def end_episode(self, episode_id: str) -> None:
        """Forget what was kept about an episode."""
        ...


def make_policy(name: str, role: Role) -> Policy:
    """Build a policy by name: ``heuristic`` (offline, OpenCV) or ``standin-<N>ms`` (fixed latency)."""
    if name == "heuristic":
        from agos.agents.heuristic.uav import HeuristicUav
        from agos.agents.heuristic.ugv import HeuristicUgv

        return HeuristicUav() if role == "uav" else HeuristicUgv()
    if name.startswith("standin-"):
        from agos.agents.standin import FixedLatencyPolicy, parse_standin

        return FixedLatencyPolicy(role, parse_standin(name))
    raise ValueError(f"unknown policy {name!r}; known: heuristic, standin-<N>ms")


def action_for(obs: Observation, name: str, **fields: object) -> Action:
    """An action answering ``obs`` (run, episode, role and decision index filled in)."""
    return Action(run_id=obs.run_id, episode_id=obs.episode_id, role=obs.role,
                  decision_index=obs.decision_index, action=name, **fields)
