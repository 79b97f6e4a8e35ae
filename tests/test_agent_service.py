"""The agent service's dispatch (agents/agent_service.py) over the in-memory bus: inline policies are
answered on the publishing thread, the others on the asyncio loop; errors cost a WAIT."""

from __future__ import annotations

import asyncio
import os
import threading
import time

import pytest

from agos.agents.agent_service import serve_async
from agos.agents.contract import Policy, action_for
from agos.agents.registry import make_policy
from agos.runtime import keys
from agos.runtime.bus import Inbox, MemoryBus
from agos.runtime.codec import decode, encode
from agos.runtime.process import StopFlag
from agos.runtime.schemas import Action, CoordinationState, EpisodeRecord, Observation, Pose, Waypoint

from support.waiting import wait_until

ANSWER_HANG_BOUND_S = 30.0
"""A hang bound, not a timing promise: an answer in process takes microseconds."""

RUN = "svc"


def _obs(episode: str = "e1", index: int = 1) -> Observation:
    return Observation(
        run_id=RUN, episode_id=episode, role="uav", decision_index=index, sim_time_s=float(index),
        pose=Pose(position_world_m=(0.0, 0.0, 80.0), yaw_rad=0.0), mode="aerial", images=[], references=[],
        legal_actions=["MOVE_TO_UAV_WAYPOINT", "WAIT"],
        waypoint_options=[Waypoint(waypoint_id="U1", position_world_m=(40.0, 0.0, 80.0), kind="uav_grid")],
        region_world_m=(0.0, 0.0, 100.0, 100.0),
        coordination=CoordinationState(run_id=RUN, episode_id=episode, sim_time_s=float(index)))




class Serving:
    """serve_async on its own loop thread, over a MemoryBus the test publishes into."""

    def __init__(self, policy, reconnect_grace_s: float = 0.0) -> None:
        self.bus, self.stop, self.policy = MemoryBus(), StopFlag(), policy
        self.actions = Inbox()
        self.bus.subscribe(keys.act(RUN, "*", "uav"), self.actions)
        self.thread = threading.Thread(target=lambda: asyncio.run(serve_async(
            self.bus, policy, RUN, self.stop, concurrency=4, reconnect_grace_s=reconnect_grace_s)), daemon=True)
        self.thread.start()
        self.token = self.bus.declare_token(keys.slot_live(RUN, "w1"))  # as a world worker's slot
        assert wait_until(lambda: self.bus.wait_for_subscriber(keys.obs(RUN, "w1", "uav"), 0))

    def __enter__(self) -> Serving:
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join(5)

    def tell(self, index: int, attempt: int, worker: str = "w1") -> None:
        """Publish observation ``index`` of attempt ``attempt`` on ``worker``'s slot: MemoryBus hands it
        over before this returns, so it is taken or dropped by then."""
        obs = _obs(index=index)
        obs.attempt = attempt
        self.bus.publish(keys.obs(RUN, worker, "uav"), encode(obs))

    def ask(self, index: int, attempt: int, worker: str = "w1") -> Action:
        """:meth:`tell`, and the answer."""
        self.tell(index, attempt, worker)
        sample = self.actions.get(ANSWER_HANG_BOUND_S)
        assert sample is not None, "no answer"
        return decode(sample.payload)


def test_inline_policy_is_answered_on_the_publishing_thread() -> None:
    with Serving(make_policy("standin-0ms", "uav")) as svc:
        assert svc.policy.inline
        svc.bus.publish(keys.obs(RUN, "w1", "uav"), encode(_obs()))
        sample = svc.actions.get(0)  # already there when publish returns: no hand-over to the loop
        assert sample is not None
        action = decode(sample.payload)
        assert (action.action, action.waypoint_id, action.decision_index) == ("MOVE_TO_UAV_WAYPOINT", "U1", 1)
        assert action.agent_wall_latency_s is not None


