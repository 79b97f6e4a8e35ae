"""Heuristic UAV: cover the active grid, annotate the cell of a look-alike of the target.

Coverage: every visited node also counts its four axis neighbours as seen (the 60 deg nadir
view spans about 92 m at 80 m, so their centres are in view). The UAV flies towards the nearest
node not yet seen, one legal neighbour move at a time. Detection: standing objects (from the
nadir depth) with the target's paint, footprint and height against the reference views (see
:mod:`aerial`; without a depth image, paint colour and footprint alone, :mod:`perception`).
Candidates rejected by the UGV are remembered and not annotated again.

``paint_only``: the ``paint-only`` policy, the floor of what the paint alone buys: the best match
of the target's paint, whatever its size, height or attributes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from agos.agents.contract import Policy, action_for
from agos.agents.heuristic.aerial import detect_vehicles_from_above
from agos.agents.heuristic.perception import AerialDetection, TargetProfile, detect_from_above, profile_from_references
from agos.runtime.camera import cell_of_pixel, pixel_to_ground
from agos.runtime.codec import decode_image
from agos.runtime.schemas import Action, ImageFrame, Observation, Role

SEEN_RADIUS_M = 41.0
REJECTED_RADIUS_M = 12.0


@dataclass
class _Memory:
    profile: TargetProfile
    seen: set[str] = field(default_factory=set)


class HeuristicUav(Policy):
    role: Role = "uav"
    name = "heuristic"

    def __init__(self, *, paint_only: bool = False) -> None:
        self._memory: dict[str, _Memory] = {}
        self.paint_only = paint_only
        self.name = "paint-only" if paint_only else "heuristic"

    def end_episode(self, episode_id: str) -> None:
        self._memory.pop(episode_id, None)

    def act(self, obs: Observation) -> Action:
        mem = self._memory.get(obs.episode_id)
        if mem is None:
            mem = self._memory[obs.episode_id] = _Memory(profile_from_references(obs.references))
        here = np.asarray(obs.pose.position_world_m[:2])
        for wp in obs.active_uav_waypoints:
            if math.dist(wp.position_world_m[:2], here) <= SEEN_RADIUS_M:
                mem.seen.add(wp.waypoint_id)

        if "ANNOTATE_CANDIDATE" in obs.legal_actions:
            cell = self._target_cell(obs, mem.profile)
            if cell is not None:
                return action_for(obs, "ANNOTATE_CANDIDATE", cell=cell,
                                  message=f"Candidate in cell {cell}; please verify.",
                                  rationale="paint colour, footprint and height match the reference")

        if "MOVE_TO_UAV_WAYPOINT" in obs.legal_actions and obs.waypoint_options:
            unseen = [w for w in obs.active_uav_waypoints if w.waypoint_id not in mem.seen]
            if not unseen:  # everything seen once: start a second sweep
                mem.seen = set()
                unseen = list(obs.active_uav_waypoints)
            goal = min(unseen, key=lambda w: (math.dist(w.position_world_m[:2], here), w.waypoint_id))
            step = min(obs.waypoint_options,
                       key=lambda w: (math.dist(w.position_world_m[:2], goal.position_world_m[:2]), w.waypoint_id))
            return action_for(obs, "MOVE_TO_UAV_WAYPOINT", waypoint_id=step.waypoint_id,
                              rationale=f"coverage towards {goal.waypoint_id}")
        return action_for(obs, "NO_RELIABLE_CANDIDATE")

    def _target_cell(self, obs: Observation, profile: TargetProfile) -> str | None:
        frame = next((f for f in obs.images if f.kind == "rgb" and f.name == "nadir"), None)
        if frame is None or frame.intrinsics is None or frame.world_from_camera is None:
            return None
        rgb = decode_image(frame.data)
        pose = np.asarray(frame.world_from_camera).reshape(4, 4)
        rejected = [c.center_world_m for c in obs.coordination.candidates if c.status in ("rejected", "false_confirm")]
        intr = frame.intrinsics
        for det in _detections(obs, frame, rgb, pose, profile, self.paint_only):
            ground = pixel_to_ground(det.u_px, det.v_px, pose, intr)
            if any(math.dist(ground, r) <= REJECTED_RADIUS_M for r in rejected):
                continue
            return cell_of_pixel(det.u_px, det.v_px, intr.width_px, intr.height_px)
        return None


def _detections(obs: Observation, frame: ImageFrame, rgb: np.ndarray, pose: np.ndarray,
                profile: TargetProfile, paint_only: bool) -> list[AerialDetection]:
    """The nadir view's matches, best first: by shape and context when its depth image came with
    it, else by colour and footprint."""
    assert frame.intrinsics is not None
    depth = next((f for f in obs.images if f.kind == "depth" and f.name == frame.name), None)
    if depth is None:
        return detect_from_above(rgb, profile, altitude_m=float(pose[2, 3]), fy_px=frame.intrinsics.fy_px)
    depth_m = decode_image(depth.data).astype(np.float32) * float(depth.depth_scale_m or 1.0)
    return detect_vehicles_from_above(rgb, depth_m, profile, intrinsics=frame.intrinsics, world_from_camera=pose,
                                      paint_only=paint_only)
