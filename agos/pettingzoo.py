"""The two roles as a PettingZoo parallel environment: ``agos.pettingzoo.parallel_env(...)``.

.. code-block:: python

    from agos.pettingzoo import parallel_env

    env = parallel_env()                                  # generated episodes of grid-s7
    observations, infos = env.reset(seed=0)
    while env.agents:
        actions = {a: env.action_space(a).sample(observations[a]["action_mask"]) for a in env.agents}
        observations, rewards, terminations, truncations, infos = env.step(actions)

Agents ``uav`` and ``ugv``; one ``step`` is one decision round of the world (agos.Env underneath: the
same engine, rules, link model and records). Spaces and the index of each action: :mod:`agos.spaces`
(docs/AGENTS.md, "Actions as indices"). A role the world does not ask this round still gets its
last observation, with the no-op mask (index 0 alone) and ``state[asked] = 0``; its action is not
applied. An index outside the mask becomes the world's counted WAIT.

Rewards (both roles get the team's): ``"sparse"`` (default) 1 when the episode ends with an
accepted CONFIRM, else 0. ``"shaped"`` adds, per role: -0.01 for each of its decisions, +0.2 the
first time the target is in its view (the UAV's nadir view with the target oracle-visible; the
UGV's six views where CONFIRM would pass), and -0.5 to both for a false CONFIRM. The view bonuses use
the world's ground truth, which a reward may (an observation never does).

Terminations and truncations come from the episode's end: ``confirmed`` and ``false_confirm``
terminate both roles; the decision budget spent, the simulated-time limit, or an error truncate them.
``infos[role]``: ``asked``, ``decision_index``, ``sim_time_s``, ``legal_actions``, ``applied`` and
``fallback_reason`` (of its decision in the step just made), ``text`` (AGOS-Agent's prompt for the
decision asked, its images as ``[image: ...]`` captions; with ``text=True``) and, at the end,
``termination`` and ``success``; :attr:`AgosParallelEnv.record` is the episode's record.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar, Literal

import msgspec
import numpy as np

from agos import spaces as arrays  # first: it says which extra to install when gymnasium is missing

try:
    from gymnasium import spaces
    from pettingzoo import ParallelEnv
except ModuleNotFoundError as missing:
    raise ModuleNotFoundError(f"agos.pettingzoo needs {missing.name}: pip install 'agos[learn]' (docs/LIBRARY.md)",
                              name=missing.name) from None
from agos.env import Env, EnvStateError
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.keys import ROLES
from agos.runtime.schemas import DIFFICULTIES, Action, Difficulty, EpisodeRecord, EpisodeSpec, Observation, Role, StepEvent
from agos.runtime.settings import DEFAULT_TOWN
from agos.world.sim.scene import Scene
from agos.world.towns.asset import Town, open_town, town_for

__all__ = ["AgosParallelEnv", "parallel_env"]

Reward = Literal["sparse", "shaped"]
STEP_COST = 0.01
SEEN_BONUS = 0.2
FALSE_CONFIRM = -0.5
TERMINATING = ("confirmed", "false_confirm")


def parallel_env(episodes: Sequence[EpisodeSpec] | str | os.PathLike[str] | None = None,
                 config: EpisodeConfig | None = None, **kwargs: Any) -> AgosParallelEnv:
    """An :class:`AgosParallelEnv` (PettingZoo's usual constructor name); arguments as it takes them."""
    return AgosParallelEnv(episodes, config, **kwargs)


class AgosParallelEnv(ParallelEnv[Role, dict[str, np.ndarray], int]):
    """Both roles of agos as a PettingZoo ``ParallelEnv`` (module docstring).

    ``episodes``: episodes to play (a list, or an episode file), one drawn by the seeded generator at
    each reset; None: each reset samples a new episode of ``town`` (``difficulties``: drawn from
    these), as ``agos episodes sample`` does. ``config``: the run configuration (``agos.episode_config``;
    default ``EpisodeConfig()``: rich look, full-size images); ``depth``/``semantic``: add those images;
    ``reward``: ``"sparse"`` or ``"shaped"``; ``text``: put the VLM prompt's text in ``infos``;
    ``scene``: a scene of this town in ``config.look`` to play in (not closed by :meth:`close`; one
    environment at a time), else the environment builds its own.
    """

    metadata: ClassVar[dict[str, Any]] = {"name": "agos_v0", "render_modes": [], "is_parallelizable": True}

    def __init__(self, episodes: Sequence[EpisodeSpec] | str | os.PathLike[str] | None = None,
                 config: EpisodeConfig | None = None, *, town: str = DEFAULT_TOWN,
                 difficulties: Sequence[Difficulty] = DIFFICULTIES, depth: bool = False,
                 semantic: bool = False, reward: Reward = "sparse", text: bool = True,
                 render_mode: str | None = None, scene: Scene | None = None) -> None:
        if reward not in ("sparse", "shaped"):
            raise ValueError(f"reward={reward!r}: give 'sparse' or 'shaped' (docs/LIBRARY.md)")
        if render_mode is not None:
            raise ValueError(f"render_mode={render_mode!r}: this environment draws nothing itself (the observations "
                             "hold the images)")
        self.config = config or EpisodeConfig()
        self.reward, self.text, self.render_mode = reward, text, render_mode
        self.difficulties = list(difficulties)
        self.possible_agents: list[Role] = list(ROLES)
        self.agents: list[Role] = []
        self._episodes = _episode_list(episodes, self.config.look)
        if self._episodes:
            first = self._episodes[0]
            self._town: Town = town_for(first.town.generator, first.town.seed, first.asset_sha256,
                                        town_id=first.town.town_id)
            others = sorted({e.town.town_id for e in self._episodes if e.asset_sha256 != first.asset_sha256})
            if others:
                raise ValueError(f"the episodes are in towns {first.town.town_id} and {', '.join(others)}: one "
                                 "environment plays one town (make one per town)")
        else:
            self._town = open_town(town)
        if scene is not None and scene.look != self.config.look:
            raise ValueError(f"the scene was built with look {scene.look!r} but the configuration's look is "
                             f"{self.config.look!r}: build it with look=config.look")
        self._own_scene = scene is None
        self._scene = scene or Scene(self._town.layout, look=self.config.look, renderer=self.config.renderer)
        self._spaces = {role: arrays.observation_space(role, self.config, depth=depth, semantic=semantic)
                        for role in ROLES}
        self._action_spaces = {role: spaces.Discrete(arrays.action_count(role)) for role in ROLES}
        self._env: Env | None = None
        self._rng: np.random.Generator | None = None
        self._last: dict[Role, Observation] = {}
        self._seen: set[Role] = set()
        self._memory: dict[Role, Any] = {}
        self._closed = False

    # ----- PettingZoo's API ----------------------------------------------------------------------
    def observation_space(self, agent: Role) -> spaces.Dict:
        return self._spaces[agent]

    def action_space(self, agent: Role) -> spaces.Discrete:
        return self._action_spaces[agent]

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[dict[Role, dict[str, np.ndarray]], dict[Role, dict[str, Any]]]:
        """A new episode (module docstring); ``seed`` seeds the draw of it (and of the ones after)."""
        if self._closed:
            raise EnvStateError("reset() after close(): this environment is closed; build another")
        if seed is not None or self._rng is None:
            self._rng = np.random.default_rng(seed)
        if self._env is not None:
            self._env.abandon()  # the scene is free again: a sampler may use it
        spec = self._draw()
        if self._env is None:
            self._env = Env(spec, self.config, illegal="wait", run_id="pettingzoo", scene=self._scene, town=self._town)
        observations = self._env.reset(spec)
        self.agents = list(ROLES)
        self._last, self._seen = {}, set()
        self._memory = {role: _memory() for role in ROLES} if self.text else {}
        obs, _, infos = self._observe(observations, [], None)
        return obs, infos

    def step(self, actions: Mapping[Role, int | np.integer]
             ) -> tuple[dict[Role, dict[str, np.ndarray]], dict[Role, float], dict[Role, bool], dict[Role, bool],
                        dict[Role, dict[str, Any]]]:
        """One decision round: each asked role's action index (others are ignored)."""
        pending = self._pending("step")
        return self.step_actions({role: arrays.action_from_index(obs, int(actions[role])) if role in actions else None
                                  for role, obs in pending.items()})

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._env is not None:
            self._env.close()
        if self._own_scene:
            self._scene.close()

    # ----- beyond PettingZoo's API ---------------------------------------------------------------
    @property
    def pending(self) -> dict[Role, Observation]:
        """The world's observations (text level, :class:`agos.runtime.schemas.Observation`) of the roles
        asked this round: what an agos policy reads (``policy.act(obs)``)."""
        return {} if self._env is None else self._env.pending

    @property
    def record(self) -> EpisodeRecord:
        """The record of the episode last played to its end."""
        if self._env is None:
            raise EnvStateError("no episode has been played: reset(), then step() until no agents are left")
        return self._env.record

    def step_actions(self, actions: Mapping[Role, Action | None]
                     ) -> tuple[dict[Role, dict[str, np.ndarray]], dict[Role, float], dict[Role, bool],
                                dict[Role, bool], dict[Role, dict[str, Any]]]:
        """:meth:`step` with the world's own actions (an agos policy's answers, messages included):
        one per asked role, None for no action."""
        self._pending("step")
        assert self._env is not None
        result = self._env.step(actions)
        obs, rewards, infos = self._observe(result.observations, result.events, result.record)
        done = result.record is not None
        terminated = done and result.record is not None and result.record.termination in TERMINATING
        terminations = dict.fromkeys(self.agents, terminated)
        truncations = dict.fromkeys(self.agents, done and not terminated)
        if done:
            self.agents = []
        return obs, rewards, terminations, truncations, infos

    # ----- helpers -------------------------------------------------------------------------------
    def _pending(self, call: str) -> dict[Role, Observation]:
        if self._closed:
            raise EnvStateError(f"{call}() after close(): this environment is closed; build another")
        if self._env is None:
            raise EnvStateError(f"{call}() before reset(): call reset() first")
        if not self.agents:
            raise EnvStateError(f"{call}() after the episode ended (no agents left): call reset()")
        return self._env.pending

    def _draw(self) -> EpisodeSpec:
        assert self._rng is not None
        if self._episodes:
            return self._episodes[int(self._rng.integers(len(self._episodes)))]
        from agos.world.episodes.sampling import sample_episode

        difficulty = self.difficulties[int(self._rng.integers(len(self.difficulties)))]
        seed = int(self._rng.integers(2**31 - 1))
        spec = sample_episode(self._town, self._scene, difficulty, 0, seed=seed, stream=DIFFICULTIES.index(difficulty))
        return msgspec.structs.replace(spec, episode_id=f"{spec.episode_id}-s{seed}")  # one id per drawn episode

    def _observe(self, observations: dict[Role, Observation], events: list[StepEvent], record: EpisodeRecord | None
                 ) -> tuple[dict[Role, dict[str, np.ndarray]], dict[Role, float], dict[Role, dict[str, Any]]]:
        self._last.update(observations)
        applied = {e.role: e for e in events}
        for made in events:
            if self.text:
                _remember(self._memory[made.role], made)
        rewards = self._rewards(events, record)
        obs: dict[Role, dict[str, np.ndarray]] = {}
        infos: dict[Role, dict[str, Any]] = {}
        for role in ROLES:
            asked = role in observations
            last = self._last.get(role)
            space = self._spaces[role]
            obs[role] = arrays.observation_arrays(last, space, asked=asked) if last is not None else \
                {k: np.zeros(s.shape or (), s.dtype) for k, s in space.spaces.items()} | \
                {"action_mask": arrays.action_mask(None, role)}
            event = applied.get(role)
            info: dict[str, Any] = {
                "asked": asked, "decision_index": last.decision_index if last is not None and asked else 0,
                "sim_time_s": float(last.sim_time_s) if last is not None else 0.0,
                "legal_actions": list(last.legal_actions) if last is not None and asked else ["WAIT"],
                "applied": None if event is None else event.applied,
                "fallback_reason": None if event is None else event.fallback_reason}
            if self.text:
                info["text"] = _prompt_text(observations[role], self._memory[role]) if asked else ""
            if record is not None:
                info |= {"termination": record.termination, "success": record.success}
            infos[role] = info
        return obs, rewards, infos

    def _rewards(self, events: list[StepEvent], record: EpisodeRecord | None) -> dict[Role, float]:
        rewards = dict.fromkeys(ROLES, 0.0)
        if self.reward == "shaped":
            for e in events:
                rewards[e.role] -= STEP_COST
                if e.role not in self._seen and (e.target_visible_uav or e.target_visible_ugv):
                    self._seen.add(e.role)
                    rewards[e.role] += SEEN_BONUS
        if record is not None:
            team = 1.0 if record.success else (FALSE_CONFIRM if self.reward == "shaped"
                                               and record.termination == "false_confirm" else 0.0)
            rewards = {role: value + team for role, value in rewards.items()}
        return rewards


def _episode_list(episodes: Sequence[EpisodeSpec] | str | os.PathLike[str] | None, look: str) -> list[EpisodeSpec]:
    if episodes is None:
        return []
    if isinstance(episodes, (str, os.PathLike)):
        from agos.world.episodes.files import read_split

        return read_split(Path(episodes), look=look)
    if not episodes:
        raise ValueError("episodes=[]: give at least one episode, or None to sample them")
    return list(episodes)


def _memory() -> Any:
    from agos.agents.vlm.request import Memory

    return Memory()


def _remember(memory: Any, event: StepEvent) -> None:
    """What AGOS-Agent's memory keeps of a decision (agents/vlm/agent.py): its line, the road waypoint."""
    requested = event.requested
    detail = "" if requested is None or event.applied != requested.action else \
        requested.waypoint_id or requested.cell or requested.candidate_id or ""
    memory.note(event.decision_index, event.applied, detail)
    if event.applied == "MOVE_TO_ROAD_WAYPOINT" and requested is not None:
        memory.at(requested.waypoint_id)


def _prompt_text(obs: Observation, memory: Any) -> str:
    """AGOS-Agent's prompt for ``obs``, text only: each image as its caption (agents/vlm/agos_prompts.py)."""
    from agos.agents.vlm import agos_prompts

    build = agos_prompts.uav_prompt if obs.role == "uav" else agos_prompts.ugv_prompt
    prompt = build(obs, memory, images="references")
    return "\n".join(part["text"] for part in prompt.parts if part.get("type") == "text")
