"""The UAV while the UGV verifies its candidate, an episode setting (docs/AGENTS.md): ``frozen`` (the
default, asked nothing until it hears the candidate resolved) or ``active`` (asked as usual, only
MOVE_TO_UAV_WAYPOINT or WAIT legal, a message riding with either). The world's rules in-process, the
setting in the configuration hash, and the ways to set it."""

from __future__ import annotations

import pytest

from agos import Env
from agos.agents.contract import action_for
from agos.deploy.cli import build_parser
from agos.deploy.cli.common import settings_of
from agos.deploy.run.configure import run_episode_config
from agos.runtime.episode_config import EpisodeConfig, StoredConfigError, ToolConfig, config_hash, read_config
from agos.runtime.schemas import Action, Observation, Role, StepEvent
from agos.runtime.settings import load_config
from agos.world.episodes.sampling import generate_episodes
from agos.world.sim.engine import NullSink
from agos.world.sim.scene import Scene
from agos.world.towns.asset import build_town

GUIDANCE = "Candidate is the red car by the kerb."


@pytest.fixture(scope="module")
def world():
    town = build_town("grid", 7)
    with Scene(town.layout, look="flat") as scene:
        yield town, scene, generate_episodes(town, scene, per_difficulty=1, seed=1)[0]


class Log(NullSink):
    def __init__(self) -> None:
        self.steps: list[StepEvent] = []

    def step(self, event: StepEvent) -> None:
        self.steps.append(event)


class AnnotateThenHold:
    """The UAV annotates the centre cell at once, then (while its candidate is open) tries
    NO_RELIABLE_CANDIDATE, then moves, then WAITs with a guidance message; afterwards it WAITs. The
    UGV WAITs, and REJECTs the candidate once it has heard the guidance (never, with ``reject=False``)."""

    def __init__(self, *, reject: bool = True) -> None:
        self.reject = reject
        self.seen: list[Observation] = []
        """What it was asked, in order (Env.play's ``seen``)."""
        self.open_tries = 0

    def decide(self, observations: dict[Role, Observation]) -> dict[Role, Action | None]:
        return {role: self._choose(obs) for role, obs in observations.items()}

    def _choose(self, obs: Observation) -> Action:
        open_ = [c for c in obs.coordination.candidates if c.status in ("pending", "arrived")]
        if obs.role == "ugv":
            heard = any(m.text == GUIDANCE for m in obs.coordination.messages)
            if self.reject and open_ and heard:
                return action_for(obs, "REJECT", candidate_id=open_[0].candidate_id)
            return action_for(obs, "WAIT")
        if obs.decision_index == 1:
            return action_for(obs, "ANNOTATE_CANDIDATE", cell="C3")
        if open_:
            self.open_tries += 1
            if self.open_tries == 1:
                return action_for(obs, "NO_RELIABLE_CANDIDATE")
            if self.open_tries == 2:
                return action_for(obs, "MOVE_TO_UAV_WAYPOINT", waypoint_id=obs.waypoint_options[0].waypoint_id)
        return action_for(obs, "WAIT", message=GUIDANCE if open_ else None)


def _run(world, config: EpisodeConfig, source: AnnotateThenHold) -> Log:
    town, scene, spec = world
    log = Log()
    with Env(spec, config, illegal="wait", run_id="t", worker_id="w", scene=scene, town=town, sink=log) as env:
        env.play(source, seen=source.seen)  # illegal="wait": the UAV's NO_RELIABLE_CANDIDATE while verified is the world's WAIT
    return log


