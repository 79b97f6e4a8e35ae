"""The world's clock for the expert's decisions: which role is asked what, when (Stage 2).

A small replica of :class:`agos.world.sim.engine.EpisodeRunner`'s timing for the actions the
expert takes, on the ideal link (every sync and message delivered at once): a role is ready when
its action completes (a move by its length and speed, STOP_OBSERVE ``stop_observe_s``,
ANNOTATE_CANDIDATE and REJECT ``short_action_s``); roles ready at one instant are asked together,
each on what it knew before the round (so a UGV asked in the same instant as the UAV's annotation
does not know the candidate yet), and applied UAV first; WAIT lasts ``wait_max_s`` unless a change
reaches the role first (a candidate, a status, a message); the UAV is frozen from its annotation
until it hears the candidate resolved, or ``max_freeze_s`` passes. Times are computed with the
world's own float operations, so a step's ``sim_time_s`` equals the world's clock exactly.

What each role does when asked comes from an :class:`Agenda` (the planner's); the timeline keeps
the steps, counts decisions and tells the planner when the episode ends (CONFIRM) or a wrong
candidate has been rejected.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.keys import ROLES
from agos.runtime.schemas import ExpertStep, Role


class Agenda(Protocol):
    """What a role does when the timeline asks it at ``now``; ``knows_candidate``: the role has
    heard of the open candidate (before this round)."""

    def next_step(self, now: float, knows_candidate: bool) -> tuple[ExpertStep, float]:
        """The step and how long its action takes (s; WAIT: ignored)."""
        ...


@dataclass
class _RoleClock:
    ready_s: float = 0.0
    waiting: bool = False
    frozen: bool = False
    frozen_since_s: float = 0.0


@dataclass
class Timeline:
    cfg: EpisodeConfig
    steps: dict[Role, list[ExpertStep]] = field(default_factory=lambda: {"uav": [], "ugv": []})
    clocks: dict[Role, _RoleClock] = field(default_factory=lambda: {"uav": _RoleClock(), "ugv": _RoleClock()})
    ugv_knows: bool = False
    """The UGV has heard of the open candidate."""
    now_s: float = 0.0
    confirmed: bool = False

    @property
    def decisions(self) -> int:
        return len(self.steps["uav"]) + len(self.steps["ugv"])

    def run(self, agendas: dict[Role, Agenda], *, until_reject: bool) -> None:
        """Ask the roles, in the world's order, until CONFIRM or (``until_reject``) until the
        round in which the UGV rejects a candidate has been delivered."""
        while not self.confirmed:
            uav, ugv = self.clocks["uav"], self.clocks["ugv"]
            ready_uav = math.inf if uav.frozen else uav.ready_s
            t_unfreeze = uav.frozen_since_s + self.cfg.max_freeze_s if uav.frozen else math.inf
            now = min(ready_uav, ugv.ready_s, t_unfreeze)
            if now > self.cfg.sim_time_limit_s:
                raise RuntimeError("the expert's plan runs past the episode's time limit")
            self.now_s = max(self.now_s, now)
            if t_unfreeze <= now:
                uav.frozen, uav.waiting, uav.ready_s = False, False, self.now_s
                continue
            due = [r for r in ROLES if (ready_uav if r == "uav" else ugv.ready_s) <= self.now_s + 1e-9]
            knows = self.ugv_knows
            applied: list[ExpertStep] = []
            for role in due:
                step, duration_s = agendas[role].next_step(self.now_s, knows if role == "ugv" else True)
                self._apply(role, step, duration_s)
                applied.append(step)
                if self.confirmed:
                    return
            rejected = False
            for role, step in zip(due, applied, strict=True):
                other: Role = "ugv" if role == "uav" else "uav"
                if step.action == "ANNOTATE_CANDIDATE":
                    self.ugv_knows = True
                    self._wake("ugv")
                if step.action in ("GO_TO_CANDIDATE", "REJECT") or step.message:
                    self._wake(other)
                if step.action == "REJECT":
                    self.ugv_knows, rejected = False, True
                    if uav.frozen:
                        uav.frozen, uav.waiting, uav.ready_s = False, False, self.now_s
            if rejected and until_reject:
                return

    def _apply(self, role: Role, step: ExpertStep, duration_s: float) -> None:
        clock = self.clocks[role]
        clock.waiting = False
        self.steps[role].append(step)
        now = self.now_s
        if step.action == "WAIT":
            clock.ready_s, clock.waiting = now + self.cfg.wait_max_s, True
        elif step.action == "MOVE_TO_UAV_WAYPOINT":
            clock.ready_s = now + duration_s
        elif step.action in ("MOVE_TO_ROAD_WAYPOINT", "GO_TO_CANDIDATE"):
            clock.ready_s = now + max(duration_s, self.cfg.short_action_s)
        elif step.action == "ANNOTATE_CANDIDATE":
            clock.frozen, clock.frozen_since_s = True, now
            clock.ready_s = now + self.cfg.short_action_s
        elif step.action == "STOP_OBSERVE":
            clock.ready_s = now + self.cfg.stop_observe_s
        elif step.action == "REJECT":
            clock.ready_s = now + self.cfg.short_action_s
        elif step.action == "CONFIRM":
            self.confirmed = True
        else:
            raise ValueError(f"the expert takes no {step.action}")

    def _wake(self, role: Role) -> None:
        clock = self.clocks[role]
        if clock.waiting and clock.ready_s > self.now_s:
            clock.ready_s = self.now_s
        clock.waiting = False
