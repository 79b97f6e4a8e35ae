"""Heuristic UGV: drive to the UAV's candidate, stop, look around, confirm or reject.

No candidate: WAIT (the world wakes it when the coordination state changes). Pending
candidate: GO_TO_CANDIDATE. Arrived: STOP_OBSERVE. Six views: CONFIRM when a region with the
target's paint stands on the road at the reference's painted height within 48 m, else REJECT.
"""

from __future__ import annotations

import math

import numpy as np

from agos.agents.contract import action_for
from agos.agents.heuristic.perception import TargetProfile, detect_from_ground, profile_from_references
from agos.agents.navigation import Navigator
from agos.runtime.codec import decode_image
from agos.runtime.schemas import Action, Observation, Role

MIN_PIXELS = 80


APPROACH_WITHIN_M = 12.0


class HeuristicUgv:
    role: Role = "ugv"
    name = "heuristic"

    def __init__(self) -> None:
        self._profiles: dict[str, TargetProfile] = {}
        self.nav = Navigator()

    def end_episode(self, episode_id: str) -> None:
        self._profiles.pop(episode_id, None)
        self.nav.forget(episode_id)

    def act(self, obs: Observation) -> Action:
        profile = self._profiles.get(obs.episode_id)
        if profile is None:
            profile = self._profiles[obs.episode_id] = profile_from_references(obs.references)
        active = next((c for c in obs.coordination.candidates if c.status in ("pending", "arrived")), None)

        if obs.mode == "stop_6view":
            if self._target_in_views(obs, profile):
                return action_for(obs, "CONFIRM", candidate_id=active.candidate_id if active else None,
                                  message="Target confirmed.", rationale="paint and height match nearby")
            if active is not None:
                return action_for(obs, "REJECT", candidate_id=active.candidate_id,
                                  message=f"{active.candidate_id} is not the target; keep searching.")
        if active is not None and active.status == "pending" and "GO_TO_CANDIDATE" in obs.legal_actions:
            return action_for(obs, "GO_TO_CANDIDATE", candidate_id=active.candidate_id,
                              message=f"Driving to {active.candidate_id}.")
        if active is not None and active.status == "pending" and obs.mode == "driving":
            # No road-graph path planning: approach by the options' distance hints, then stop.
            if math.dist(obs.pose.position_world_m[:2], active.center_world_m) <= APPROACH_WITHIN_M:
                return action_for(obs, "STOP_OBSERVE")
            step = self.nav.towards(obs, active.center_world_m)
            if step is not None:
                return action_for(obs, "MOVE_TO_ROAD_WAYPOINT", waypoint_id=step)
        if active is not None and active.status == "arrived" and obs.mode == "driving":
            return action_for(obs, "STOP_OBSERVE")
        return action_for(obs, "WAIT")

    def _target_in_views(self, obs: Observation, profile: TargetProfile) -> bool:
        depth_frames = {f.name: f for f in obs.images if f.kind == "depth"}
        for frame in obs.images:
            if frame.kind != "rgb" or frame.name not in depth_frames or frame.intrinsics is None:
                continue
            d = depth_frames[frame.name]
            depth_m = decode_image(d.data).astype(np.float32) * float(d.depth_scale_m or 1.0)
            i = frame.intrinsics
            found = detect_from_ground(
                decode_image(frame.data), depth_m, view=frame.name, fx_px=i.fx_px, fy_px=i.fy_px, cx_px=i.cx_px,
                cy_px=i.cy_px, world_from_camera=np.asarray(frame.world_from_camera).reshape(4, 4), profile=profile)
            if any(det.pixels >= MIN_PIXELS for det in found):
                return True
        return False
