"""The episode engine's settings: an :class:`~agos.runtime.episode_config.EpisodeConfig` as the
engine, the rules and the observations read it.

The configuration holds the values as a person writes them (pixel thresholds at reference image
sizes, tools as named switches); :func:`episode_settings` derives the engine's view of them, and
:func:`with_budget` applies a configured decision budget to an episode.
"""

from __future__ import annotations

from dataclasses import dataclass

import msgspec

from agos.runtime.episode_config import CameraConfig, ConfirmConfig, EpisodeConfig, TimingMode
from agos.runtime.links import CommProfile
from agos.runtime.schemas import EpisodeSpec


@dataclass(frozen=True)
class EpisodeSettings:
    """The engine's view of an :class:`~agos.runtime.episode_config.EpisodeConfig`, made only by
    :func:`agos.world.sim.engine_settings.episode_settings`: the same values with pixel thresholds scaled
    to the configured image sizes and the tools as flags. No defaults here: those live in the
    configuration, once."""

    config: EpisodeConfig
    """What these settings were made from (stored in the record with its hash)."""
    uav_speed_mps: float
    ugv_speed_mps: float
    wait_max_s: float
    stop_observe_s: float
    short_action_s: float
    uav_visible_min_px: int
    """Oracle threshold for "target visible from the air", at the configured nadir view size."""
    max_annotations: int
    sim_time_limit_s: float
    recent_messages: int
    max_freeze_s: float
    """A UAV that has not heard its candidate resolved by then is asked again (lossy links)."""
    comm: CommProfile
    timing_mode: TimingMode
    """``lockstep``: the sim clock waits for decisions; ``realtime``: a decision's wall-clock
    latency delays its effect in sim time, while the teammate carries on."""
    candidates: bool
    """Structured candidates: ANNOTATE_CANDIDATE and GO_TO_CANDIDATE exist. Off for the Baseline,
    which coordinates through text messages only."""
    e2a: bool
    """Ego-to-Allo projection: a candidate is its grid cell on the ground. Off (no_e2a ablation):
    the candidate centre is the UAV's ground footprint and its polygon the whole view."""
    rgpp: bool
    """Road-graph path planning: GO_TO_CANDIDATE exists. Off (no_rgpp): the UGV approaches through
    road waypoints, each with its distance to the candidate as a hint."""
    oracle: bool
    """Give observations the ground-truth hints of the oracle policy."""
    link_seed: int
    """Extra seed of the link streams, for repeating an episode under other link randomness."""
    confirm: ConfirmConfig
    """The checker's thresholds at the configured ground view size."""
    cameras: CameraConfig


def episode_settings(config: EpisodeConfig) -> EpisodeSettings:
    """The engine's settings for ``config`` (thresholds scaled to the configured image sizes)."""
    return EpisodeSettings(
        config=config, uav_speed_mps=config.uav_speed_mps, ugv_speed_mps=config.ugv_speed_mps, wait_max_s=config.wait_max_s,
        stop_observe_s=config.stop_observe_s, short_action_s=config.short_action_s,
        uav_visible_min_px=config.uav_visible_min_px(), max_annotations=config.max_annotations,
        sim_time_limit_s=config.sim_time_limit_s, recent_messages=config.recent_messages,
        max_freeze_s=config.max_freeze_s, comm=config.comm, timing_mode=config.timing_mode,
        candidates=config.tools.candidates, e2a=config.tools.e2a, rgpp=config.tools.rgpp, oracle=config.tools.oracle,
        link_seed=config.link_seed, confirm=config.confirm_at_view_size(), cameras=config.cameras)


def with_budget(spec: EpisodeSpec, config: EpisodeConfig) -> EpisodeSpec:
    """``spec`` with the configured decision budget, when the configuration sets one."""
    if config.decision_budget is None or config.decision_budget == spec.decision_budget:
        return spec
    return msgspec.structs.replace(spec, decision_budget=config.decision_budget)
