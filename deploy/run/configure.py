"""The one builder of a run's :class:`~agos.runtime.episode_config.EpisodeConfig`.

``agos eval``/``demo`` (the orchestrator), ``agos sweep`` and ``agos check`` all call
:func:`episode_config`: the ``[world]`` settings as layered by :func:`agos.runtime.settings.load_config`
(defaults < TOML file < ``AGOS_WORLD__…`` environment < flags), then the run's comm profile
(``--comm``), timing mode (``--timing``) and the world-side tools of its policies.
"""

from __future__ import annotations

from pydantic import ValidationError

from agos.agents.names import tools_for
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.links import load_profile
from agos.runtime.settings import AgosConfig, config_error


def episode_config(cfg: AgosConfig, *, policies: dict[str, str], comm: str | None = None,
                   timing_mode: str | None = None, decision_budget: int | None = None) -> EpisodeConfig:
    """The run's episode configuration. ``comm`` is a profile name (deploy/comm) or TOML file
    (raises :class:`~agos.runtime.links.ProfileError`); unknown policy names raise ValueError."""
    data = cfg.world.model_dump()
    data["tools"] = tools_for(policies)
    if comm is not None:
        data["comm"] = load_profile(comm).model_dump()
    if timing_mode is not None:
        data["timing_mode"] = timing_mode
    if decision_budget is not None:
        data["decision_budget"] = decision_budget
    try:
        return EpisodeConfig.model_validate(data)
    except ValidationError as exc:
        raise config_error(exc, "command line", section="world.") from None
