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
