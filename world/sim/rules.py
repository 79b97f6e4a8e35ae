"""The task rules: which actions a role may take now, and what each action does.

Contract: :func:`refusal` and :func:`uav_legal` / :func:`ugv_legal` only read the state.
:func:`apply_action` applies one checked action to the :class:`~agos.world.sim.state.EpisodeState`
at its ``sim_time_s``: it moves the role, sets when it is ready again, creates candidates and
changes their status (freezing the UAV after an annotation when the configuration says
``frozen``), and ends the episode on CONFIRM (so there is at most :data:`MAX_CONFIRMATIONS`). It
raises :class:`IllegalAction` (the engine turns it into a logged WAIT) before changing anything
when the action's arguments are not valid now. It renders only what the action itself sees
(STOP_OBSERVE's six views, the CONFIRM checker's line-of-sight rays) and never sends through a
link: syncs and messages are the engine's.

The two tools the paper ablates live here: E2A (Ego-to-Allo projection, :func:`_project_cell`:
an annotated grid cell becomes a polygon on the ground; without it, the footprint's centre,
:mod:`agos.world.sim.projection`) and RGPP (road-graph path planning,
:func:`approach_anchor`: a candidate gets the road anchor GO_TO_CANDIDATE drives to). In runs
with the oracle's hints a candidate that contains the target is approached where the CONFIRM
checker would accept (:func:`_oracle_approach`): the oracle's shortest road path.
"""

from __future__ import annotations

import copy
import math

import networkx as nx
import numpy as np

from agos.runtime.geometry import point_in_polygon
from agos.runtime.schemas import Action, ActionName, Candidate, CandidateStatus, Observation, Role, Waypoint
from agos.world.sim import sensors
from agos.world.sim.confirm import ConfirmEvidence, check_confirm
from agos.world.sim.evidence import line_of_sight, nearest_verifying_anchor, target_points
from agos.world.sim.options import heading_after, shortest_path
from agos.world.sim.projection import candidate_region
from agos.world.sim.state import EpisodeState
from agos.world.towns.roadgraph import RoadGraphs


class IllegalAction(ValueError):
    """The action is not legal now; the text says why (it becomes a WAIT)."""


MAX_CONFIRMATIONS = 1
"""CONFIRMs the UGV may make in an episode: the first one ends it, accepted or not. The world sends
it with the count used (``CoordinationState.max_confirmations`` / ``confirmations_used``): the
UGV prompt's remaining confirmation budget (docs/AGENTS.md)."""


# ----- legality ---------------------------------------------------------------------------------
def uav_legal(st: EpisodeState, options: list[Waypoint]) -> list[ActionName]:
    """The UAV's legal actions. While its own view holds an open candidate it may not annotate; with
    ``uav_during_verification = "active"`` it may then only move or wait (the ``frozen`` UAV is asked
    then only after ``max_freeze_s``, and keeps NO_RELIABLE_CANDIDATE as before)."""
    verifying = st.active_candidate("uav") is not None
    legal: list[ActionName] = ["MOVE_TO_UAV_WAYPOINT"] if options else []
    if st.cfg.tools.candidates and not verifying and len(st.candidates) < st.cfg.max_annotations:
        legal.append("ANNOTATE_CANDIDATE")
    if verifying and st.cfg.uav_during_verification == "active":
        return [*legal, "WAIT"]
    return [*legal, "NO_RELIABLE_CANDIDATE", "WAIT"]


def ugv_legal(st: EpisodeState, options: list[Waypoint]) -> list[ActionName]:
    legal: list[ActionName] = ["MOVE_TO_ROAD_WAYPOINT"] if options else []
    if st.active_candidate("ugv") is not None and st.cfg.tools.rgpp:
        legal.append("GO_TO_CANDIDATE")
    legal += ["STOP_OBSERVE", "CONFIRM"]
    if st.active_candidate("ugv") is not None or st.ugv.mode == "stop_6view":
        legal.append("REJECT")
    return [*legal, "WAIT"]


def refusal(role: Role, obs: Observation, action: Action | None) -> str | None:
    """Why ``action`` cannot answer ``obs`` at all (missing, another decision, not legal now);
    ``None`` when it may be applied."""
    if action is None:
        return "no action before the deadline"
    if action.decision_index != obs.decision_index or action.role != role:
        return f"action answers decision {action.role}#{action.decision_index}, not {role}#{obs.decision_index}"
    if action.action not in obs.legal_actions:
        return f"{action.action} is not legal now (legal: {', '.join(obs.legal_actions)})"
    return None


# ----- effects ----------------------------------------------------------------------------------
def apply_action(st: EpisodeState, role: Role, action: Action, obs: Observation) -> str | None:
    """Apply a legal ``action`` of ``role``; returns the candidate it concerns, if any."""
    return (_apply_uav if role == "uav" else _apply_ugv)(st, action, obs)


