"""How a run's child processes get their settings: one path, the ``AGOS_<SECTION>__<KEY>``
environment variables :func:`agos.runtime.settings.load_config` reads.

``agos eval`` (and ``demo``, ``dataset build``) builds each child's settings as an
:class:`~agos.runtime.settings.AgosConfig`: the settings every child reads (the ``--config`` file,
then this process's environment: :func:`shared_settings`) with what that child alone is told (the
router's endpoint, the run id, the secured bus's credentials of its identity, the model endpoint of
VLM agents: :func:`with_settings`). :func:`settings_env` turns that object into the variables the
child is started with; the child's command line carries only what is not a setting (``--role``,
``--worker-id``, ``--out`` ...). Nothing secret is ever on a command line, which any user can read
in a process listing.

What the environment does not carry: ``[world.comm]`` (a comm profile's fields must come together,
and ``load_config`` checks each variable on its own; its blackouts are a list), any other list, and
None over a default that is not None (there is none). A child reads ``[world]`` only for the failure
record of a job grant it cannot read: the run's episode configuration, comm profile included,
travels whole in every job grant, and ``agos eval --comm`` names the run's profile.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel, SecretStr

from agos.runtime.settings import ENV_PREFIX, ENV_SEPARATOR, AgosConfig, is_setting_variable, load_config

AGENT_CONCURRENCY = 32
"""Decisions an agent service answers at once unless told (``agos agent --concurrency``); a run with
more world workers tells its agents one per worker, since every episode in flight may wait on them."""


def _text(value: object) -> str | None:
    """A setting's value as its environment variable holds it; None when a variable cannot hold it."""
    if isinstance(value, SecretStr):
        return value.get_secret_value()
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (str, int, float, Path)):
        return str(value)
    return None  # None, lists: see the module docstring


NOT_CARRIED = ("AGOS_WORLD__COMM",)
"""Settings the environment does not carry (see the module docstring)."""


def _leaves(model: BaseModel, defaults: BaseModel, prefix: str) -> dict[str, str]:
    out: dict[str, str] = {}
    for name in type(model).model_fields:
        value, default = getattr(model, name), getattr(defaults, name)
        variable = f"{prefix}{ENV_SEPARATOR}{name.upper()}"
        if variable in NOT_CARRIED:
            continue
        if isinstance(value, BaseModel):
            out |= _leaves(value, default, variable)
            continue
        if value == default:
            continue
        text = _text(value)
        if text is not None:
            out[variable] = text
    return out


def settings_env(cfg: AgosConfig) -> dict[str, str]:
    """``cfg`` as ``AGOS_<SECTION>__<KEY>`` variables: each setting that differs from the defaults.
    A process that reads only these (and no other setting variable) loads ``cfg`` again."""
    defaults = AgosConfig()
    out: dict[str, str] = {}
    for section in AgosConfig.model_fields:
        out |= _leaves(getattr(cfg, section), getattr(defaults, section), ENV_PREFIX + section.upper())
    return out


def child_environ(cfg: AgosConfig, inherited: Mapping[str, str]) -> dict[str, str]:
    """The whole environment of a child whose settings are ``cfg``: ``inherited`` without its setting
    variables (``cfg`` already holds what they said), then :func:`settings_env`."""
    return {k: v for k, v in inherited.items() if not is_setting_variable(k)} | settings_env(cfg)


def shared_settings(config_path: Path | None) -> AgosConfig:
    """What every child of a run reads before it is told anything of its own: the ``--config`` file
    of the command that starts it, then this process's environment (no command-line flag)."""
    return load_config(config_path)


def with_settings(cfg: AgosConfig, **sections: dict[str, Any]) -> AgosConfig:
    """``cfg`` with some settings replaced: ``with_settings(cfg, zenoh={"connect": EP}, run={...})``."""
    return cfg.model_copy(update={name: getattr(cfg, name).model_copy(update=fields) for name, fields in sections.items()})
