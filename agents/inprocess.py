"""Policies called in the world's own process: a :class:`DecisionSource` for tests, examples and
debugging (the benchmark itself runs agents as separate processes over zenoh)."""

from __future__ import annotations

from agos.agents.contract import Policy
from agos.runtime.schemas import Action, Observation, Role


class InProcessAgents:
    def __init__(self, policies: dict[Role, Policy]) -> None:
        self.policies = policies

    def decide(self, observations: dict[Role, Observation]) -> dict[Role, Action | None]:
        return {role: self.policies[role].act(obs) for role, obs in observations.items()}