def wait(st: EpisodeState, role: Role) -> None:
    """WAIT (and every fallback): ready again after ``wait_max_s`` unless woken earlier."""
    agent = st.uav if role == "uav" else st.ugv
    agent.ready_at = st.sim_time_s + st.cfg.wait_max_s
    agent.waiting = True


def _apply_uav(st: EpisodeState, action: Action, obs: Observation) -> str | None:
    uav, now = st.uav, st.sim_time_s
    uav.waiting = False
    if action.action == "MOVE_TO_UAV_WAYPOINT":
        if action.waypoint_id not in {w.waypoint_id for w in obs.waypoint_options}:
            raise IllegalAction(f"waypoint {action.waypoint_id!r} is not a UAV option now")
        node = st.town.uav_grid.nodes[action.waypoint_id]
        dist = math.dist(uav.position[:2], node.position_world_m[:2])
        uav.node, uav.position = node.node_id, node.position_world_m
        uav.ready_at = now + dist / st.cfg.uav_speed_mps
        return None
    if action.action == "ANNOTATE_CANDIDATE":
        try:
            cell = (action.cell or "").upper()
            sensors.parse_cell(cell)
        except ValueError as exc:
            raise IllegalAction(str(exc)) from None
        polygon, centre = _project_cell(st, cell)
        approach = _oracle_approach(st, polygon) if st.cfg.tools.oracle else None
        if approach is None:
            approach = approach_anchor(st.roads, st.ugv.node, centre)
        cand = Candidate(candidate_id=f"C{len(st.candidates) + 1:03d}", cell=cell,
                         polygon_world_m=[(round(x, 3), round(y, 3)) for x, y in polygon],
                         center_world_m=(round(centre[0], 3), round(centre[1], 3)), status="pending",
                         created_sim_time_s=now,
                         approach_waypoint_id=RoadGraphs.anchor_id(approach) if approach is not None else None)
        st.candidates.append(cand)
        st.channel.views["uav"].candidates[cand.candidate_id] = copy.copy(cand)
        if st.cfg.uav_during_verification == "frozen":
            uav.frozen, uav.frozen_since = True, now
        uav.ready_at = now + st.cfg.short_action_s
        return cand.candidate_id
    if action.action == "NO_RELIABLE_CANDIDATE":
        uav.ready_at = now + st.cfg.short_action_s
        return None
    wait(st, "uav")
    return None


def _apply_ugv(st: EpisodeState, action: Action, obs: Observation) -> str | None:
    ugv, now = st.ugv, st.sim_time_s
    ugv.waiting = False
    kind = action.action
    if kind == "MOVE_TO_ROAD_WAYPOINT":
        if action.waypoint_id not in {w.waypoint_id for w in obs.waypoint_options}:
            raise IllegalAction(f"waypoint {action.waypoint_id!r} is not a road option now")
        _drive_to(st, RoadGraphs.parse_anchor_id(action.waypoint_id))
        return None
    if kind == "GO_TO_CANDIDATE":
        cand = _candidate(st, action.candidate_id)
        if cand.approach_waypoint_id is None:
            raise IllegalAction(f"candidate {cand.candidate_id} has no reachable road approach")
        _drive_to(st, RoadGraphs.parse_anchor_id(cand.approach_waypoint_id))
        _set_status(st, cand.candidate_id, "arrived")
        return cand.candidate_id
    if kind == "STOP_OBSERVE":
        ugv.mode, ugv.fresh_stop = "stop_6view", True
        ugv.six = sensors.six_views(st.scene, st.ugv_xy(), ugv.heading_rad, st.cfg.cameras)
        st.ground_visible = not check_confirm(confirm_evidence(st), st.cfg.confirm_at_view_size())
        st.ground_observed |= st.ground_visible
        ugv.ready_at = now + st.cfg.stop_observe_s
        return None
    if kind == "CONFIRM":
        st.n_confirm += 1
        reasons = check_confirm(confirm_evidence(st), st.cfg.confirm_at_view_size())
        active = st.active_candidate("ugv")
        if active is not None:
            _set_status(st, active.candidate_id, "false_confirm" if reasons else "confirmed")
        st.termination = "false_confirm" if reasons else "confirmed"
        st.confirm_failure = "; ".join(reasons) or None
        return active.candidate_id if active else None
    if kind == "REJECT":
        rejected = st.active_candidate("ugv") if action.candidate_id is None else _candidate(st, action.candidate_id)
        ugv.mode, ugv.fresh_stop = "driving", False
        ugv.ready_at = now + st.cfg.short_action_s
        if rejected is not None:
            _set_status(st, rejected.candidate_id, "rejected")  # the UAV learns it through the link
            return rejected.candidate_id
        return None
    wait(st, "ugv")
    return None


