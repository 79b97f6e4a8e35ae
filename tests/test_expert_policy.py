"""The expert policy replays the world's plan through the real episode engine (in-process) and
succeeds: on a procedural town and an imported CARLA town, every difficulty, with no fallback,
its decisions exactly the plan's, the paper's three messages delivered, a wrong candidate
rejected in a hard episode where one is staged."""

from __future__ import annotations

from pathlib import Path

import pytest

from agos import Env
from agos.agents.names import tools_for
from agos.agents.registry import make_policy
from agos.runtime.episode_config import EpisodeConfig, ToolConfig
from agos.runtime.schemas import EpisodeRecord, ExpertStep, Observation
from agos.world.expert import planner
from agos.world.sim.scene import Scene

CARLA = Path(__file__).resolve().parents[2] / "shared" / "maps" / "carla"


def _play(town, scene, spec) -> tuple[EpisodeRecord, dict[str, list[ExpertStep]], list, list[str]]:
    """One expert episode in-process: its record, the plan the world made, its step events and the
    texts of the messages delivered."""
    plans: list = []
    original = planner.plan_episode

    def keep(st, **kwargs):
        plan = original(st, **kwargs)
        plans.append(plan)
        return plan

    class Events:
        def __init__(self) -> None:
            self.steps: list = []
            self.texts: list[str] = []

        def step(self, event) -> None:
            self.steps.append(event)

        def coordination(self, truth, views) -> None:
            pass

        def message(self, message) -> None:
            self.texts.append(message.text)

    sink = Events()
    planner.plan_episode = keep  # type: ignore[assignment]
    try:  # an expert configuration has the Env install the world's planner
        with Env(spec, EpisodeConfig(look="flat", tools=ToolConfig(expert=True)), run_id="t", worker_id="t",
                 scene=scene, town=town, sink=sink) as env:
            record = env.play({r: make_policy("expert", r) for r in ("uav", "ugv")})
    finally:
        planner.plan_episode = original  # type: ignore[assignment]
    assert len(plans) == 1, "the world plans once per episode"
    return record, plans[0].steps, sink.steps, sink.texts


@pytest.mark.slow
@pytest.mark.parametrize("town_name", ["tee-s17", "Town10HD"])
def test_the_expert_succeeds_and_its_decisions_are_the_plan(town_name: str) -> None:
    from agos.world.episodes.sampling import sample_episode
    from agos.world.towns.asset import freeze, open_town
    from agos.world.towns.imported import imported_layout

    if town_name.startswith("Town"):
        if not (CARLA / f"{town_name}.xodr").exists():
            pytest.skip("the CARLA maps are not in ../shared/maps/carla")
        town = freeze(imported_layout(CARLA / f"{town_name}.xodr"))
    else:
        town = open_town(town_name)
    with Scene(town.layout, look="flat") as scene:
        for d, difficulty in enumerate(("easy", "mid", "hard")):
            spec = sample_episode(town, scene, difficulty, 0, seed=3, stream=d)
            record, steps, events, texts = _play(town, scene, spec)
            assert record.success and record.termination == "confirmed", spec.episode_id
            assert record.fallbacks == 0
            assert (record.decisions_uav, record.decisions_ugv) == (len(steps["uav"]), len(steps["ugv"]))
            for event in events:  # each decision was the plan's step, at the plan's time
                step = steps[event.role][event.decision_index - 1]
                assert event.applied == step.action and event.sim_time_s == pytest.approx(step.sim_time_s, abs=1e-9)
            # the position exchange and any inspection request are delivered; the confirmation is sent as the episode ends
            assert any(t.startswith("UAV at (") for t in texts) and any(t.startswith("UGV at (") for t in texts)
            requests = sum("please verify" in (s.message or "") for s in steps["uav"])
            assert sum("please verify" in t for t in texts) == requests
            joined = steps["uav"][0].action == "ANNOTATE_CANDIDATE"  # the position and the request in one message
            assert sum(entry.kind == "message" for entry in record.ledger) == 3 + requests - joined
            assert record.n_confirm == 1
            rejected = [c for c in record.candidates if c.status == "rejected"]
            assert len(rejected) == sum(s.action == "REJECT" for s in steps["ugv"])  # each staged wrong candidate
            assert all(c.distance_to_polygon_m > 0 for c in rejected)  # a wrong candidate holds no target


def test_the_expert_needs_the_world_plan_and_only_its_runs_get_one() -> None:
    from agos.agents.expert import ExpertPolicy
    from agos.world.towns.asset import open_town

    assert tools_for({"uav": "expert", "ugv": "expert"})["expert"] is True
    assert tools_for({"uav": "oracle", "ugv": "oracle"})["expert"] is False
    assert EpisodeConfig().config_hash() == EpisodeConfig(tools=ToolConfig(expert=False)).config_hash()
    assert EpisodeConfig(tools=ToolConfig(expert=True)).config_hash() != EpisodeConfig().config_hash()
    town = open_town("tee-s17")
    with Scene(town.layout, look="flat") as scene:
        from agos.world.episodes.sampling import sample_episode

        spec = sample_episode(town, scene, "easy", 0, seed=3, stream=0)
        seen: list[Observation] = []
        with Env(spec, EpisodeConfig(look="flat"), run_id="t", worker_id="t", scene=scene, town=town) as env:
            env.play({r: make_policy("random", r) for r in ("uav", "ugv")}, seen=seen)
        assert seen and all(obs.expert is None for obs in seen)
        with pytest.raises(ValueError, match="policy 'expert'"):
            ExpertPolicy("uav").act(seen[0])
