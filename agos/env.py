"""``agos.Env``: one episode of the agos world at a time, stepped from your own Python loop.

The process path (``agos eval``) runs a world worker that asks agent processes over zenoh for every
decision. :class:`Env` runs the same :class:`~agos.world.sim.engine.EpisodeRunner` (the same rules,
link model, clock and record) in your process and hands the decisions to you instead:

.. code-block:: python

    with Env("episodes.jsonl", index=0, config=episode_config(look="flat")) as env:
        observations = env.reset()                 # {"uav": Observation, "ugv": Observation}
        while observations:                        # the roles asked this round
            actions = {role: my_policy(obs) for role, obs in observations.items()}
            observations = env.step(actions).observations
        print(env.record.success)

Contract (docs/LIBRARY.md):

* ``reset()`` sets the episode up and returns the observations of the roles asked first (both, at
  the start); ``step(actions)`` takes one :class:`~agos.runtime.schemas.Action` per role asked
  (:attr:`Env.pending`) and returns the next round's observations, the step events the decisions
  made, and, once the episode has ended, its :class:`~agos.runtime.schemas.EpisodeRecord`. Rounds
  come in simulated time: a role is asked again when its last action has finished, so a round may
  ask one role or both.
* ``play(agents)`` is ``reset`` then ``step`` until the end, the actions from a :class:`Policy` per
  role (called as in-process runners always called them) or from one ``DecisionSource`` answering
  every role asked; ``agos sweep``, ``agos check agent``, tests and benchmarks play so.
* Calls out of order raise :class:`EnvStateError` (a ``RuntimeError``) saying which call comes
  next: ``step`` before ``reset``, ``step`` after the end, anything after ``close``.
* With ``illegal="raise"`` (the default) an action that cannot answer its observation (a name not
  in ``legal_actions``, a waypoint not among the options, a cell not in A1..E5, a candidate the UGV
  does not hold, an action for another decision, a role not asked, a role asked but left out)
  raises :class:`IllegalActionError` (a ``ValueError``) naming the role, the decision and why, and
  nothing is applied: correct it and call ``step`` again. With ``illegal="wait"`` the world does
  what it does for agent processes: the decision becomes a counted WAIT, and its step event says
  why (``StepEvent.fallback_reason``).
* The same episode, configuration and decisions give the same record as ``agos eval`` with agents
  that take those decisions, but for ``run_id``, ``worker_id``, ``wall_time_s`` and ``provenance``
  (tests/test_env.py holds the two paths side by side for every scripted policy).

Layer: ``agos`` itself (this folder) sits on ``world``, ``agents`` and ``runtime``, beside
``deploy``; nothing below imports it (docs/ARCHITECTURE.md §0).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Self, cast

from agos.agents.contract import Policy, action_for
from agos.agents.inprocess import InProcessAgents
from agos.agents.names import tools_for
from agos.runtime.camera import parse_cell
from agos.runtime.episode_config import EpisodeConfig, ToolConfig
from agos.runtime.links import load_profile
from agos.runtime.model_link import load_model_link
from agos.runtime.schemas import (
    DIFFICULTIES,
    Action,
    AgentMessage,
    Candidate,
    CoordinationState,
    Difficulty,
    EpisodeRecord,
    EpisodeSpec,
    Observation,
    Role,
    StepEvent,
)
from agos.runtime.settings import DEFAULT_TOWN
from agos.world.sim import rules
from agos.world.sim.engine import ROLE_ORDER, DecisionSource, EpisodeRunner, EpisodeSink, SetupMemo
from agos.world.sim.scene import Scene
from agos.world.towns.asset import Town, open_town, town_for

__all__ = ["ROLES", "Env", "EnvStateError", "IllegalActionError", "StepResult", "episode_config"]

ROLES: tuple[Role, Role] = ROLE_ORDER
"""The two roles, in the order the world applies a round's actions."""
IllegalMode = Literal["raise", "wait"]
MOVES = {"uav": "MOVE_TO_UAV_WAYPOINT", "ugv": "MOVE_TO_ROAD_WAYPOINT"}
MEMO_EPISODES = 256
"""Episodes whose setup renders an Env keeps (a few small images each)."""


