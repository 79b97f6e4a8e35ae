"""The expert's mTSP instance of an episode, from the town and the episode alone (no rendering):
the waypoints of :mod:`agos.world.expert.coverage` still to search, on the roles' metric closures
(:mod:`agos.world.expert.closure`), from where each role is and when it is free.
"""

from __future__ import annotations

from dataclasses import dataclass

from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.schemas import EpisodeSpec
from agos.world.expert.closure import uav_times, ugv_times
from agos.world.expert.coverage import CoverageProblem, coverage_problem
from agos.world.expert.mtsp import MtspInstance
from agos.world.towns.asset import Town


@dataclass(frozen=True)
class RoutingProblem:
    """An :class:`MtspInstance` and the waypoints its node indices name."""

    instance: MtspInstance
    uav_nodes: list[str]
    """UAV grid node of each UAV index (0: where the UAV is)."""
    ugv_nodes: list[int]
    """UGV anchor of each UGV index (0: where the UGV is)."""


def episode_coverage(town: Town, spec: EpisodeSpec, cfg: EpisodeConfig) -> CoverageProblem:
    """Both roles' waypoints of ``spec`` under the camera and checker of ``cfg``."""
    return coverage_problem(town, spec.region_world_m, spec.active_uav_waypoints, spec.uav_start_waypoint,
                            town.roads.parse_anchor_id(spec.ugv_start_waypoint), nadir_fov_deg=cfg.cameras.nadir_fov_deg,
                            ugv_reach_m=cfg.confirm.max_distance_m)


def routing_problem(town: Town, spec: EpisodeSpec, cfg: EpisodeConfig, cov: CoverageProblem, *,
                    uav_at: str, uav_t: float, ugv_at: int, ugv_t: float,
                    visited_uav: set[str], visited_ugv: set[int]) -> RoutingProblem:
    """The mTSP over the waypoints not yet searched (a pair is searched when either of its nodes
    was visited), from the roles' positions, their free times as offsets."""
    partner_uav = dict(cov.pairs)
    partner_ugv = {g: a for a, g in cov.pairs}
    seen_uav, seen_ugv = visited_uav | {uav_at}, visited_ugv | {ugv_at}
    uav_nodes = [uav_at] + [n for n in cov.uav_nodes if n not in seen_uav and partner_uav.get(n) not in seen_ugv]
    ugv_nodes = [ugv_at] + [g for g in cov.ugv_nodes if g not in seen_ugv and partner_ugv.get(g) not in seen_uav]
    pairs = tuple((uav_nodes.index(a), ugv_nodes.index(g)) for a, g in cov.pairs
                  if a in uav_nodes[1:] and g in ugv_nodes[1:])
    active = set(spec.active_uav_waypoints)
    inst = MtspInstance(uav_times(town.uav_grid, active, uav_nodes, cfg.uav_speed_mps),
                        ugv_times(town.roads, ugv_nodes, cfg.ugv_speed_mps), pairs, uav_t, ugv_t)
    return RoutingProblem(inst, uav_nodes, ugv_nodes)


def first_problem(town: Town, spec: EpisodeSpec, cfg: EpisodeConfig) -> tuple[CoverageProblem, RoutingProblem]:
    """The episode's first mTSP: both roles at their starts at time 0."""
    cov = episode_coverage(town, spec, cfg)
    start = town.roads.parse_anchor_id(spec.ugv_start_waypoint)
    return cov, routing_problem(town, spec, cfg, cov, uav_at=spec.uav_start_waypoint, uav_t=0.0, ugv_at=start, ugv_t=0.0,
                                visited_uav=set(), visited_ugv=set())
