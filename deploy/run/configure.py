"""The one builder of a run's :class:`~agos.runtime.episode_config.EpisodeConfig`.

``agos eval``/``demo`` (the orchestrator), ``agos sweep`` and ``agos check`` all call
:func:`run_episode_config`: the ``[world]`` settings as layered by :func:`agos.runtime.settings.load_config`
(defaults < TOML file < ``AGOS_WORLD__…`` environment < flags), then the run's comm profile
(``--comm``), the placement of its model (``--model-link``), each role's localisation error
(``--pose-error``), timing mode (``--timing``) and the
world-side tools of its policies.
"""

from __future__ import annotations

from pydantic import ValidationError

from agos.agents.names import tools_for
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.links import load_profile
from agos.runtime.model_link import load_model_link, placement
from agos.runtime.sensing import load_pose_error
from agos.runtime.settings import AgosConfig, config_error


def run_episode_config(cfg: AgosConfig, *, policies: dict[str, str], comm: str | None = None,
                       timing_mode: str | None = None, decision_budget: int | None = None,
                       model_link: str | None = None, pose_error: str | None = None) -> EpisodeConfig:
    """The run's episode configuration. ``comm`` is a profile name (deploy/comm) or TOML file
    (raises :class:`~agos.runtime.links.ProfileError`); ``model_link`` a placement (deploy/model_link)
    or TOML file (:class:`~agos.runtime.model_link.ModelLinkError`); ``pose_error`` a localisation-error
    profile (deploy/sensing) or TOML file (:class:`~agos.runtime.sensing.PoseErrorProfileError`); unknown
    policy names raise ValueError."""
    data = cfg.world.model_dump()
    data["tools"] = tools_for(policies)
    if comm is not None:
        data["comm"] = load_profile(comm).model_dump()
    if model_link is not None:
        placed = placement(load_model_link(model_link))
        data["model_link"] = None if placed is None else placed.model_dump()
    if pose_error is not None:
        data["pose_error"] = load_pose_error(pose_error).model_dump()
    if timing_mode is not None:
        data["timing_mode"] = timing_mode
    if decision_budget is not None:
        data["decision_budget"] = decision_budget
    try:
        return EpisodeConfig.model_validate(data)
    except ValidationError as exc:
        raise config_error(exc, "command line", section="world.") from None