def test_async_policies_are_answered_on_the_loop() -> None:
    with Serving(make_policy("standin-20ms", "uav")) as svc:
        assert not svc.policy.inline
        svc.bus.publish(keys.obs(RUN, "w1", "uav"), encode(_obs()))
        sample = svc.actions.get(5.0)
        assert sample is not None and decode(sample.payload).action == "MOVE_TO_UAV_WAYPOINT"
        assert decode(sample.payload).agent_wall_latency_s > 0


class Gated(Policy):
    """A plain ``act`` policy that answers only once the test opens its gate."""

    role, name = "uav", "gated"

    def __init__(self) -> None:
        self.gate, self.threads = threading.Event(), []

    def act(self, obs: Observation) -> Action:
        self.threads.append(threading.get_ident())
        assert self.gate.wait(5.0)
        return action_for(obs, "WAIT")

    def end_episode(self, episode_id: str) -> None:
        pass


def test_plain_policies_run_in_worker_threads() -> None:
    policy = Gated()
    with Serving(policy) as svc:
        svc.bus.publish(keys.obs(RUN, "w1", "uav"), encode(_obs()))
        assert svc.actions.get(0) is None  # publish returned while the policy still waits
        policy.gate.set()
        sample = svc.actions.get(5.0)
        assert sample is not None and decode(sample.payload).action == "WAIT"
        assert policy.threads and policy.threads[0] not in (threading.get_ident(), svc.thread.ident)


class Exploding(Policy):
    role, name = "uav", "exploding"

    def __init__(self, inline: bool) -> None:
        self.inline, self.ended = inline, []

    def act(self, obs: Observation) -> Action:
        if obs.decision_index == 1:
            raise RuntimeError("bug in the policy")
        return action_for(obs, "WAIT", rationale="fine")

    def end_episode(self, episode_id: str) -> None:
        self.ended.append(episode_id)


@pytest.mark.parametrize("inline", [True, False])
def test_policy_errors_cost_a_wait_and_episodes_end(inline: bool) -> None:
    policy = Exploding(inline)
    with Serving(policy) as svc:
        svc.bus.publish(keys.obs(RUN, "w1", "uav"), encode(_obs(index=1)))
        svc.bus.publish(keys.obs(RUN, "w1", "uav"), b"not msgpack")  # logged, ignored
        svc.bus.publish(keys.obs(RUN, "w1", "uav"), encode(_obs(index=2)))
        got = [decode(s.payload) for s in (svc.actions.get(5.0), svc.actions.get(5.0))]
        assert sorted((a.decision_index, a.action, a.rationale) for a in got) == [
            (1, "WAIT", "policy error (see agent log)"), (2, "WAIT", "fine")]
        record = EpisodeRecord(
            run_id=RUN, episode_id="e1", difficulty="easy", status="finished", termination="budget_exhausted",
            success=False, ground_observed=False, n_confirm=0, ugv_path_length_m=0.0, shortest_path_length_m=None,
            final_distance_m=50.0, uav_budget=80, uav_first_visible_step=None, candidates=[], decisions_uav=2,
            decisions_ugv=0, sim_time_s=2.0, wall_time_s=0.1, worker_id="w", town_id="grid-s7", asset_sha256="ab" * 32,
            seed=1, renderer="tiny")
        svc.bus.publish(keys.result(RUN, "w1"), encode(record))  # anyone may publish a result: it ends nothing
        time.sleep(0.2)
        assert policy.ended == []
        svc.bus.publish(keys.obs(RUN, "w1", "uav"), encode(_obs("e2", index=2)))  # the slot's next episode
        assert svc.actions.get(5.0) is not None
        assert wait_until(lambda: policy.ended == ["e1"])
        svc.bus.undeclare_token(svc.token)  # the world worker is gone
        assert wait_until(lambda: policy.ended == ["e1", "e2"])


class Mistyped(Policy):
    """Answers through ``action_for`` (an ``Action`` struct, built without checks) with values the
    world would refuse, or with no action at all."""

    name, inline = "mistyped", True

    def act(self, obs) -> Action:
        if obs.decision_index == 1:
            return action_for(obs, "FLY")  # not an action name
        if obs.decision_index == 2:
            return action_for(obs, "MOVE_TO_UAV_WAYPOINT", waypoint_id=7)  # not a string
        return {"action": "WAIT"}  # not an Action

    def end_episode(self, episode_id: str) -> None:
        pass


