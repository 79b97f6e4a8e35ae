"""Heuristic UAV: cover the active grid, annotate the cell of a look-alike of the target.

Coverage: every visited node also counts its four axis neighbours as seen (the 60 deg nadir
view spans about 92 m at 80 m, so their centres are in view). The UAV flies towards the nearest
node not yet seen, one legal neighbour move at a time. Detection: standing objects (from the
nadir depth) with the target's paint, footprint and height against the reference views (see
:mod:`aerial`, the height against the side reference's outline top, :mod:`ground`; without a
depth image, paint colour and footprint alone, :mod:`colour_match`).

Annotations are few (five an episode) and each costs the UGV a drive, so during the first sweep
the UAV annotates only a detection scoring ``ANNOTATE_SCORE`` or more and remembers weaker ones;
once every node has been seen it flies back to the best one it remembers and annotates it (or the
best detection as good). The annotation message names the detection's ground point
(``near (x, y) m``, read by the heuristic UGV). Points the UGV rejected are remembered and not
annotated again.

``paint_only``: the ``paint-only`` policy, the floor of what the paint alone buys: the best match
of the target's paint, whatever its size, height or attributes, annotated as soon as it is seen.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from agos.agents.contract import Policy, action_for
from agos.agents.heuristic.aerial import MIN_SCORE, detect_vehicles_from_above
from agos.agents.heuristic.colour_match import AerialDetection, TargetProfile, detect_from_above, profile_from_references
from agos.agents.heuristic.ground import side_reference
from agos.agents.navigation import uav_route
from agos.runtime.camera import cell_of_pixel, pixel_to_ground
from agos.runtime.codec import decode_image
from agos.runtime.schemas import Action, ImageFrame, Observation, Role, Waypoint

SEEN_RADIUS_M = 41.0
REJECTED_RADIUS_M = 12.0
"""Around the centre of a rejected candidate whose annotated point the UAV does not know."""
REJECTED_POINT_RADIUS_M = 4.0
"""Around a rejected annotation's point: the vehicle the UGV turned down (a neighbour stays)."""
ANNOTATE_SCORE = 0.75
"""During the first sweep, the score a detection needs to be annotated at once."""
SAME_POINT_M = 4.0
"""Detections this close are one vehicle (in the memory of weaker ones)."""


