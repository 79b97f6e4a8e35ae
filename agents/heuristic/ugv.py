"""Heuristic UGV: drive to the UAV's candidate, stop, look around, confirm, look again or reject.

No candidate: WAIT (the world wakes it when the coordination state changes). Pending
candidate: GO_TO_CANDIDATE. Arrived: STOP_OBSERVE. Six views, judged by
:func:`~agos.agents.heuristic.ground.judge_views` against the reference views: CONFIRM when an
object within reach stands on the street with the target's paint (its brightness judged in the
light it stands in), its outline's top and its paint's top, its paint's share per height band and
no more than its length. A CONFIRM ends the episode (the confirmation budget is one), so the UGV
confirms only what it has seen whole and near; otherwise it may stop again for a second look, up
to ``MAX_LOOKS`` STOP_OBSERVEs a candidate:

- at a *lead* (an object that agrees with the target as far as it could be seen, but from too far
  or cut by the top of the view): from the road option nearest a good viewing distance to it;
- at the point the UAV named in its message (:data:`UAV_POINT`; else the candidate's centre) when
  that point is hidden from the six views (a vehicle parked next to the UGV blocks them).

Else REJECT. ``paint_only`` (the ``paint-only`` policy): CONFIRM on the first object of the
target's paint in view, REJECT otherwise, no second look.
"""

from __future__ import annotations

import math
import re

import numpy as np

from agos.agents.contract import Policy, action_for
from agos.agents.heuristic.colour_match import TargetProfile, profile_from_references
from agos.agents.heuristic.ground import TOO_CLOSE_M, GroundView, SideReference, find_target, judge_views, side_reference
from agos.agents.navigation import Navigator
from agos.runtime.codec import decode_image
from agos.runtime.geometry import point_in_polygon
from agos.runtime.schemas import Action, Candidate, MessageRecord, Observation, Role, Waypoint

MIN_PIXELS = 80
APPROACH_WITHIN_M = 12.0
MAX_LOOKS = 3
"""STOP_OBSERVEs the UGV makes for one candidate before it rejects it."""
VIEWING_DISTANCE_M = 10.0
"""Where the UGV likes to stand from what it looks at again: near enough that a pixel is 5 cm,
far enough that a box truck's top is in view."""
MIN_VIEWING_DISTANCE_M = 6.0
"""Never nearer than this to what it looks at (a bus seen end-on is 5.5 m long from its middle)."""
LEAD_WELL_SEEN_M = 10.0
"""A lead nearer than this was seen as well as the UGV can see it: no second look for it."""
MIN_MOVE_M = 3.0
"""A second look is from a road option at least this far from every place the UGV looked from."""
UAV_POINT = re.compile(r"near \((-?\d+(?:\.\d+)?), (-?\d+(?:\.\d+)?)\)")
"""The point a heuristic UAV names in its annotation message (``... near (x, y) m``)."""
HIDDEN_BELOW = 0.4
"""A point counts as hidden when fewer than this share of the probes around it are in sight."""
PROBE_OFFSETS_M = ((0.0, 0.0), (1.5, 0.0), (-1.5, 0.0), (0.0, 1.5), (0.0, -1.5))
PROBE_HEIGHTS_M = (0.5, 1.1)
OCCLUDER_MARGIN_M = 0.5
"""A probe is in sight when the view's depth there reaches to within half the target's length and
this of the probe (the vehicle at the point hides its own middle)."""
SIGHT_RANGE_M = 45.0


def uav_point(messages: list[MessageRecord], polygon_world_m: list[tuple[float, float]]) -> tuple[float, float] | None:
    """The latest point a UAV message names (``near (x, y)``) inside a candidate's ground polygon, if any."""
    for msg in reversed(messages):
        if msg.sender != "uav":
            continue
        m = UAV_POINT.search(msg.text)
        if m is not None:
            p = (float(m.group(1)), float(m.group(2)))
            if point_in_polygon(p, polygon_world_m):
                return p
    return None


def point_in_sight(views: list[GroundView], point_xy: tuple[float, float], *, half_length_m: float) -> bool:
    """Whether the six views see the place ``point_xy`` (within ``SIGHT_RANGE_M``): at least
    ``HIDDEN_BELOW`` of the probes (0.5 and 1.1 m up, at and 1.5 m around the point) project into a
    view whose depth there reaches within ``half_length_m`` (the target's) and ``OCCLUDER_MARGIN_M``
    of the probe: nothing but a vehicle standing at the point is in front of it."""
    seen = total = 0
    for dx, dy in PROBE_OFFSETS_M:
        for z in PROBE_HEIGHTS_M:
            total += 1
            probe = np.array([point_xy[0] + dx, point_xy[1] + dy, z, 1.0])
            for v in views:
                cam = np.linalg.inv(v.world_from_camera) @ probe
                if cam[2] <= 0.1 or cam[2] > SIGHT_RANGE_M:
                    continue
                u = v.intrinsics.fx_px * cam[0] / cam[2] + v.intrinsics.cx_px
                w = v.intrinsics.fy_px * cam[1] / cam[2] + v.intrinsics.cy_px
                h, wd = v.depth_m.shape
                if not (0 <= u < wd and 0 <= w < h):
                    continue
                if v.depth_m[int(w), int(u)] >= cam[2] - half_length_m - OCCLUDER_MARGIN_M:
                    seen += 1
                    break
    return seen >= HIDDEN_BELOW * total