class EnvStateError(RuntimeError):
    """A call out of order; the message says which call comes next."""


class IllegalActionError(ValueError):
    """An action that cannot answer its observation; nothing was applied (``illegal="raise"``)."""


@dataclass(frozen=True)
class StepResult:
    """What one :meth:`Env.step` gave."""

    observations: dict[Role, Observation]
    """The roles asked next and what each sees; empty once the episode has ended."""
    events: list[StepEvent]
    """One event per decision just applied (what was requested, what was applied and why), in order."""
    messages: list[AgentMessage] = field(default_factory=list)
    """Messages the link delivered while the world played on to the next round."""
    record: EpisodeRecord | None = None
    """The episode's record, once it has ended (then also :attr:`Env.record`)."""

    @property
    def done(self) -> bool:
        """The episode has ended (no role is asked any more)."""
        return not self.observations


def episode_config(*, policies: str | Mapping[Role, str] | None = None, comm: str | os.PathLike[str] | None = None,
                   model_link: str | os.PathLike[str] | None = None, **world: Any) -> EpisodeConfig:
    """An :class:`EpisodeConfig` as ``agos eval`` would build it for ``policies`` (one name for both
    roles, or one per role: sets the world-side tools, e.g. the oracle's hints or the expert's plan)
    over the link profile ``comm`` (a name in deploy/comm, e.g. ``"lossy"``, or a TOML file), with the
    model placed by ``model_link`` (a name in deploy/model_link, e.g. ``"lte"``, or a TOML file), with
    any other ``[world]`` field given by keyword (``look="flat"``, ``decision_budget=20``,
    ``cameras={"nadir_px": 128}``, ``pose_error="gnss-5m"`` ...). Raises ``ValueError`` (pydantic's, or a profile's one line)."""
    data = dict(world)
    if policies is not None:
        names = dict.fromkeys(ROLES, policies) if isinstance(policies, str) else dict(policies)
        data["tools"] = ToolConfig(**tools_for(cast(dict[str, str], names)))
    if comm is not None:
        data["comm"] = load_profile(comm if isinstance(comm, str) else Path(comm))
    if model_link is not None:
        data["model_link"] = load_model_link(model_link if isinstance(model_link, str) else Path(model_link))
    return EpisodeConfig.model_validate(data)


class _Collect:
    """The runner's sink: keeps what one step produced, and passes everything on to ``then``."""

    def __init__(self, then: EpisodeSink | None) -> None:
        self.then = then
        self.events: list[StepEvent] = []
        self.messages: list[AgentMessage] = []

    def step(self, event: StepEvent) -> None:
        self.events.append(event)
        if self.then is not None:
            self.then.step(event)

    def coordination(self, truth: CoordinationState, views: dict[Role, CoordinationState]) -> None:
        if self.then is not None:
            self.then.coordination(truth, views)

    def message(self, message: AgentMessage) -> None:
        self.messages.append(message)
        if self.then is not None:
            self.then.message(message)

    def take(self) -> tuple[list[StepEvent], list[AgentMessage]]:
        out = (self.events, self.messages)
        self.events, self.messages = [], []
        return out


class _Memo(dict[bytes, SetupMemo]):
    """The setup renders of the last :data:`MEMO_EPISODES` episodes played (EpisodeRunner's
    ``setup_memo``): a reset of an episode played before renders only its first observations."""

    def __setitem__(self, key: bytes, value: SetupMemo) -> None:
        super().__setitem__(key, value)
        while len(self) > MEMO_EPISODES:
            del self[next(iter(self))]


