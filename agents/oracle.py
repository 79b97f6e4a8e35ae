"""The oracle policy: uses the ground-truth hints the world gives only to it.

An upper bound for the benchmark and a solvability check (oracle SR should be near 100 %).
UAV: annotate the grid cell containing the target as soon as it is in view, else fly towards it.
UGV: take a candidate with GO_TO_CANDIDATE, else drive towards the target; stop when near;
CONFIRM exactly when the checker would accept, else move on.
"""

from __future__ import annotations

import math

import numpy as np

from agos.agents.contract import action_for
from agos.agents.navigation import Navigator
from agos.runtime.camera import cell_of_pixel, ground_to_pixel
from agos.runtime.schemas import Action, Observation, Role

STOP_WITHIN_M = 25.0


class OracleUav:
    role: Role = "uav"
    name = "oracle"
    inline = True  # microseconds, no I/O: answered on the receiving thread (agents/service.py)

    def end_episode(self, episode_id: str) -> None:
        pass

    def act(self, obs: Observation) -> Action:
        hints = obs.oracle
        if hints is None:
            raise ValueError("the oracle policy needs a run started with policy 'oracle' (world hints missing)")
        if hints.target_in_view and "ANNOTATE_CANDIDATE" in obs.legal_actions:
            cell = _cell_of(obs, hints.target_world_m)
            if cell is not None:
                return action_for(obs, "ANNOTATE_CANDIDATE", cell=cell, message=f"Target in {cell}.")
        if "MOVE_TO_UAV_WAYPOINT" in obs.legal_actions and obs.waypoint_options:
            best = min(obs.waypoint_options, key=lambda w: (math.dist(w.position_world_m[:2], hints.target_world_m),
                                                             w.waypoint_id))
            if math.dist(best.position_world_m[:2], hints.target_world_m) < math.dist(obs.pose.position_world_m[:2],
                                                                                      hints.target_world_m):
                return action_for(obs, "MOVE_TO_UAV_WAYPOINT", waypoint_id=best.waypoint_id)
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


class OracleUgv:
    role: Role = "ugv"
    name = "oracle"
    inline = True

    def __init__(self) -> None:
        self.nav = Navigator()

    def end_episode(self, episode_id: str) -> None:
        self.nav.forget(episode_id)

    def act(self, obs: Observation) -> Action:
        hints = obs.oracle
        if hints is None:
            raise ValueError("the oracle policy needs a run started with policy 'oracle' (world hints missing)")
        active = next((c for c in obs.coordination.candidates if c.status in ("pending", "arrived")), None)
        if obs.mode == "stop_6view":
            if hints.confirm_would_succeed:
                return action_for(obs, "CONFIRM", message="Target confirmed.")
            self.nav.mark_stopped(obs)
            if active is not None:
                return action_for(obs, "REJECT", candidate_id=active.candidate_id)
        if active is not None and active.status == "pending" and "GO_TO_CANDIDATE" in obs.legal_actions:
            return action_for(obs, "GO_TO_CANDIDATE", candidate_id=active.candidate_id)
        here = obs.pose.position_world_m[:2]
        if math.dist(here, hints.target_world_m) <= STOP_WITHIN_M and not self.nav.stopped_here(obs):
            return action_for(obs, "STOP_OBSERVE")
        step = self.nav.towards(obs, hints.target_world_m)
        if step is not None:
            return action_for(obs, "MOVE_TO_ROAD_WAYPOINT", waypoint_id=step)
        return action_for(obs, "WAIT")
