"""What an episode leaves behind: its :class:`EpisodeRecord`, and SPL's shortest path.

Contract: :func:`shortest_confirmable_path` is computed once when the episode is set up (before
any decision, target and look-alikes already in the scene): the road distance from the UGV
start to the nearest fine node from which STOP_OBSERVE then CONFIRM would be accepted, or
``None`` when no such node is found within ``max_checks`` renders. It renders only the views
facing the target and changes nothing. :func:`episode_record` reads the finished
:class:`~agos.world.sim.state.EpisodeState` and changes nothing either.
"""

from __future__ import annotations

import math

import networkx as nx

from agos.runtime.episode_config import CameraConfig, ConfirmConfig
from agos.runtime.geometry import distance_to_polygon
from agos.runtime.schemas import CandidateOutcome, EpisodeRecord, VehicleSpec
from agos.runtime.traces import trace_stats
from agos.world.sim.confirm import check_confirm
from agos.world.sim.evidence import ground_evidence, line_of_sight, target_points
from agos.world.sim.scene import Scene
from agos.world.sim.state import EpisodeState
from agos.world.towns.asset import Town


def shortest_confirmable_path(scene: Scene, town: Town, start_node: int, target: VehicleSpec, target_uid: int,
                              confirm: ConfirmConfig, cameras: CameraConfig,
                              max_checks: int = 30) -> float | None:
    """SPL's shortest path: road distance from ``start_node`` to the nearest fine node from
    which a STOP_OBSERVE then CONFIRM would be accepted (nodes in Dijkstra order, ties by node id;
    distance and line of sight are checked before rendering)."""
    lengths = nx.single_source_dijkstra_path_length(town.roads.fine, start_node, weight="length_m")
    pos = town.roads.positions_world_m
    target_xy = (target.position_world_m[0], target.position_world_m[1])
    points = target_points(target.position_world_m, target.yaw_rad)
    checks = 0
    for node, dist in sorted(lengths.items(), key=lambda kv: (kv[1], kv[0])):
        xy = (float(pos[node][0]), float(pos[node][1]))
        if math.dist(xy, target_xy) > confirm.max_distance_m:
            continue
        if not line_of_sight(scene, xy, target_uid, points):
            continue
        checks += 1
        evidence = ground_evidence(scene, town, node, target_uid, points, target_xy, cameras)
        if not check_confirm(evidence, confirm):
            return round(float(dist), 3)
        if checks >= max_checks:
            break
    return None


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
        link=st.channel.stats(st.candidates), ledger=st.channel.ledger, confirm_rejection=st.confirm_failure,
        tools=cfg.tools.model_dump(),
        config=cfg.model_dump(mode="json"), config_hash=cfg.config_hash(),
        agent_stats=trace_stats(st.traces), decision_traces=st.traces)