class Env:
    """The agos world for one episode at a time, in this process (module docstring).

    ``episode``: an :class:`EpisodeSpec`, or an episode file (JSONL, as ``agos episodes sample``
    writes it) of which episode ``index`` is played, checked as ``agos eval`` checks a split.
    ``config``: the run configuration (:func:`episode_config`; default ``EpisodeConfig()``, the
    rich look, as ``agos eval`` runs). ``scene`` and ``town``: one already built for this town and
    ``config.look`` (tests share one across many episodes); otherwise the Env builds its own and
    closes it in :meth:`close`. ``sink``: also gets every step event, coordination state and
    message (as a world worker publishes them). ``run_id`` names the run in observations and records,
    ``worker_id`` the player in records (``agos sweep`` writes ``"sweep"``).
    """

    def __init__(self, episode: EpisodeSpec | str | os.PathLike[str], config: EpisodeConfig | None = None, *,
                 index: int = 0, illegal: IllegalMode = "raise", run_id: str = "env", worker_id: str = "env",
                 scene: Scene | None = None, town: Town | None = None, sink: EpisodeSink | None = None) -> None:
        if illegal not in ("raise", "wait"):
            raise ValueError(f"illegal={illegal!r}: give 'raise' (an IllegalActionError) or 'wait' (a counted WAIT)")
        self.config = config or EpisodeConfig()
        self.spec = episode if isinstance(episode, EpisodeSpec) else _from_file(Path(episode), index, self.config.look)
        self.illegal: IllegalMode = illegal
        self.run_id = run_id
        self.worker_id = worker_id
        if scene is not None and scene.look != self.config.look:
            raise ValueError(f"the scene was built with look {scene.look!r} but the configuration's look is "
                             f"{self.config.look!r}: build it with look=config.look")
        self._own_scene = scene is None
        self._town = town or town_for(self.spec.town.generator, self.spec.town.seed, self.spec.asset_sha256,
                                      town_id=self.spec.town.town_id)
        if self._town.sha256 != self.spec.asset_sha256:
            raise ValueError(f"episode {self.spec.episode_id} is in town {self.spec.town.town_id} "
                             f"({self.spec.asset_sha256[:12]}), the town given is {self._town.town_id} "
                             f"({self._town.sha256[:12]})")
        self._scene = scene or Scene(self._town.layout, look=self.config.look, renderer=self.config.renderer)
        if self.config.tools.expert:
            from agos.world import expert

            expert.install()  # the expert's plan rides in observations (world/expert/)
        self._sink = _Collect(sink)
        self._memo = _Memo()
        self._runner: EpisodeRunner | None = None
        self._record: EpisodeRecord | None = None
        self._closed = False

    # ----- building ------------------------------------------------------------------------------
    @classmethod
    def generated(cls, *, town: str = DEFAULT_TOWN, difficulty: Difficulty = "easy", seed: int = 0,
                  config: EpisodeConfig | None = None, **kwargs: Any) -> Self:
        """An Env on an episode sampled now, as ``agos episodes sample --town TOWN --seed SEED`` samples
        the first of ``difficulty`` (checked solvable by rendering; a second or so). ``kwargs``: as
        :class:`Env` takes them."""
        from agos.world.episodes.sampling import sample_episode

        config = config or EpisodeConfig()
        built = open_town(town)
        given: Scene | None = kwargs.pop("scene", None)
        scene = given or Scene(built.layout, look=config.look, renderer=config.renderer)
        try:
            spec = sample_episode(built, scene, difficulty, 0, seed=seed, stream=DIFFICULTIES.index(difficulty))
            env = cls(spec, config, scene=scene, town=built, **kwargs)
        except BaseException:
            if given is None:
                scene.close()
            raise
        env._own_scene = given is None
        return env

    # ----- state ---------------------------------------------------------------------------------
    @property
    def scene(self) -> Scene:
        """The PyBullet scene episodes are played in (free between episodes: samplers may use it)."""
        return self._scene

    @property
    def town(self) -> Town:
        return self._town

    @property
    def pending(self) -> dict[Role, Observation]:
        """The observations awaiting actions (the roles :meth:`step` wants); empty before
        :meth:`reset` and after the end."""
        return {} if self._runner is None else dict(self._runner.pending)

    @property
    def done(self) -> bool:
        """The episode in play has ended (its record is :attr:`record`)."""
        return self._record is not None

    @property
    def record(self) -> EpisodeRecord:
        """The record of the episode last played to its end."""
        if self._record is None:
            raise EnvStateError("no episode has ended yet: reset(), then step() until StepResult.done")
        return self._record

    # ----- playing -------------------------------------------------------------------------------
    def reset(self, episode: EpisodeSpec | None = None) -> dict[Role, Observation]:
        """Start the episode (again; or ``episode``, another of the same town) from its beginning,
        abandoning one in play; the observations of the roles asked first."""
        self._check_open("reset")
        self.abandon()
        if episode is not None:
            if episode.asset_sha256 != self._town.sha256:
                raise ValueError(f"episode {episode.episode_id} is in town {episode.town.town_id}, this Env's scene is "
                                 f"{self._town.town_id}: build another Env for it")
            self.spec = episode
        self._record = None
        self._runner = EpisodeRunner(self._scene, self._town, self.spec, run_id=self.run_id, worker_id=self.worker_id,
                                     config=self.config, sink=self._sink, setup_memo=self._memo)
        self._sink.take()
        observations = self._runner.start()
        if not observations:
            self._finish()
        return observations

    def step(self, actions: Mapping[Role, Action | None]) -> StepResult:
        """Apply one action per role asked (:attr:`pending`; ``None`` for a role: no action, a counted
        WAIT) and play on to the next round (module docstring)."""
        self._check_open("step")
        runner = self._runner
        if runner is None:
            raise EnvStateError("step() before reset(): call reset() first")
        if self._record is not None:
            raise EnvStateError(f"episode {self.spec.episode_id} is over ({self._record.termination}): "
                                "call reset() to play it (or another) again")
        if self.illegal == "raise":
            self._check(runner.pending, actions)
        observations = runner.advance(actions)
        events, messages = self._sink.take()
        record = self._finish() if not observations else None
        return StepResult(observations, events, messages, record)

    def play(self, agents: Mapping[Role, Policy] | DecisionSource, *,
             seen: list[Observation] | None = None) -> EpisodeRecord:
        """The whole episode from its start; its record. ``agents``: one :class:`Policy` per role, called
        as :class:`~agos.agents.inprocess.InProcessAgents` calls them (``act``, on this thread; a policy
        that defines only ``act_async`` has it run to completion on a fresh event loop per decision,
        and VLM policies' ``act`` does that with a fresh HTTP client, as in ``agos sweep``), each told
        the episode has ended; or a :class:`~agos.world.sim.engine.DecisionSource`, one object whose
        ``decide(observations)`` answers every role asked in a round (a scripted pair, a central
        controller, agents asked over the bus). ``seen``: gets every observation asked, in the order
        asked. An exception from a policy or source abandons the episode (no record) and propagates."""
        policies: Mapping[Role, Policy] = agents if isinstance(agents, Mapping) else {}
        source = InProcessAgents(dict(policies)) if isinstance(agents, Mapping) else agents
        observations = self.reset()
        try:
            while observations:
                if seen is not None:
                    seen.extend(observations.values())
                observations = self.step(source.decide(observations)).observations
        finally:
            if self._record is None:  # an exception: the episode's vehicles leave the scene
                self.abandon()
            for policy in policies.values():
                policy.end_episode(self.spec.episode_id)
        return self.record

    def action(self, role: Role, name: str, **fields: Any) -> Action:
        """An action answering ``role``'s pending observation (run, episode, decision filled in);
        ``fields``: ``waypoint_id``, ``cell``, ``candidate_id``, ``message``."""
        obs = self.pending.get(role)
        if obs is None:
            raise EnvStateError(f"{role} is not asked now (asked: {', '.join(self.pending) or 'nobody'})")
        return action_for(obs, name, **fields)

    def abandon(self) -> None:
        """Stop the episode in play without a record (its vehicles leave the scene); nothing if none."""
        if self._runner is not None and self._record is None:
            self._runner.teardown()
        self._runner = None

    def close(self) -> None:
        """Abandon the episode in play and close the scene if this Env built it; a second call does nothing."""
        if self._closed:
            return
        self.abandon()
        self._closed = True
        if self._own_scene:
            self._scene.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----- helpers -------------------------------------------------------------------------------
    def _finish(self) -> EpisodeRecord:
        assert self._runner is not None
        self._record = self._runner.finish()
        return self._record

    def _check_open(self, call: str) -> None:
        if self._closed:
            raise EnvStateError(f"{call}() after close(): this Env is closed; build another")

    def _check(self, pending: dict[Role, Observation], actions: Mapping[Role, Action | None]) -> None:
        extra = [r for r in actions if r not in pending]
        if extra:
            raise IllegalActionError(f"{', '.join(map(str, extra))} not asked this round (asked: {', '.join(pending)}): "
                                     "give actions only for Env.pending")
        for role, obs in pending.items():
            if role not in actions:
                raise IllegalActionError(f"{role} decision {obs.decision_index}: no action given (give None for a "
                                         "counted WAIT)")
            action = actions[role]
            problem = None if action is None else action_problem(obs, action)
            if problem is not None:
                raise IllegalActionError(f"{role} decision {obs.decision_index}: {problem}")


