"""The oracle policy: uses the ground-truth hints the world gives only to it.

An upper bound for the benchmark and a solvability check: it succeeds on every solvable episode
(``bench/oracle_sweep.py`` runs it over every town and difficulty).

UAV: fly the shortest route over the active nodes to the node nearest the target (then the next
nearest, should the target be hidden from there) and annotate the grid cell that holds the target
as soon as it is in view; then wait, in view, while the UGV verifies.

UGV: wait for that candidate and take GO_TO_CANDIDATE. In runs with the oracle's hints the world
approaches a candidate that holds the target at the anchor nearest by road where the CONFIRM
checker accepts (``world/sim/rules.py``), so this is the shortest road path to a verifying pose;
then STOP_OBSERVE and CONFIRM exactly when the checker would accept. Fallback when no usable
candidate comes (another UAV policy, no candidate tools, no RGPP): approach the target greedily by
the road options and stop near it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from agos.agents.contract import Policy, action_for
from agos.agents.navigation import Navigator, uav_route
from agos.runtime.camera import cell_of_pixel, ground_to_pixel
from agos.runtime.schemas import Action, Observation, OracleHints, Role

STOP_WITHIN_M = 25.0
CANDIDATE_PATIENCE_S = 120.0
"""How long the UGV waits for a candidate (since its candidates last changed) before it searches
by itself; the oracle UAV annotates well within this (a few flights of 4-6 s)."""


def _hints(obs: Observation) -> OracleHints:
    if obs.oracle is None:
        raise ValueError("the oracle policy needs a run started with policy 'oracle' (world hints missing)")
    return obs.oracle


class OracleUav(Policy):
    role: Role = "uav"
    name = "oracle"
    inline = True  # under a millisecond, no I/O: answered on the receiving thread (agents/agent_service.py)

    def __init__(self) -> None:
        self._tried: dict[str, set[str]] = {}
        """Per episode: nodes the UAV has been at without an annotatable view of the target."""

    def end_episode(self, episode_id: str) -> None:
        self._tried.pop(episode_id, None)

    def act(self, obs: Observation) -> Action:
        hints = _hints(obs)
        cell = _cell_of(obs, hints.target_world_m) if hints.target_in_view else None
        if cell is not None:
            if "ANNOTATE_CANDIDATE" in obs.legal_actions:
                return action_for(obs, "ANNOTATE_CANDIDATE", cell=cell, message=f"Target in {cell}.")
            return action_for(obs, "WAIT")  # our candidate is open: stay with the target in view
        nodes = obs.active_uav_waypoints
        if "MOVE_TO_UAV_WAYPOINT" not in obs.legal_actions or not obs.waypoint_options or not nodes:
            return action_for(obs, "WAIT")
        here = min(nodes, key=lambda w: (math.dist(w.position_world_m[:2], obs.pose.position_world_m[:2]), w.waypoint_id))
        tried = self._tried.setdefault(obs.episode_id, set())
        tried.add(here.waypoint_id)
        spacing = min(max(abs(w.position_world_m[0] - here.position_world_m[0]),
                          abs(w.position_world_m[1] - here.position_world_m[1])) for w in obs.waypoint_options)
        options = {w.waypoint_id for w in obs.waypoint_options}
        # the untried nodes nearest the target first: the first reachable one is where to look next
        for goal in sorted((w for w in nodes if w.waypoint_id not in tried),
                           key=lambda w: (math.dist(w.position_world_m[:2], hints.target_world_m), w.waypoint_id)):
            route = uav_route(nodes, here.waypoint_id, goal.waypoint_id, spacing)
            if route is not None and len(route) > 1 and route[1] in options:
                return action_for(obs, "MOVE_TO_UAV_WAYPOINT", waypoint_id=route[1])
            tried.add(goal.waypoint_id)  # out of reach from here
        return action_for(obs, "WAIT")


def _cell_of(obs: Observation, xy: tuple[float, float]) -> str | None:
    frame = next((f for f in obs.images if f.kind == "rgb" and f.name == "nadir"), None)
    if frame is None or frame.intrinsics is None or frame.world_from_camera is None:
        return None
    i = frame.intrinsics
    pixel = ground_to_pixel(xy, np.asarray(frame.world_from_camera).reshape(4, 4), i)
    if pixel is None or not (0 <= pixel[0] < i.width_px and 0 <= pixel[1] < i.height_px):
        return None
    return cell_of_pixel(pixel[0], pixel[1], i.width_px, i.height_px)


@dataclass
class _UgvMemory:
    known: frozenset[tuple[str, str]] = frozenset()
    """The candidates the UGV knows and their status, at its last decision."""
    news_s: float = 0.0
    """Sim time when that last changed."""


class OracleUgv(Policy):
    role: Role = "ugv"
    name = "oracle"
    inline = True

    def __init__(self) -> None:
        self.nav = Navigator()
        self._memory: dict[str, _UgvMemory] = {}

    def end_episode(self, episode_id: str) -> None:
        self.nav.forget(episode_id)
        self._memory.pop(episode_id, None)

    def act(self, obs: Observation) -> Action:
        hints = _hints(obs)
        mem = self._memory.setdefault(obs.episode_id, _UgvMemory())
        known = frozenset((c.candidate_id, c.status) for c in obs.coordination.candidates)
        if known != mem.known:
            mem.known, mem.news_s = known, obs.sim_time_s
        active = next((c for c in obs.coordination.candidates if c.status in ("pending", "arrived")), None)
        if obs.mode == "stop_6view":
            if hints.confirm_would_succeed:
                return action_for(obs, "CONFIRM", message="Target confirmed.")
            self.nav.mark_stopped(obs)
            if active is not None:  # not verifiable from here: the UAV annotates again, approached from here
                return action_for(obs, "REJECT", candidate_id=active.candidate_id)
        if active is not None and active.status == "pending" and "GO_TO_CANDIDATE" in obs.legal_actions:
            return action_for(obs, "GO_TO_CANDIDATE", candidate_id=active.candidate_id)
        if active is not None and active.status == "arrived" and obs.mode == "driving" and not self.nav.stopped_here(obs):
            return action_for(obs, "STOP_OBSERVE")
        if active is None and obs.sim_time_s - mem.news_s < CANDIDATE_PATIENCE_S:
            return action_for(obs, "WAIT")  # woken when a candidate arrives
        # fallback: no candidate came, or no GO_TO_CANDIDATE: approach the target by the road options
        here = obs.pose.position_world_m[:2]
        if math.dist(here, hints.target_world_m) <= STOP_WITHIN_M and not self.nav.stopped_here(obs):
            return action_for(obs, "STOP_OBSERVE")
        step = self.nav.towards(obs, hints.target_world_m)
        if step is not None:
            return action_for(obs, "MOVE_TO_ROAD_WAYPOINT", waypoint_id=step)
        return action_for(obs, "WAIT")
