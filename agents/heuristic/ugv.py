"""Heuristic UGV: drive to the UAV's candidate, stop, look around, confirm or reject.

No candidate: WAIT (the world wakes it when the coordination state changes). Pending
candidate: GO_TO_CANDIDATE. Arrived: STOP_OBSERVE. Six views: CONFIRM when an object within
48 m stands on the street with the target's paint (its brightness judged in the light it stands
in), its body height and no more than its length (:mod:`ground`), else REJECT. ``paint_only``
(the ``paint-only`` policy): CONFIRM on the first object of the target's paint in view.
"""

from __future__ import annotations

import math

import numpy as np

from agos.agents.contract import Policy, action_for
from agos.agents.heuristic.ground import GroundView, find_target
from agos.agents.heuristic.perception import TargetProfile, profile_from_references
from agos.agents.navigation import Navigator
from agos.runtime.codec import decode_image
from agos.runtime.schemas import Action, Observation, Role

MIN_PIXELS = 80


APPROACH_WITHIN_M = 12.0


class HeuristicUgv(Policy):
    role: Role = "ugv"
    name = "heuristic"

    def __init__(self, *, paint_only: bool = False) -> None:
        self._profiles: dict[str, TargetProfile] = {}
        self.nav = Navigator()
        self.paint_only = paint_only
        self.name = "paint-only" if paint_only else "heuristic"

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
                                  message="Target confirmed.", rationale="paint, height and length match nearby")
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
        views = []
        for frame in obs.images:
            d = depth_frames.get(frame.name)
            if frame.kind != "rgb" or d is None or frame.intrinsics is None or frame.world_from_camera is None:
                continue
            depth_m = decode_image(d.data).astype(np.float32) * float(d.depth_scale_m or 1.0)
            views.append(GroundView(frame.name, decode_image(frame.data), depth_m, frame.intrinsics,
                                    np.asarray(frame.world_from_camera).reshape(4, 4)))
        return bool(find_target(views, profile, min_pixels=MIN_PIXELS, paint_only=self.paint_only))
