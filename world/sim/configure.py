"""An :class:`~agos.runtime.episode_config.EpisodeConfig` as the episode engine uses it.

The configuration holds the values as a person writes them (pixel thresholds at reference image
sizes, tools as named switches); :func:`episode_settings` derives the engine's view of them, and
:func:`with_budget` applies a configured decision budget to an episode.
"""

from __future__ import annotations

import msgspec

from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.schemas import EpisodeSpec
from agos.world.sim.state import EpisodeSettings


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
