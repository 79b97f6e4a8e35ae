"""A policy that never answers: for tests of what gives up on a stuck decision (a pool's close)."""

from __future__ import annotations

import time

from agos.agents.contract import Policy
from agos.runtime.schemas import Action, Observation, Role


class Stalling(Policy):
    """``act`` sleeps ``seconds`` (default 10 minutes) and then raises: it never answers in a test's time."""

    def __init__(self, role: Role, seconds: float = 600.0) -> None:
        super().__init__(role)
        self.seconds = seconds

    def act(self, obs: Observation) -> Action:
        time.sleep(self.seconds)
        raise TimeoutError(f"{self.role} stalled {self.seconds} s on decision {obs.decision_index}")