def test_mistyped_answers_cost_a_wait() -> None:
    with Serving(Mistyped("uav")) as svc:
        for index in (1, 2, 3):
            svc.bus.publish(keys.obs(RUN, "w1", "uav"), encode(_obs(index=index)))
        got = [decode(svc.actions.get(5.0).payload) for _ in range(3)]
        assert [(type(a), a.decision_index, a.action, a.rationale) for a in got] == [
            (Action, i, "WAIT", "policy error (see agent log)") for i in (1, 2, 3)]


def test_observations_are_subscribed_exactly_while_a_world_holds_its_slot() -> None:
    with Serving(make_policy("standin-0ms", "uav")) as svc:
        exact = keys.obs(RUN, "w1", "uav")
        assert [expr for expr, _ in svc.bus._subs if "/obs/" in expr] == [exact]  # no slot/*/obs wildcard
        ready = Inbox()
        svc.bus.watch_liveliness(keys.slot_ready(RUN, "*", "*", "*"), ready)
        [(key, payload)] = [(s.key, s.payload) for s in ready.drain()]
        assert payload == b"+" and key.startswith(keys.slot_ready(RUN, "w1", "uav", f"uav-{os.getpid()}-"))
        assert not svc.bus.wait_for_subscriber(keys.obs(RUN, "w2", "uav"), 0)  # no worker w2
        second = svc.bus.declare_token(keys.slot_live(RUN, "w2"))
        svc.bus.undeclare_token(svc.token)
        svc.bus.declare_token(keys.slot_live(RUN, "w9"))  # handled after the two changes above
        assert wait_until(lambda: svc.bus.wait_for_subscriber(keys.obs(RUN, "w9", "uav"), 0))
        assert not svc.bus.wait_for_subscriber(exact, 0)  # w1 is gone
        svc.bus.publish(keys.obs(RUN, "w2", "uav"), encode(_obs()))
        answer = svc.actions.get(0)
        assert answer is not None and answer.key == keys.act(RUN, "w2", "uav")  # on the asking slot
        svc.bus.undeclare_token(second)
        assert wait_until(lambda: not svc.bus.wait_for_subscriber(keys.obs(RUN, "w2", "uav"), 0))
        assert sorted((s.key.split("/")[3], s.payload) for s in ready.drain()) == [
            ("w1", b"-"), ("w2", b"+"), ("w2", b"-"), ("w9", b"+")]
        svc.bus.publish(exact, encode(_obs(index=2)))
        assert svc.actions.get(0.1) is None


def test_a_service_started_after_the_world_serves_the_slots_in_flight() -> None:
    bus, stop = MemoryBus(), StopFlag()
    bus.declare_token(keys.slot_live(RUN, "w1"))  # the world was there first
    actions = Inbox()
    bus.subscribe(keys.act(RUN, "w1", "uav"), actions)
    thread = threading.Thread(target=lambda: asyncio.run(serve_async(bus, make_policy("standin-0ms", "uav"), RUN, stop,
                                                                     concurrency=1)), daemon=True)
    thread.start()
    try:
        assert wait_until(lambda: bus.wait_for_subscriber(keys.obs(RUN, "w1", "uav"), 0))
        bus.publish(keys.obs(RUN, "w1", "uav"), encode(_obs("e7")))
        assert actions.get(1.0) is not None
    finally:
        stop.set()
        thread.join(5)


class _Remembering(Policy):
    """A policy whose answer depends on its memory of the episode: the number of decisions it has
    seen, as the waypoint id it names."""

    name = "remembering"
    role = "uav"

    def __init__(self, inline: bool) -> None:
        self.inline = inline
        self.memory: dict[str, int] = {}

    def end_episode(self, episode_id: str) -> None:
        self.memory.pop(episode_id, None)

    def act(self, obs: Observation) -> Action:
        self.memory[obs.episode_id] = self.memory.get(obs.episode_id, 0) + 1
        return action_for(obs, "MOVE_TO_UAV_WAYPOINT", waypoint_id=f"U{self.memory[obs.episode_id]}")


