"""What an episode leaves behind: its :class:`EpisodeRecord`, and SPL's shortest path.

Contract: :func:`shortest_confirmable_path` is computed once when the episode is set up (before
any decision, target and look-alikes already in the scene): the road distance from the UGV
start to the nearest decision anchor (the poses a UGV can stop at) from which STOP_OBSERVE then
CONFIRM would be accepted, or ``None`` when none can be reached. It renders only the views facing
the target and changes nothing. :func:`episode_record` reads the finished
:class:`~agos.world.sim.state.EpisodeState` and changes nothing either.
"""

from __future__ import annotations

import math

from agos.runtime.episode_config import CameraConfig, ConfirmConfig
from agos.runtime.geometry import distance_to_polygon
from agos.runtime.model_link import Exchange
from agos.runtime.provenance import provenance
from agos.runtime.schemas import (
    ActionName,
    CandidateOutcome,
    EpisodeRecord,
    LoggedStep,
    PoseErrorStats,
    Role,
    VehicleSpec,
)
from agos.runtime.traces import trace_stats, trace_usage
from agos.world.sim.evidence import nearest_verifying_anchor
from agos.world.sim.scene import Scene
from agos.world.sim.state import EpisodeState
from agos.world.towns.asset import Town


def shortest_confirmable_path(scene: Scene, town: Town, start_node: int, target: VehicleSpec, target_uid: int,
                              confirm: ConfirmConfig, cameras: CameraConfig) -> float | None:
    """SPL's shortest path: road distance from ``start_node`` (the UGV's start, with the road's
    heading there) to the nearest pose the UGV can take where a STOP_OBSERVE then CONFIRM would
    be accepted: a decision anchor, judged with the heading the UGV arrives with
    (:func:`~agos.world.sim.evidence.nearest_verifying_anchor`, the oracle's goal)."""
    found = nearest_verifying_anchor(scene, town, start_node, town.roads.heading_at(start_node), target_uid,
                                     target.position_world_m, target.yaw_rad, confirm, cameras)
    return None if found is None else round(found[1], 3)


def episode_record(st: EpisodeState, wall_time_s: float) -> EpisodeRecord:
    """The record of a finished episode (``status="finished"``)."""
    outcomes = [CandidateOutcome(
        candidate_id=c.candidate_id, cell=c.cell, center_world_m=c.center_world_m, status=c.status,
        distance_to_polygon_m=round(distance_to_polygon(st.target_xy, c.polygon_world_m), 3),
        center_error_m=round(math.dist(c.center_world_m, st.target_xy), 3)) for c in st.candidates]
    cfg = st.cfg
    return EpisodeRecord(
        run_id=st.run_id, episode_id=st.spec.episode_id, difficulty=st.spec.difficulty,
        status="finished", termination=st.termination or "error",
        success=st.termination == "confirmed", ground_observed=st.ground_observed,
        n_confirm=st.n_confirm, ugv_path_length_m=round(st.ugv.path_length_m, 3),
        shortest_path_length_m=st.shortest_path_m,
        final_distance_m=round(math.dist(st.ugv_xy(), st.target_xy), 3),
        uav_budget=st.spec.decision_budget, uav_first_visible_step=st.tau, candidates=outcomes,
        decisions_uav=st.uav.decisions, decisions_ugv=st.ugv.decisions, fallbacks=st.fallbacks,
        sim_time_s=round(st.sim_time_s, 3), wall_time_s=round(wall_time_s, 3), worker_id=st.worker_id,
        town_id=st.town.town_id, asset_sha256=st.town.sha256, seed=st.spec.seed,
        renderer=st.scene.renderer_name(), comm_profile=cfg.comm.name, timing_mode=cfg.timing_mode,
        pose_error_profile=cfg.pose_error.name, pose_error=pose_error_stats(st),
        model_link=None if st.model_link is None else st.model_link.stats(),
        link=st.channel.stats(st.candidates), ledger=st.channel.ledger, confirm_rejection=st.confirm_failure,
        tools=cfg.tools.model_dump(),
        config=cfg.model_dump(mode="json"), config_hash=cfg.config_hash(),
        agent_stats=trace_stats(st.traces), usage=trace_usage(st.traces),
        decision_traces=st.traces, step_log=st.step_log, provenance=provenance())