@pytest.mark.slow
def test_active_uav_may_only_move_or_wait_while_its_candidate_is_verified(world) -> None:
    source = AnnotateThenHold()
    log = _run(world, EpisodeConfig(look="flat", uav_during_verification="active"), source)
    uav_steps = [s for s in log.steps if s.role == "uav"]
    annotate = uav_steps[0]
    assert annotate.applied == "ANNOTATE_CANDIDATE"
    reject = next(s for s in log.steps if s.applied == "REJECT")
    # asked again as soon as the annotation is done, not frozen until the UGV decides
    during = [o for o in source.seen if o.role == "uav" and o.decision_index > 1
              and any(c.status in ("pending", "arrived") for c in o.coordination.candidates)]
    assert len(during) >= 3 and during[0].sim_time_s == pytest.approx(annotate.sim_time_s + 1.0)
    assert all(o.legal_actions == ["MOVE_TO_UAV_WAYPOINT", "WAIT"] for o in during)
    by_index = {s.decision_index: s for s in uav_steps}
    tried_open = by_index[during[0].decision_index]
    assert tried_open.applied == "WAIT" and "NO_RELIABLE_CANDIDATE is not legal now" in (tried_open.fallback_reason or "")
    assert by_index[during[1].decision_index].applied == "MOVE_TO_UAV_WAYPOINT"
    guided = by_index[during[2].decision_index]
    assert guided.applied == "WAIT" and guided.fallback_reason is None
    assert log.steps.index(guided) < log.steps.index(reject)  # the UGV rejected after hearing the guidance
    # once the UAV hears of the rejection, the whole search set is back
    after = [o for o in source.seen if o.role == "uav" and o.coordination.candidates
             and all(c.status == "rejected" for c in o.coordination.candidates)]
    assert after and {"ANNOTATE_CANDIDATE", "NO_RELIABLE_CANDIDATE", "WAIT"} <= set(after[0].legal_actions)


@pytest.mark.slow
def test_frozen_uav_is_asked_nothing_until_max_freeze_and_keeps_its_actions(world) -> None:
    config = EpisodeConfig(look="flat")
    assert config.uav_during_verification == "frozen"  # the default
    source = AnnotateThenHold(reject=False)
    log = _run(world, config, source)
    annotate = next(s for s in log.steps if s.role == "uav")
    asked = [o for o in source.seen if o.role == "uav" and o.decision_index == 2]
    assert asked and asked[0].sim_time_s >= annotate.sim_time_s + config.max_freeze_s
    # the frozen UAV, asked after the timeout with its candidate still open: the actions it always had
    assert asked[0].legal_actions == ["MOVE_TO_UAV_WAYPOINT", "NO_RELIABLE_CANDIDATE", "WAIT"]


def test_the_setting_counts_in_the_hash_only_when_active() -> None:
    frozen, active = EpisodeConfig(), EpisodeConfig(uav_during_verification="active")
    assert frozen.config_hash() != active.config_hash()
    stored = frozen.model_dump(mode="json")
    assert stored["uav_during_verification"] == "frozen"  # named in every stored configuration
    before_the_field = {k: v for k, v in stored.items() if k != "uav_during_verification"}
    assert frozen.config_hash() == config_hash(before_the_field)  # records made before it keep their hash
    assert read_config(before_the_field, where="old record").uav_during_verification == "frozen"
    assert config_hash(active.model_dump(mode="json")) == active.config_hash()


def test_the_expert_refuses_an_active_uav() -> None:
    with pytest.raises(ValueError, match="frozen"):
        EpisodeConfig(uav_during_verification="active", tools=ToolConfig(expert=True))
    stored = {**EpisodeConfig().model_dump(mode="json"), "uav_during_verification": "active",
              "tools": {**ToolConfig(expert=True).model_dump(), "expert": True}}
    with pytest.raises(StoredConfigError, match="uav_during_verification"):
        read_config(stored, where="job grant")


def test_the_setting_is_reachable_from_flag_file_and_environment(tmp_path) -> None:
    args = build_parser().parse_args(["eval", "--uav-verification", "active"])
    cfg = settings_of(args)
    assert cfg.world.uav_during_verification == "active"
    run_config = run_episode_config(cfg, policies={"uav": "agos-agent", "ugv": "agos-agent"})
    assert run_config.uav_during_verification == "active"
    assert settings_of(build_parser().parse_args(["eval"])).world.uav_during_verification == "frozen"
    toml = tmp_path / "c.toml"
    toml.write_text('[world]\nuav_during_verification = "active"\n')
    assert load_config(toml, environ={}).world.uav_during_verification == "active"
    env = {"AGOS_WORLD__UAV_DURING_VERIFICATION": "active"}
    assert load_config(None, environ=env).world.uav_during_verification == "active"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["eval", "--uav-verification", "sometimes"])