class HeuristicUgv(Policy):
    role: Role = "ugv"
    name = "heuristic"

    def __init__(self, *, paint_only: bool = False) -> None:
        self._profiles: dict[str, tuple[TargetProfile, SideReference]] = {}
        self._looked_from: dict[str, dict[str, list[tuple[float, float]]]] = {}
        """Per episode and candidate, where the UGV made its STOP_OBSERVEs."""
        self.nav = Navigator()
        self.paint_only = paint_only
        self.name = "paint-only" if paint_only else "heuristic"

    def end_episode(self, episode_id: str) -> None:
        self._profiles.pop(episode_id, None)
        self._looked_from.pop(episode_id, None)
        self.nav.forget(episode_id)

    def act(self, obs: Observation) -> Action:
        refs = self._profiles.get(obs.episode_id)
        if refs is None:
            profile = profile_from_references(obs.references)
            refs = self._profiles[obs.episode_id] = (profile, side_reference(obs.references, profile))
        active = next((c for c in obs.coordination.candidates if c.status in ("pending", "arrived")), None)
        here = (float(obs.pose.position_world_m[0]), float(obs.pose.position_world_m[1]))

        if obs.mode == "stop_6view":
            views = _views(obs)
            if self.paint_only:
                if find_target(views, refs[0], min_pixels=MIN_PIXELS, paint_only=True):
                    return action_for(obs, "CONFIRM", candidate_id=active.candidate_id if active else None,
                                      message="Target confirmed.", rationale="the target's paint nearby")
            else:
                judged = judge_views(views, *refs, min_pixels=MIN_PIXELS)
                if judged.matches:
                    return action_for(obs, "CONFIRM", candidate_id=active.candidate_id if active else None,
                                      message="Target confirmed.",
                                      rationale="paint, outline and paint tops, paint bands and length match nearby")
                if active is not None:
                    leads = [(d.x_m, d.y_m) for d in judged.leads
                             if d.distance_m > LEAD_WELL_SEEN_M or d.distance_m < TOO_CLOSE_M]
                    step = self._second_look(obs, active, views, refs[0], leads)
                    if step is not None:
                        return action_for(obs, "MOVE_TO_ROAD_WAYPOINT", waypoint_id=step.waypoint_id,
                                          message=f"{active.candidate_id}: taking a second look.",
                                          rationale="a possible match seen from too far, or the candidate hidden")
            if active is not None:
                return action_for(obs, "REJECT", candidate_id=active.candidate_id,
                                  message=f"{active.candidate_id} is not the target; keep searching.")
        if active is not None and active.status == "pending" and "GO_TO_CANDIDATE" in obs.legal_actions:
            return action_for(obs, "GO_TO_CANDIDATE", candidate_id=active.candidate_id,
                              message=f"Driving to {active.candidate_id}.")
        if active is not None and active.status == "pending" and obs.mode == "driving":
            # No road-graph path planning: approach by the options' distance hints, then stop.
            if math.dist(here, active.center_world_m) <= APPROACH_WITHIN_M:
                return self._stop(obs, active, here)
            step_id = self.nav.towards(obs, active.center_world_m)
            if step_id is not None:
                return action_for(obs, "MOVE_TO_ROAD_WAYPOINT", waypoint_id=step_id)
        if active is not None and active.status == "arrived" and obs.mode == "driving":
            return self._stop(obs, active, here)
        return action_for(obs, "WAIT")

    def _stop(self, obs: Observation, cand: Candidate, here: tuple[float, float]) -> Action:
        self._looked_from.setdefault(obs.episode_id, {}).setdefault(cand.candidate_id, []).append(here)
        return action_for(obs, "STOP_OBSERVE")

    def _second_look(self, obs: Observation, cand: Candidate, views: list[GroundView], profile: TargetProfile,
                     leads_xy: list[tuple[float, float]]) -> Waypoint | None:
        """The road option to look again from, or None (reject): towards the lead nearest the UAV's
        point, else towards that point when the views do not see it."""
        looked = self._looked_from.get(obs.episode_id, {}).get(cand.candidate_id, [])
        if len(looked) >= MAX_LOOKS:
            return None
        centre = (float(cand.center_world_m[0]), float(cand.center_world_m[1]))
        point = uav_point(obs.coordination.messages, cand.polygon_world_m) or centre
        here = (float(obs.pose.position_world_m[0]), float(obs.pose.position_world_m[1]))
        if leads_xy:
            goal = min(leads_xy, key=lambda xy: math.dist(xy, point))
            near = math.dist(here, goal)
            reach = near - MIN_MOVE_M if near > TOO_CLOSE_M else SIGHT_RANGE_M  # nearer to the lead, or away
        elif not point_in_sight(views, point, half_length_m=(profile.body_length_m or profile.length_m) / 2):
            goal = point
            reach = max(math.dist(here, goal), LEAD_WELL_SEEN_M)  # elsewhere, not further
        else:
            return None
        options = [w for w in obs.waypoint_options
                   if all(math.dist(w.position_world_m[:2], p) >= MIN_MOVE_M for p in looked)
                   and MIN_VIEWING_DISTANCE_M <= math.dist(w.position_world_m[:2], goal) <= reach]
        if not options:
            return None
        return min(options, key=lambda w: (abs(math.dist(w.position_world_m[:2], goal) - VIEWING_DISTANCE_M),
                                           w.waypoint_id))


def _views(obs: Observation) -> list[GroundView]:
    """The observation's RGB views with their depth images, intrinsics and poses."""
    depth_frames = {f.name: f for f in obs.images if f.kind == "depth"}
    views = []
    for frame in obs.images:
        d = depth_frames.get(frame.name)
        if frame.kind != "rgb" or d is None or frame.intrinsics is None or frame.world_from_camera is None:
            continue
        depth_m = decode_image(d.data).astype(np.float32) * float(d.depth_scale_m or 1.0)
        views.append(GroundView(frame.name, decode_image(frame.data), depth_m, frame.intrinsics,
                                np.asarray(frame.world_from_camera).reshape(4, 4)))
    return views