def pose_error_stats(st: EpisodeState) -> dict[str, PoseErrorStats]:
    """Per role, the horizontal error of the pose it was shown at its decisions (empty when exact)."""
    if st.cfg.pose_error.exact:
        return {}
    out: dict[str, PoseErrorStats] = {}
    for role, fixes in st.decision_fixes.items():
        if fixes:
            errors = [f.horizontal_m for f in fixes]
            out[role] = PoseErrorStats(mean_m=round(sum(errors) / len(errors), 3), max_m=round(max(errors), 3),
                                       degraded_share=round(sum(f.degraded for f in fixes) / len(fixes), 3))
    return out


def decision_pose_error_m(st: EpisodeState, role: Role) -> float | None:
    """The horizontal error of the pose ``role`` was shown at its latest decision (None when exact)."""
    fixes = st.decision_fixes[role]
    return round(fixes[-1].horizontal_m, 3) if fixes and not st.cfg.pose_error.exact else None


def logged_step(st: EpisodeState, role: Role, decision_index: int, applied: ActionName, candidate_id: str | None,
                route_before: int, trip: Exchange | None = None) -> LoggedStep:
    """The step log's entry for a decision just applied: where ``role`` is now, and for a UGV that
    drove, the road it drove (its route had ``route_before`` nodes before the decision); ``trip``: what
    its request and reply met on the link to the model (None: no link, or no model asked)."""
    x, y = st.uav.position[:2] if role == "uav" else st.ugv_xy()
    road: list[tuple[float, float]] = []
    if role == "ugv" and len(st.ugv.route) > route_before:
        nodes = st.ugv.route[max(0, route_before - 1):]
        road = _simplified([(float(p[0]), float(p[1])) for p in st.roads.positions_world_m[nodes]])
    polygon: list[tuple[float, float]] = []
    if applied == "ANNOTATE_CANDIDATE" and candidate_id is not None:
        polygon = next(([(round(px, 3), round(py, 3)) for px, py in c.polygon_world_m]
                        for c in st.candidates if c.candidate_id == candidate_id), [])
    return LoggedStep(role=role, decision_index=decision_index, sim_time_s=round(st.sim_time_s, 3), applied=applied,
                      position_world_m=(round(float(x), 3), round(float(y), 3)), road_path_world_m=road,
                      candidate_id=candidate_id, candidate_polygon_world_m=polygon,
                      pose_error_m=decision_pose_error_m(st, role),
                      model_link_s=None if trip is None else round(trip.link_s, 4),
                      model_bytes_up=0 if trip is None else trip.bytes_up,
                      model_bytes_down=0 if trip is None else trip.bytes_down)


def _simplified(points: list[tuple[float, float]], tolerance_m: float = 0.25) -> list[tuple[float, float]]:
    """``points`` as a polyline that stays within ``tolerance_m`` of them (Douglas-Peucker; the ends
    always kept), rounded to millimetres."""
    keep = [False] * len(points)
    keep[0] = keep[-1] = True
    spans = [(0, len(points) - 1)]
    while spans:
        a, c = spans.pop()
        (ax, ay), (cx, cy) = points[a], points[c]
        span = math.hypot(cx - ax, cy - ay)
        worst, where = 0.0, -1
        for b in range(a + 1, c):
            bx, by = points[b]
            off = (abs((cx - ax) * (by - ay) - (cy - ay) * (bx - ax)) / span) if span > 1e-9 else math.hypot(bx - ax, by - ay)
            if off > worst:
                worst, where = off, b
        if worst > tolerance_m:
            keep[where] = True
            spans += [(a, where), (where, c)]
    return [(round(x, 3), round(y, 3)) for (x, y), k in zip(points, keep, strict=True) if k]
