"""A world worker's slot (world/sim/worker.py) is announced to agent services once for the worker's
session, and each episode's decision source waits, before the first observation, until each due role's
service has subscribed to the slot (its ``ready`` token): over the in-memory bus, which reports tokens
as zenoh does."""

from __future__ import annotations

import time

import pytest

from agos.runtime import keys
from agos.runtime.bus import Inbox, MemoryBus, Sample
from agos.runtime.process import StopFlag
from agos.world.sim.worker import AgentVanished, BusDecisionSource, MissingAgent, WorkerSlot


class _Due:
    decision_index = 1


def _source(bus: MemoryBus, wait_s: float = 0.2, episode: str = "e1") -> BusDecisionSource:
    return BusDecisionSource(WorkerSlot(bus, "r", "w1"), episode, timeout_s=1.0, stop=StopFlag(), agent_wait_s=wait_s)


def test_the_slot_token_lives_while_the_slot_does_whatever_the_episodes() -> None:
    bus, changes = MemoryBus(), Inbox()
    bus.watch_liveliness(keys.slot_live("r", "*"), changes)
    slot = WorkerSlot(bus, "r", "w1")
    assert changes.drain() == [Sample("agos/r/slot/w1/live", b"+")]
    declared = (list(bus._subs), list(bus._watchers))
    for episode in ("e1", "e2", "e3"):  # episodes declare nothing of their own
        BusDecisionSource(slot, episode, timeout_s=1.0, stop=StopFlag()).close()
    assert changes.drain() == [] and (bus._subs, bus._watchers) == declared
    slot.close()
    assert changes.drain() == [Sample("agos/r/slot/w1/live", b"-")]
    assert bus._subs == [] and bus._watchers == [(keys.slot_live("r", "*"), changes)]


def test_an_agent_lost_mid_episode_ends_the_attempt_even_if_another_took_its_place() -> None:
    bus = MemoryBus()
    source = BusDecisionSource(WorkerSlot(bus, "r", "w1"), "e1", timeout_s=1.0, stop=StopFlag(), reconnect_grace_s=0.2)
    ready = bus.declare_token(keys.slot_ready("r", "w1", "uav", "uav-1"))
    source._check_agents({"uav": _Due()})  # type: ignore[dict-item]
    source._watch_agents()
    bus.undeclare_token(ready)  # a router restart: gone, and back within the grace with its memory
    source._watch_agents()
    ready = bus.declare_token(keys.slot_ready("r", "w1", "uav", "uav-1"))
    time.sleep(0.3)
    source._watch_agents()
    bus.undeclare_token(ready)
    source._watch_agents()  # none back yet: within the grace
    bus.declare_token(keys.slot_ready("r", "w1", "uav", "uav-2"))  # a restarted service, without the memory
    with pytest.raises(AgentVanished, match="UAV"):
        source._watch_agents()
    source.close()


def test_agents_that_stay_away_past_the_grace_end_the_attempt() -> None:
    bus = MemoryBus()
    source = BusDecisionSource(WorkerSlot(bus, "r", "w1"), "e1", timeout_s=1.0, stop=StopFlag(), reconnect_grace_s=0.0)
    ready = bus.declare_token(keys.slot_ready("r", "w1", "ugv", "ugv-1"))
    source._check_agents({"ugv": _Due()})  # type: ignore[dict-item]
    bus.undeclare_token(ready)
    with pytest.raises(AgentVanished, match="UGV"):
        source._watch_agents()
    source.close()


def test_first_decision_waits_for_the_agents_ready_token_not_for_any_subscriber() -> None:
    bus = MemoryBus()
    source = _source(bus)
    bus.subscribe("agos/**", Inbox())  # an observer of everything is not an agent
    with pytest.raises(MissingAgent, match="UAV"):
        source._check_agents({"uav": _Due()})  # type: ignore[dict-item]
    bus.declare_token(keys.slot_ready("r", "w1", "uav", "uav-1"))
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
    source = BusDecisionSource(WorkerSlot(bus, "r", "w2"), "e1", timeout_s=1.0, stop=StopFlag(), agent_wait_s=0.2,
                               attempt=2)
    bus.declare_token(keys.slot_ready("r", "w2", "uav", "uav-1"))

    class Agent(Inbox):
        def put(self, sample: Sample) -> None:
            obs = decode(sample.payload)
            assert obs.attempt == 2  # the world stamps its attempt on every observation
            # a late answer of the slot's previous episode, one of another attempt, then the one asked
            for episode, attempt, action in (("e0", 2, "REJECT"), ("e1", 1, "CONFIRM"), ("e1", 2, "WAIT")):
                bus.publish(keys.act("r", "w2", "uav"), encode(Action(
                    run_id="r", episode_id=episode, role="uav", decision_index=obs.decision_index, attempt=attempt,
                    action=action)))

    bus.subscribe(keys.obs("r", "w2", "uav"), Agent())
    obs = Observation(run_id="r", episode_id="e1", role="uav", decision_index=1, sim_time_s=0.0,
                      pose=Pose(position_world_m=(0.0, 0.0, 80.0), yaw_rad=0.0), mode="aerial", images=[],
                      references=[], legal_actions=["WAIT", "CONFIRM"], waypoint_options=[],
                      region_world_m=(0.0, 0.0, 1.0, 1.0), coordination=CoordinationState(run_id="r", episode_id="e1",
                                                                                        sim_time_s=0.0))
    answered = source.decide({"uav": obs})["uav"]
    assert answered is not None and (answered.action, answered.attempt) == ("WAIT", 2)
    assert sorted(reason for _, reason in source.rejections.counts) == [
        "for another attempt of the episode", "for another episode than the slot's"]
    source.close()
