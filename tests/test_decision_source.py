"""The world's decision source (world/sim/worker.py) announces its episode to agent services and waits,
before the first observation, until each due role's service has subscribed (its ``ready`` token):
over the in-memory bus, which reports tokens as zenoh does."""

from __future__ import annotations

import pytest

from agos.runtime import keys
from agos.runtime.bus import Inbox, MemoryBus, Sample
from agos.runtime.process import StopFlag
from agos.world.sim.worker import BusDecisionSource, MissingAgent


class _Due:
    decision_index = 1


def _source(bus: MemoryBus, wait_s: float = 0.2) -> BusDecisionSource:
    return BusDecisionSource(bus, "r", "e1", worker_id="w1", timeout_s=1.0, stop=StopFlag(), agent_wait_s=wait_s)


def test_the_episode_token_lives_while_the_source_does() -> None:
    bus, changes = MemoryBus(), Inbox()
    bus.watch_liveliness(keys.episode_live("r", "*", "*"), changes)
    source = _source(bus)
    assert changes.drain() == [Sample("agos/r/ep/e1/live/w1", b"+")]
    source.close()
    assert changes.drain() == [Sample("agos/r/ep/e1/live/w1", b"-")]
    assert bus._subs == [] and bus._watchers == [(keys.episode_live("r", "*", "*"), changes)]


def test_first_decision_waits_for_the_agents_ready_token_not_for_any_subscriber() -> None:
    bus = MemoryBus()
    source = _source(bus)
    bus.subscribe("agos/**", Inbox())  # an observer of everything is not an agent
    with pytest.raises(MissingAgent, match="UAV"):
        source._check_agents({"uav": _Due()})  # type: ignore[dict-item]
    bus.declare_token(keys.episode_ready("r", "e1", "uav", "uav-1"))
    source._check_agents({"uav": _Due()})  # type: ignore[dict-item]
    with pytest.raises(MissingAgent, match="UGV"):  # the UAV's token does not stand for the UGV
        source._check_agents({"uav": _Due(), "ugv": _Due()})  # type: ignore[dict-item]
    source.close()


def test_answers_to_another_attempt_are_ignored() -> None:
    """A re-leased episode's world (attempt 2) takes only answers to attempt 2: a late action meant for
    the world that ran attempt 1 never steers it."""
    from agos.runtime.codec import decode, encode
    from agos.runtime.schemas import Action, CoordinationState, Observation, Pose

    bus = MemoryBus()
    source = BusDecisionSource(bus, "r", "e1", worker_id="w2", timeout_s=1.0, stop=StopFlag(), agent_wait_s=0.2,
                               attempt=2)
    bus.declare_token(keys.episode_ready("r", "e1", "uav", "uav-1"))

    class Agent(Inbox):
        def put(self, sample: Sample) -> None:
            obs = decode(sample.payload)
            assert obs.attempt == 2  # the world stamps its attempt on every observation
            for attempt, action in ((1, "CONFIRM"), (2, "WAIT")):
                bus.publish(keys.act("r", "e1", "uav"), encode(Action(
                    run_id="r", episode_id="e1", role="uav", decision_index=obs.decision_index, attempt=attempt,
                    action=action)))

    bus.subscribe(keys.obs("r", "e1", "uav"), Agent())
    obs = Observation(run_id="r", episode_id="e1", role="uav", decision_index=1, sim_time_s=0.0,
                      pose=Pose(position_world_m=(0.0, 0.0, 80.0), yaw_rad=0.0), mode="aerial", images=[],
                      references=[], legal_actions=["WAIT", "CONFIRM"], waypoint_options=[],
                      region_world_m=(0.0, 0.0, 1.0, 1.0), coordination=CoordinationState(run_id="r", episode_id="e1",
                                                                                        sim_time_s=0.0))
    answered = source.decide({"uav": obs})["uav"]
    assert answered is not None and (answered.action, answered.attempt) == ("WAIT", 2)
    source.close()
