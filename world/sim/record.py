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
from agos.runtime.schemas import CandidateOutcome, EpisodeRecord, VehicleSpec
from agos.runtime.traces import trace_stats
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
        link=st.channel.stats(st.candidates), ledger=st.channel.ledger, confirm_rejection=st.confirm_failure,
        tools=cfg.tools.model_dump(),
        config=cfg.model_dump(mode="json"), config_hash=cfg.config_hash(),
        agent_stats=trace_stats(st.traces), decision_traces=st.traces)