@dataclass
class _Memory:
    profile: TargetProfile
    top_m: float | None
    """The side reference's outline top (None in ``paint_only``)."""
    seen: set[str] = field(default_factory=set)
    swept: bool = False
    """Every active node has been seen once."""
    annotated: list[tuple[float, float]] = field(default_factory=list)
    """The ground point of each annotation, in order (the candidates C001, C002, ...)."""
    remembered: list[tuple[tuple[float, float], float]] = field(default_factory=list)
    """Weaker detections of the first sweep: (ground point, best score)."""


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
            profile = profile_from_references(obs.references)
            top = None if self.paint_only else side_reference(obs.references, profile).top_m
            mem = self._memory[obs.episode_id] = _Memory(profile, top)
        here = np.asarray(obs.pose.position_world_m[:2])
        for wp in obs.active_uav_waypoints:
            if math.dist(wp.position_world_m[:2], here) <= SEEN_RADIUS_M:
                mem.seen.add(wp.waypoint_id)
        if not mem.swept and all(w.waypoint_id in mem.seen for w in obs.active_uav_waypoints):
            mem.swept = True

        if "ANNOTATE_CANDIDATE" in obs.legal_actions:
            found = self._target(obs, mem)
            if found is not None:
                cell, point = found
                mem.annotated.append(point)
                near = "" if self.paint_only else f" Look near ({point[0]:.1f}, {point[1]:.1f}) m."
                return action_for(obs, "ANNOTATE_CANDIDATE", cell=cell,
                                  message=f"Candidate in cell {cell}; please verify.{near}",
                                  rationale="paint colour, footprint and height match the reference")

        if "MOVE_TO_UAV_WAYPOINT" in obs.legal_actions and obs.waypoint_options:
            if self.paint_only:  # greedy, as the policy always flew
                goal = self._unseen_goals(obs, mem, here)[0]
                step = min(obs.waypoint_options,
                           key=lambda w: (math.dist(w.position_world_m[:2], goal.position_world_m[:2]), w.waypoint_id))
                return action_for(obs, "MOVE_TO_UAV_WAYPOINT", waypoint_id=step.waypoint_id,
                                  rationale=f"coverage towards {goal.waypoint_id}")
            routed = self._route_step(obs, mem, here)
            if routed is not None:
                return action_for(obs, "MOVE_TO_UAV_WAYPOINT", waypoint_id=routed[0], rationale=routed[1])
        return action_for(obs, "NO_RELIABLE_CANDIDATE")

    @staticmethod
    def _unseen_goals(obs: Observation, mem: _Memory, here: np.ndarray) -> list[Waypoint]:
        """Nodes not seen yet, nearest first (all of them again once every one has been seen)."""
        unseen = [w for w in obs.active_uav_waypoints if w.waypoint_id not in mem.seen]
        if not unseen:  # everything seen once: start a second sweep
            mem.seen = set()
            unseen = list(obs.active_uav_waypoints)
        return sorted(unseen, key=lambda w: (math.dist(w.position_world_m[:2], here), w.waypoint_id))

    def _route_step(self, obs: Observation, mem: _Memory, here: np.ndarray) -> tuple[str, str] | None:
        """(next node, why) on the shortest flight over the active nodes (:func:`uav_route`; a greedy
        step can shuttle between two nodes where the area is not convex): to the node nearest the
        best remembered detection once every node has been seen, else to the nearest node not seen
        yet that can be reached. Nodes out of reach count as seen."""
        nodes = obs.active_uav_waypoints
        if not nodes:
            return None
        at = min(nodes, key=lambda w: (math.dist(w.position_world_m[:2], here), w.waypoint_id))
        spacing = min(max(abs(w.position_world_m[0] - at.position_world_m[0]),
                          abs(w.position_world_m[1] - at.position_world_m[1])) for w in obs.waypoint_options)
        options = {w.waypoint_id for w in obs.waypoint_options}
        goals: list[tuple[Waypoint, str]] = []
        best = self._best_remembered(obs, mem) if mem.swept else None
        if best is not None:
            near = min(nodes, key=lambda w: (math.dist(w.position_world_m[:2], best[0]), w.waypoint_id))
            goals.append((near, f"back to a possible match near {near.waypoint_id}"))
        goals += [(w, f"coverage towards {w.waypoint_id}") for w in self._unseen_goals(obs, mem, here)]
        for goal, why in goals:
            if goal.waypoint_id == at.waypoint_id:
                continue
            route = uav_route(nodes, at.waypoint_id, goal.waypoint_id, spacing)
            if route is not None and len(route) > 1 and route[1] in options:
                return route[1], why
            mem.seen.add(goal.waypoint_id)
        return None

    def _refused(self, obs: Observation, mem: _Memory) -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
        """(points, centres) the UAV must not annotate again: the points of its rejected
        annotations, and the centres of rejected candidates whose point it does not know (in
        ``paint_only``, every rejected candidate's centre, as the policy always did)."""
        points, centres = [], []
        for c in obs.coordination.candidates:
            if c.status not in ("rejected", "false_confirm"):
                continue
            k = int(c.candidate_id[1:]) - 1 if c.candidate_id[1:].isdigit() else -1
            if 0 <= k < len(mem.annotated) and not self.paint_only:
                points.append(mem.annotated[k])
            else:
                centres.append((float(c.center_world_m[0]), float(c.center_world_m[1])))
        return points, centres

    def _best_remembered(self, obs: Observation, mem: _Memory) -> tuple[tuple[float, float], float] | None:
        points, centres = self._refused(obs, mem)
        left = [(p, s) for p, s in mem.remembered
                if all(math.dist(p, q) > SAME_POINT_M for q in points + mem.annotated)
                and all(math.dist(p, c) > REJECTED_RADIUS_M for c in centres)]
        return max(left, key=lambda ps: ps[1]) if left else None

    def _target(self, obs: Observation, mem: _Memory) -> tuple[str, tuple[float, float]] | None:
        """The cell and ground point to annotate now, if any (remembering weaker detections)."""
        frame = next((f for f in obs.images if f.kind == "rgb" and f.name == "nadir"), None)
        if frame is None or frame.intrinsics is None or frame.world_from_camera is None:
            return None
        rgb = decode_image(frame.data)
        pose = np.asarray(frame.world_from_camera).reshape(4, 4)
        points, centres = self._refused(obs, mem)
        intr = frame.intrinsics
        best = None if self.paint_only else self._best_remembered(obs, mem)
        if self.paint_only:
            needed = MIN_SCORE
        elif not mem.swept:
            needed = ANNOTATE_SCORE
        else:  # the best remembered, or a detection as good
            needed = MIN_SCORE if best is None else min(ANNOTATE_SCORE, best[1] - 0.05)
        for det in _detections(obs, frame, rgb, pose, mem.profile, self.paint_only, mem.top_m):
            ground = pixel_to_ground(det.u_px, det.v_px, pose, intr)
            if (any(math.dist(ground, p) <= REJECTED_POINT_RADIUS_M for p in points)
                    or any(math.dist(ground, c) <= REJECTED_RADIUS_M for c in centres)):
                continue
            if det.score >= needed or (best is not None and math.dist(ground, best[0]) <= SAME_POINT_M):
                return cell_of_pixel(det.u_px, det.v_px, intr.width_px, intr.height_px), ground
            self._remember(mem, ground, det.score)
        return None

    @staticmethod
    def _remember(mem: _Memory, point: tuple[float, float], score: float) -> None:
        for k, (p, s) in enumerate(mem.remembered):
            if math.dist(p, point) <= SAME_POINT_M:
                mem.remembered[k] = (p, max(s, score))
                return
        mem.remembered.append((point, score))


def _detections(obs: Observation, frame: ImageFrame, rgb: np.ndarray, pose: np.ndarray,
                profile: TargetProfile, paint_only: bool, top_m: float | None = None) -> list[AerialDetection]:
    """The nadir view's matches, best first: by shape and context when its depth image came with
    it, else by colour and footprint."""
    assert frame.intrinsics is not None
    depth = next((f for f in obs.images if f.kind == "depth" and f.name == frame.name), None)
    if depth is None:
        return detect_from_above(rgb, profile, altitude_m=float(pose[2, 3]), fy_px=frame.intrinsics.fy_px)
    depth_m = decode_image(depth.data).astype(np.float32) * float(depth.depth_scale_m or 1.0)
    return detect_vehicles_from_above(rgb, depth_m, profile, intrinsics=frame.intrinsics, world_from_camera=pose,
                                      paint_only=paint_only, top_m=top_m)