def action_problem(obs: Observation, action: Action) -> str | None:
    """Why ``action`` cannot answer ``obs`` (the world would turn it into a WAIT), or None: the
    world's refusal (another decision or role, a name not legal now), then its arguments against
    what ``obs`` offers. Reads ``obs`` only."""
    problem = rules.refusal(obs.role, obs, action)
    if problem is not None:
        return problem
    if (action.run_id, action.episode_id) != (obs.run_id, obs.episode_id):
        return f"action names run {action.run_id!r}, episode {action.episode_id!r}: not this one"
    name = action.action
    if name == MOVES[obs.role]:
        options = [w.waypoint_id for w in obs.waypoint_options]
        if action.waypoint_id not in options:
            return f"{name}: waypoint {action.waypoint_id!r} is not an option now (options: {', '.join(options)})"
    elif name == "ANNOTATE_CANDIDATE":
        try:
            parse_cell(action.cell or "")
        except ValueError as exc:
            return f"{name}: {exc}"
    elif name == "GO_TO_CANDIDATE" or (name == "REJECT" and action.candidate_id is not None):
        cand = _open_candidate(obs, action.candidate_id)
        if cand is None:
            open_ids = [c.candidate_id for c in obs.coordination.candidates if c.status in ("pending", "arrived")]
            return (f"{name}: candidate {action.candidate_id!r} is not one the UGV holds open "
                    f"(open: {', '.join(open_ids) or 'none'})")
        if name == "GO_TO_CANDIDATE" and cand.approach_waypoint_id is None:
            return f"{name}: candidate {cand.candidate_id} has no road approach"
    return None


def _open_candidate(obs: Observation, candidate_id: str | None) -> Candidate | None:
    return next((c for c in obs.coordination.candidates
                 if c.candidate_id == candidate_id and c.status in ("pending", "arrived")), None)


def _from_file(path: Path, index: int, look: str) -> EpisodeSpec:
    from agos.world.episodes.files import read_split

    episodes: Sequence[EpisodeSpec] = read_split(path, look=look)
    if not 0 <= index < len(episodes):
        raise IndexError(f"{path}: episode index {index} out of range (the file has {len(episodes)} episodes: "
                         f"0..{len(episodes) - 1})")
    return episodes[index]
