"""One role as a Gymnasium environment, the other played by a policy: ``agos.gymnasium.RoleEnv``.

.. code-block:: python

    from agos.gymnasium import RoleEnv

    env = RoleEnv("ugv", partner="heuristic")        # you drive the UGV; agos's heuristic flies the UAV
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample(mask=obs["action_mask"]))

Importing this module registers both roles with Gymnasium's registry, as ``agos/UAV-v0`` and
``agos/UGV-v0`` (:data:`ENV_IDS`); ``gymnasium.make`` passes its keyword arguments on to
:class:`RoleEnv`:

.. code-block:: python

    import gymnasium
    import agos.gymnasium

    gymnasium.register_envs(agos.gymnasium)            # keeps the import: it registers the ids
    env = gymnasium.make("agos/UGV-v0", partner="heuristic", episodes="val.jsonl")
    # or, with no import of agos: gymnasium.make("agos.gymnasium:agos/UGV-v0", ...)

It wraps :class:`agos.pettingzoo.AgosParallelEnv` (the same spaces, rewards, infos and ends; the
learner's role's observation space and action space). A step is the learner's decision: the world
plays on, with the partner answering whenever it alone is asked, until the learner is asked again
or the episode ends; the rewards in between are summed. The partner answers with the world's own
actions (its messages reach the learner through the link model).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any, cast

import gymnasium
import numpy as np

from agos.agents.contract import Policy
from agos.agents.names import tools_for
from agos.agents.registry import make_policy
from agos.env import EnvStateError
from agos.pettingzoo import AgosParallelEnv
from agos.runtime.episode_config import EpisodeConfig, ToolConfig
from agos.runtime.keys import ROLES
from agos.runtime.schemas import Action, EpisodeRecord, EpisodeSpec, Role
from agos.runtime.settings import DEFAULT_POLICY
from agos.spaces import action_from_index

__all__ = ["ENV_IDS", "RoleEnv"]


class RoleEnv(gymnasium.Env[dict[str, np.ndarray], np.int64]):
    """``role`` as a Gymnasium environment (module docstring). ``partner``: the other role's policy,
    a name (as ``agos eval --policy`` takes it: its world-side tools are switched on in ``config``)
    or a :class:`~agos.agents.contract.Policy`. Other arguments: as
    :class:`~agos.pettingzoo.AgosParallelEnv` takes them."""

    metadata = {"render_modes": []}  # noqa: RUF012 - gymnasium.Env declares it so

    def __init__(self, role: Role = "uav", partner: str | Policy = DEFAULT_POLICY,
                 episodes: Sequence[EpisodeSpec] | str | os.PathLike[str] | None = None,
                 config: EpisodeConfig | None = None, **kwargs: Any) -> None:
        if role not in ROLES:
            raise ValueError(f"role={role!r}: give 'uav' or 'ugv'")
        self.role: Role = role
        self.other: Role = "ugv" if role == "uav" else "uav"
        if isinstance(partner, str):
            tools = ToolConfig(**tools_for({self.other: partner}))  # the oracle's hints, the expert's plan ...
            config = (config or EpisodeConfig()).model_copy(update={"tools": tools})
            self.partner = make_policy(partner, self.other)
        else:
            self.partner = partner
        self.parallel = AgosParallelEnv(episodes, config, **kwargs)
        self.observation_space = cast(gymnasium.spaces.Space[dict[str, np.ndarray]],
                                      self.parallel.observation_space(role))
        self.action_space = self.parallel.action_space(role)
        self.render_mode = None
        self._episode: str | None = None

    @property
    def record(self) -> EpisodeRecord:
        """The record of the episode last played to its end."""
        return self.parallel.record

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        self._forget()
        obs, infos = self.parallel.reset(seed=int(self.np_random.integers(2**31 - 1)))
        self._episode = next(iter(self.parallel.pending.values())).episode_id if self.parallel.pending else None
        while self.parallel.agents and self.role not in self.parallel.pending:  # (both roles are asked first)
            obs, _, _, _, infos = self._round(None)
        return obs[self.role], infos[self.role]

    def step(self, action: int | np.integer) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        if not self.parallel.agents:
            raise EnvStateError("step() after the episode ended: call reset()")
        obs, reward, terminated, truncated, infos = self._round(int(action))
        while self.parallel.agents and self.role not in self.parallel.pending:
            obs, r, terminated, truncated, infos = self._round(None)
            reward += r
        if not self.parallel.agents:
            self._forget()
        return obs[self.role], reward, terminated, truncated, infos[self.role]

    def close(self) -> None:
        self._forget()
        self.parallel.close()

    def _round(self, action: int | None) -> tuple[dict[Role, dict[str, np.ndarray]], float, bool, bool,
                                                   dict[Role, dict[str, Any]]]:
        """One decision round: the learner's action (when it is asked) and the partner's (when it is)."""
        pending = self.parallel.pending
        actions: dict[Role, Action | None] = {}
        if self.role in pending and action is not None:
            actions[self.role] = action_from_index(pending[self.role], action)
        if self.other in pending:
            actions[self.other] = self.partner.act(pending[self.other])
        obs, rewards, terms, truncs, infos = self.parallel.step_actions(actions)
        return obs, rewards[self.role], terms.get(self.role, False), truncs.get(self.role, False), infos

    def _forget(self) -> None:
        if self._episode is not None:
            self.partner.end_episode(self._episode)
            self._episode = None


ENV_IDS: dict[Role, str] = {"uav": "agos/UAV-v0", "ugv": "agos/UGV-v0"}
"""The Gymnasium ids of the two roles (registered when this module is imported)."""

for _role, _env_id in ENV_IDS.items():
    if _env_id not in gymnasium.registry:  # importing twice (importlib.reload) registers once
        gymnasium.register(_env_id, entry_point="agos.gymnasium:RoleEnv", kwargs={"role": _role})
