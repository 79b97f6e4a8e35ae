"""Episode records the infrastructure writes itself (never an agent outcome)."""

from __future__ import annotations

from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.provenance import provenance
from agos.runtime.schemas import EpisodeRecord, EpisodeSpec, EpisodeStatus


def failure_record(run_id: str, spec: EpisodeSpec, *, status: EpisodeStatus, worker_id: str, error: str,
                   config: EpisodeConfig, wall_time_s: float = 0.0) -> EpisodeRecord:
    """The record of an episode that did not run to its end for an infrastructure reason
    (``world_crashed``, ``invalid`` ...): scored apart, never as an agent failure. It carries the
    run's episode configuration like any record, so a resumed run's records pool with it, and the
    provenance of the process that writes it (runtime/provenance.py)."""
    return EpisodeRecord(
        run_id=run_id, episode_id=spec.episode_id, difficulty=spec.difficulty, status=status, termination="error",
        success=False, ground_observed=False, n_confirm=0, ugv_path_length_m=0.0, shortest_path_length_m=None,
        final_distance_m=0.0, uav_budget=config.decision_budget or spec.decision_budget, uav_first_visible_step=None, candidates=[],
        decisions_uav=0, decisions_ugv=0, sim_time_s=0.0, wall_time_s=round(wall_time_s, 3), worker_id=worker_id,
        town_id=spec.town.town_id, asset_sha256=spec.asset_sha256, seed=spec.seed, renderer=config.renderer,
        comm_profile=config.comm.name, timing_mode=config.timing_mode, tools=config.tools.model_dump(),
        config=config.model_dump(mode="json"), config_hash=config.config_hash(), error=error,
        provenance=provenance())