@pytest.mark.parametrize("inline", [True, False], ids=["inline", "on-the-loop"])
def test_a_new_attempt_starts_afresh_and_late_observations_of_the_old_one_are_ignored(inline: bool) -> None:
    """A re-leased episode (attempt 2) is a fresh episode for the policy; an observation of attempt 1
    arriving after it (a world that was thought dead) is not answered; answers carry the attempt."""
    with Serving(_Remembering(inline)) as svc:
        asked = [svc.ask(1, 1), svc.ask(2, 1), svc.ask(3, 1)]
        assert [(a.waypoint_id, a.attempt) for a in asked] == [("U1", 1), ("U2", 1), ("U3", 1)]
        first = svc.ask(1, 2)
        assert (first.waypoint_id, first.attempt, first.decision_index) == ("U1", 2, 1)  # memory of attempt 1 gone
        svc.tell(4, 1)  # late, of the old attempt: had the policy seen it, the next answer would name U3
        second = svc.ask(2, 2)
        assert (second.waypoint_id, second.attempt, second.decision_index) == ("U2", 2, 2)
        assert svc.actions.get(0) is None


def test_an_episode_re_leased_to_another_worker_starts_afresh_there() -> None:
    """Attempt 2 on another worker's slot: the policy forgets attempt 1 (its world was thought dead),
    and a late observation of attempt 1 on the old slot is not answered."""
    with Serving(_Remembering(True)) as svc:
        svc.bus.declare_token(keys.slot_live(RUN, "w2"))
        assert wait_until(lambda: svc.bus.wait_for_subscriber(keys.obs(RUN, "w2", "uav"), 0))

        assert [svc.ask(i, 1).waypoint_id for i in (1, 2)] == ["U1", "U2"]
        assert svc.ask(1, 2, worker="w2").waypoint_id == "U1"
        svc.tell(3, 1)  # late, on the old slot: had the policy seen it, the next answer would name U3
        assert (svc.ask(2, 2, worker="w2").waypoint_id, svc.actions.get(0)) == ("U2", None)
        assert svc.policy.memory == {"e1": 2}


@pytest.mark.parametrize("inline", [True, False], ids=["inline", "on-the-loop"])
def test_a_decision_asked_again_gets_the_same_answer_without_asking_the_policy(inline: bool) -> None:
    """The world publishes an unanswered observation again (its answer was lost, say while a router
    restarted): the answer already sent goes again, and the policy's memory moves once."""
    with Serving(_Remembering(inline)) as svc:
        for _ in range(3):
            svc.bus.publish(keys.obs(RUN, "w1", "uav"), encode(_obs(index=1)))
            assert decode(svc.actions.get(2.0).payload).waypoint_id == "U1"
        svc.bus.publish(keys.obs(RUN, "w1", "uav"), encode(_obs(index=2)))
        assert decode(svc.actions.get(2.0).payload).waypoint_id == "U2"
        assert svc.policy.memory == {"e1": 2}


def test_a_slot_back_within_the_grace_keeps_its_episode() -> None:
    """A router restart takes every token away for seconds: the slot's episode is forgotten only if its
    token stays away ``reconnect_grace_s``."""
    with Serving(_Remembering(True), reconnect_grace_s=0.5) as svc:
        def ask(index: int) -> str:
            svc.bus.publish(keys.obs(RUN, "w1", "uav"), encode(_obs(index=index)))
            return decode(svc.actions.get(2.0).payload).waypoint_id

        assert ask(1) == "U1"
        svc.bus.undeclare_token(svc.token)
        svc.token = svc.bus.declare_token(keys.slot_live(RUN, "w1"))  # back at once
        time.sleep(0.7)
        assert ask(2) == "U2" and svc.policy.memory == {"e1": 2}
        svc.bus.undeclare_token(svc.token)
        assert wait_until(lambda: svc.policy.memory == {})  # gone for good