def _candidate(st: EpisodeState, candidate_id: str | None) -> Candidate:
    """A candidate the UGV knows of (its own view) and can still act on."""
    cand = st.channel.views["ugv"].candidates.get(candidate_id or "")
    if cand is None:
        raise IllegalAction(f"no candidate {candidate_id!r} known to the UGV")
    if cand.status not in ("pending", "arrived"):
        raise IllegalAction(f"candidate {candidate_id} is {cand.status}")
    return cand


def _set_status(st: EpisodeState, candidate_id: str, status: CandidateStatus) -> None:
    """A UGV status change: in the truth and in the UGV's own view at once."""
    for cand in st.candidates:
        if cand.candidate_id == candidate_id:
            cand.status = status
    view = st.channel.views["ugv"].candidates.get(candidate_id)
    if view is not None:
        view.status = status


def _drive_to(st: EpisodeState, target: int) -> None:
    ugv, roads = st.ugv, st.roads
    try:
        path = shortest_path(roads, ugv.node, target)
    except nx.NetworkXNoPath:
        raise IllegalAction(f"no road path to {RoadGraphs.anchor_id(target)}") from None
    length = roads.path_length_m(path)
    ugv.route.extend(path[1:])
    ugv.node = target
    ugv.heading_rad = heading_after(roads, path, ugv.heading_rad)
    ugv.path_length_m += length
    ugv.mode, ugv.fresh_stop, ugv.six = "driving", False, []
    ugv.ready_at = st.sim_time_s + max(length / st.cfg.ugv_speed_mps, st.cfg.short_action_s)


# ----- E2A and RGPP -----------------------------------------------------------------------------
def _project_cell(st: EpisodeState, cell: str) -> tuple[list[tuple[float, float]], tuple[float, float]]:
    """The candidate's ground region and centre for the annotated cell of the UAV's last nadir view
    (:func:`~agos.world.sim.projection.candidate_region`): with E2A the cell's ground polygon; without,
    the cell is metadata only and the candidate is the centre of the view's footprint, a point."""
    nadir = st.uav.last_nadir
    assert nadir is not None
    return candidate_region(cell, nadir.world_from_camera, nadir.intrinsics, e2a=st.cfg.tools.e2a)


def approach_anchor(roads: RoadGraphs, node: int, centre: tuple[float, float], radius_m: float = 20.0) -> int | None:
    """Road-graph path planning from a UGV at ``node``: the reachable decision anchor that best
    trades closeness to the candidate centre against road distance (1 m closer is worth 20 m of
    driving); the nearest reachable anchor if none lies within ``radius_m``. Public so that a plan
    can tell where GO_TO_CANDIDATE will drive (agos.world.expert)."""
    lengths = nx.single_source_dijkstra_path_length(roads.fine, node, weight="length_m")
    ids, xy = roads.anchor_array()
    dist = np.hypot(xy[:, 0] - centre[0], xy[:, 1] - centre[1])
    near = [(float(d) + 0.05 * lengths[int(n)], int(n)) for n, d in zip(ids, dist, strict=True)
            if d <= radius_m and int(n) in lengths]
    if near:
        return min(near)[1]
    return next((int(ids[i]) for i in np.argsort(dist) if int(ids[i]) in lengths), None)


def _oracle_approach(st: EpisodeState, polygon: list[tuple[float, float]]) -> int | None:
    """The oracle tool's road-graph path planning (runs with the oracle's hints only): a candidate
    that contains the target is approached at the anchor nearest by road from the UGV where
    STOP_OBSERVE then CONFIRM is accepted (ground truth), so GO_TO_CANDIDATE drives the shortest
    road path to a verifying pose. None for a candidate without the target, or none verifying."""
    if not point_in_polygon(st.target_xy, polygon):
        return None
    t = st.spec.target
    found = nearest_verifying_anchor(st.scene, st.town, st.ugv.node, st.ugv.heading_rad, st.target_uid,
                                     t.position_world_m, t.yaw_rad, st.cfg.confirm_at_view_size(), st.cfg.cameras)
    return None if found is None else found[0]


# ----- CONFIRM evidence -------------------------------------------------------------------------
def confirm_evidence(st: EpisodeState) -> ConfirmEvidence:
    """Checker evidence for the UGV as it is now (its last six views)."""
    xy = st.ugv_xy()
    return ConfirmEvidence(
        fresh_stop=st.ugv.fresh_stop,
        max_target_pixels=max((sensors.target_pixels(s, st.target_uid) for s in st.ugv.six), default=0),
        distance_m=math.dist(xy, st.target_xy), line_of_sight=_line_of_sight(st, xy))


def _line_of_sight(st: EpisodeState, xy: tuple[float, float]) -> bool:
    t = st.spec.target
    return line_of_sight(st.scene, xy, st.target_uid, target_points(t.position_world_m, t.yaw_rad))
