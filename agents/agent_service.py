"""The agent service process: one role, one policy, many episodes at once.

    agos agent --role uav --policy heuristic --connect tcp/HOST:PORT --run RUN [--concurrency 32]

Every observation on a world worker's slot, ``agos/<run>/slot/<worker>/obs/<role>``, is answered on
the slot's ``.../act/<role>`` key, for each slot a world announces with its liveliness token
(``agos/<run>/slot/<worker>/live``); one slot carries the worker's episodes one after another, each
observation naming its episode and attempt. Observations are handled concurrently on an asyncio loop, at most
``concurrency`` at a time: the service awaits each policy's ``act_async`` (agents/contract.py), so
policies that define one (remote models, the fixed-latency stand-in) overlap their waiting, and
the others run ``act`` in one of ``concurrency`` worker threads (the contract's default);
``inline`` policies (microseconds, no I/O: random, oracle, standin-0ms) are answered on the
thread that received the observation. Policies receive the decoded ``Observation`` struct and
answer an ``Action`` struct, which is encoded and read back as the world will read it before it
is sent. A policy that raises (or answers what the world would refuse) is logged and answered
with a legal WAIT, so an agent bug costs a decision, never the episode. A policy whose model
endpoint gave no answer (:class:`~agos.agents.contract.EndpointOutage`) is answered with
``Action.outage`` instead: no decision, the world pauses the episode. A restarted service simply
answers what the world re-requests.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from agos.agents.contract import EndpointOutage, FatalPolicyError, Policy, action_for
from agos.agents.names import needs_vlm
from agos.agents.registry import make_policy
from agos.runtime import keys
from agos.runtime.bus import Bus, Sample, ZenohBus
from agos.runtime.codec import DecodeError, decode, decode_as, encode
from agos.runtime.health import announce, unique_id
from agos.runtime.process import StopFlag, install_stop_handlers, setup_logging
from agos.runtime.rejections import Rejections, non_finite_field
from agos.runtime.schemas import Action, Observation, Role
from agos.runtime.settings import DEFAULTS, AgosConfig

log = logging.getLogger("agos.agent")


class _Dispatch:
    """Takes each payload on the zenoh thread that received it: decodes it there (tens of
    microseconds, bounded) and then either answers at once, for ``inline`` policies (microseconds,
    no I/O), or hands the decoded message to the asyncio loop. Answering inline saves a thread
    hand-over per decision (docs/ARCHITECTURE.md, "Decision round trip").

    Observations of different slots may call in from different threads: one lock serialises
    decoding, the slots' episode bookkeeping and, for inline policies, every policy call."""

    def __init__(self, bus: Bus, policy: Policy, run_id: str, loop: asyncio.AbstractEventLoop,
                 on_loop: Callable[[str, Observation], None]) -> None:
        self.bus, self.policy, self.run_id, self.loop, self.on_loop = bus, policy, run_id, loop, on_loop
        self.inline = policy.inline
        self.lock = threading.Lock()
        self.slots: dict[str, tuple[str, int]] = {}  # worker -> the (episode, attempt) its slot runs now
        self.asked: dict[str, tuple[str, int, int]] = {}  # worker -> the latest decision (episode, attempt, index)
        self.answers: dict[str, bytes] = {}  # worker -> the answer sent to it, once sent
        self.rejections = Rejections(log)

    def _current(self, worker: str, obs: Observation) -> bool:
        """Whether ``obs`` (on ``worker``'s slot) belongs to the episode's latest attempt, noting it as
        the slot's episode. A slot that moved on to another episode ends the policy's memory of the one
        it ran (unless another slot runs it now). A newer attempt (the episode was re-leased, here or to
        another worker) starts afresh: the policy forgets the earlier one before this observation is
        answered. A late observation of an older attempt is ignored."""
        episode, attempt = obs.episode_id, obs.attempt
        if self.slots.get(worker) == (episode, attempt):
            return True
        newest = max((a for e, a in self.slots.values() if e == episode), default=attempt)
        if attempt < newest:
            log.info("ignoring %s decision %d of attempt %d: attempt %d is running", episode,
                     obs.decision_index, attempt, newest)
            return False
        previous = self.slots.pop(worker, None)
        if previous is not None and previous[0] != episode:
            self._release(previous[0])
        earlier = [w for w, (e, a) in self.slots.items() if e == episode and a < attempt]
        for w in earlier:
            del self.slots[w]
        if earlier or (previous is not None and previous[0] == episode):
            log.info("%s re-leased (attempt %d): its earlier attempt is forgotten", episode, attempt)
            self._end(episode)
        self.slots[worker] = (episode, attempt)
        return True

    def take(self, payload: bytes, worker: str, key: str) -> None:
        """One payload received on ``worker``'s observation key ``key``: answered when it is an
        observation of this run for that key's role, with finite numbers, of the episode's latest
        attempt; anything else is refused and counted."""
        with self.lock:
            try:
                message = decode(payload)
            except DecodeError as exc:
                self.rejections.reject(key, "unreadable", exc)
                return
            if type(message) is not Observation:
                self.rejections.reject(key, "wrong message type for the key", type(message).__name__)
                return
            if message.run_id != self.run_id or key != keys.obs(self.run_id, worker, message.role):
                self.rejections.reject(key, "names another run or role than its key")
                return
            if where := non_finite_field(message):
                self.rejections.reject(key, "a number that is not finite", where)
                return
            try:
                keys.check_chunk(message.episode_id, what="episode id")
            except ValueError as exc:
                self.rejections.reject(key, "an id that is not a name", exc)
                return
            if not self._current(worker, message) or self._asked_again(worker, message):
                return
            if self.inline:
                started = time.monotonic()
                self.send(worker, message, decide(self.policy, message), started)
                return
        with contextlib.suppress(RuntimeError):  # the loop is closed: the service is stopping
            self.loop.call_soon_threadsafe(self.on_loop, worker, message)

    def _asked_again(self, worker: str, obs: Observation) -> bool:
        """Whether ``obs`` asks again for the decision ``worker`` asked last (the world re-publishes an
        observation it had no answer to: the answer was lost, say while a router restarted). The
        policy is not asked twice: the answer already sent goes again, or, still being made, will go."""
        decision = (obs.episode_id, obs.attempt, obs.decision_index)
        if self.asked.get(worker) != decision:
            self.asked[worker] = decision
            self.answers.pop(worker, None)
            return False
        if (payload := self.answers.get(worker)) is not None:
            self.bus.publish(keys.act(self.run_id, worker, obs.role), payload)
        return True

    def send(self, worker: str, obs: Observation, action: Action, started: float) -> None:
        """Send the policy's ``action`` answering ``obs`` (:func:`publish_action`) and keep it for a
        repeated question."""
        payload = publish_action(self.bus, self.run_id, worker, obs, action, started)
        with contextlib.nullcontext() if self.inline else self.lock:  # inline: the caller holds it
            if self.asked.get(worker) == (obs.episode_id, obs.attempt, obs.decision_index):
                self.answers[worker] = payload

    def slot_over(self, worker: str) -> None:
        """The world serving ``worker``'s slot is gone (its liveliness token ended: it stopped, or
        died): the policy forgets the slot's episode. Not a result on the bus, which anyone could
        publish."""
        with self.lock:
            previous = self.slots.pop(worker, None)
            self.asked.pop(worker, None)
            self.answers.pop(worker, None)
            if previous is not None:
                self._release(previous[0])

    def _release(self, episode: str) -> None:
        """A slot no longer runs ``episode``: the policy forgets it unless another slot runs it."""
        if all(e != episode for e, _ in self.slots.values()):
            self._end(episode)

    def _end(self, episode: str) -> None:
        if self.inline:
            self.policy.end_episode(episode)
        else:  # on the loop, like every other call of a non-inline policy, in order with the observations
            with contextlib.suppress(RuntimeError):
                self.loop.call_soon_threadsafe(self.policy.end_episode, episode)


class _SlotSubscriptions:
    """Subscribes the dispatch to each world worker's observation key exactly, while the worker holds
    its slot's liveliness token (``keys.slot_live``; tokens alive when the service starts count, so a
    restarted service picks up the slots in flight), and then says so with its own token
    (``keys.slot_ready``), which the world waits for before an episode's first observation. zenoh
    delivers to an exact key expression faster than to ``slot/*/obs/<role>``: 10-20 us per decision
    in situ (docs/ARCHITECTURE.md §6, "Decision round trip"). The declarations follow the worker
    processes, never the episodes (docs/ARCHITECTURE.md §2). Token changes arrive on zenoh's
    threads; the (un)subscribing is done on the asyncio loop, outside zenoh's callbacks."""

    def __init__(self, bus: Bus, run_id: str, role: Role, agent_id: str, dispatch: _Dispatch,
                 loop: asyncio.AbstractEventLoop, *, reconnect_grace_s: float) -> None:
        self.bus, self.run_id, self.role, self.agent_id = bus, run_id, role, agent_id
        self.dispatch, self.loop, self.reconnect_grace_s = dispatch, loop, reconnect_grace_s
        self.handles: dict[str, tuple[Any, Any]] = {}  # worker -> (subscription, ready token)
        self.leaving: dict[str, asyncio.TimerHandle] = {}  # worker -> its drop, if its token stays away

    def put(self, sample: Sample) -> None:
        with contextlib.suppress(RuntimeError):  # the loop is closed: the service is stopping
            self.loop.call_soon_threadsafe(self.update, sample.key, sample.payload == b"+")

    def update(self, key: str, alive: bool) -> None:
        """A slot's token came (subscribe) or went: the slot is dropped, and its episode forgotten, only
        if it stays away ``reconnect_grace_s`` (a router restart takes every token away for seconds;
        zenoh declares this service's subscription and token again itself when it reconnects)."""
        worker = keys.slot_of(key)
        if alive and (leaving := self.leaving.pop(worker, None)) is not None:
            leaving.cancel()
        if alive and worker not in self.handles:
            obs_key = keys.obs(self.run_id, worker, self.role)
            try:
                subscription = self.bus.subscribe_payloads(
                    obs_key, functools.partial(self.dispatch.take, worker=worker, key=obs_key))
                ready = self.bus.declare_token(keys.slot_ready(self.run_id, worker, self.role, self.agent_id))
            except Exception:  # e.g. the session is closing; the next token change tries again
                log.exception("could not subscribe to %s", obs_key)
                return
            self.handles[worker] = (subscription, ready)
        elif not alive and worker in self.handles and worker not in self.leaving:
            self.leaving[worker] = self.loop.call_later(self.reconnect_grace_s, self._drop, worker)

    def _drop(self, worker: str) -> None:
        self.leaving.pop(worker, None)
        if worker in self.handles:
            subscription, ready = self.handles.pop(worker)
            self.bus.undeclare_token(ready)
            self.bus.unsubscribe(subscription)
            self.bus.forget(keys.slot_prefix(self.run_id, worker))
            self.dispatch.slot_over(worker)

    def close(self) -> None:
        for leaving in self.leaving.values():
            leaving.cancel()
        for worker in list(self.handles):
            self._drop(worker)


def decide(policy: Policy, obs: Observation) -> Action:
    """``policy.act``; a policy error is logged and answered with a legal WAIT, an endpoint outage
    with :func:`outage_answer`."""
    try:
        return policy.act(obs)
    except EndpointOutage as exc:
        return outage_answer(obs, exc)
    except Exception:
        return _policy_failed(obs)


async def answer(policy: Policy, obs: Observation) -> Action:
    """The policy's ``act_async`` (by default ``act`` in a worker thread of the loop's default
    executor, which :func:`serve_async` sizes); a policy error is logged and answered with a WAIT."""
    try:
        return await policy.act_async(obs)
    except FatalPolicyError:  # the service stops (serve_async)
        raise
    except EndpointOutage as exc:
        return outage_answer(obs, exc)
    except Exception:
        return _policy_failed(obs)


def outage_answer(obs: Observation, outage: EndpointOutage) -> Action:
    """The answer to ``obs`` when the policy's endpoint gave no answer: ``Action.outage`` holds the line,
    and the world applies nothing (it pauses the episode and gives it back: world/sim/worker.py)."""
    log.warning("%s %s #%d: no decision, the model endpoint gave no answer: %s", obs.episode_id, obs.role,
                obs.decision_index, outage)
    return action_for(obs, "WAIT", outage=str(outage)[:500] or type(outage).__name__)


def _policy_failed(obs: Observation) -> Action:
    """Called in an ``except`` block: log the error, answer a legal WAIT."""
    log.exception("policy failed on %s #%d; answering WAIT", obs.episode_id, obs.decision_index)
    return action_for(obs, "WAIT", rationale="policy error (see agent log)")


def publish_action(bus: Bus, run_id: str, worker: str, obs: Observation, action: Action, started: float) -> bytes:
    """Stamp the policy's wall-clock latency (realtime mode charges it in simulated time), check the
    answer as the world will read it (structs are built without checks) and send it; one the world
    would refuse is logged and replaced by a legal WAIT. Returns the payload sent."""
    latency = round(time.monotonic() - started, 4)
    try:
        payload = _stamped(action, latency)
    except Exception:
        action = _policy_failed(obs)
        payload = _stamped(action, latency)
    bus.publish(keys.act(run_id, worker, action.role), payload)
    return payload


def _stamped(action: Action, latency_s: float) -> bytes:
    """``action`` with its latency, encoded and read back as an ``Action`` (in C), as the world
    reads it: raises when the world would refuse it (a wrong type, an unknown action name)."""
    action.agent_wall_latency_s = latency_s
    payload = encode(action)
    decode_as(payload, Action)
    return payload


async def serve_async(bus: Bus, policy: Policy, run_id: str, stop: StopFlag, *, concurrency: int,
                      reconnect_grace_s: float = DEFAULTS.run.reconnect_grace_s, worker: str = "*") -> int:
    """Answer ``policy.role``'s decisions of run ``run_id`` until ``stop``: of every world worker's slot, or
    only of ``worker``'s (``agos ros2 bridge --worker``). Returns the exit status."""
    loop = asyncio.get_running_loop()
    limit = asyncio.Semaphore(concurrency)
    executor = ThreadPoolExecutor(max_workers=concurrency, thread_name_prefix="policy")
    loop.set_default_executor(executor)  # where the contract's default act_async runs act
    tasks: set[asyncio.Task] = set()
    fatal: list[FatalPolicyError] = []

    async def handle(worker: str, obs: Observation) -> None:
        async with limit:
            started = time.monotonic()  # the policy's latency, not the wait for a free slot
            try:
                action = await answer(policy, obs)
            except FatalPolicyError as exc:  # no answer, no further decisions: the run must not go on
                if not fatal:
                    log.error("%s", exc)
                fatal.append(exc)
                stop.set()
                return
        dispatch.send(worker, obs, action, started)

    def on_loop(worker: str, message: Observation) -> None:
        """Start answering an observation of ``worker``'s slot."""
        task = loop.create_task(handle(worker, message))
        tasks.add(task)
        task.add_done_callback(tasks.discard)

    agent_id = unique_id(policy.role)
    dispatch = _Dispatch(bus, policy, run_id, loop, on_loop)
    slots = _SlotSubscriptions(bus, run_id, policy.role, agent_id, dispatch, loop, reconnect_grace_s=reconnect_grace_s)
    bus.watch_liveliness(keys.slot_live(run_id, worker), slots)
    bus.declare_token(keys.live(run_id, "agent", agent_id))
    announce("agent", agent_id, run_id)
    log.info("%s agent (%s) serving run %s, up to %d decisions at once%s", policy.role, policy.name, run_id,
             concurrency, " (answered inline)" if dispatch.inline else "")
    try:
        while not stop.is_set():
            await asyncio.sleep(0.25)  # samples arrive through the dispatch; this only watches the stop flag
    finally:
        slots.close()
        dispatch.rejections.log_summary()
        for task in tasks:
            task.cancel()
        executor.shutdown(wait=False, cancel_futures=True)
    return fatal[0].exit_code if fatal else 0


def main(cfg: AgosConfig, *, role: Role, policy_name: str | None = None, concurrency: int,
         dataset_out: Path | None = None) -> int:
    setup_logging(f"agent-{role}")
    stop = install_stop_handlers()
    name = policy_name or (cfg.run.policy_uav if role == "uav" else cfg.run.policy_ugv)
    policy = make_policy(name, role, vlm=cfg.vlm, dataset_out=dataset_out)
    try:
        asyncio.run(policy.preflight())
    except Exception as exc:  # the policy's own words on what to fix
        log.error("%s preflight failed: %s", "VLM" if needs_vlm(name) else f"policy {name!r}", exc)
        return 3
    if needs_vlm(name) and cfg.vlm.replaying:
        log.info("VLM calls of %s replayed from %s (no endpoint)", cfg.vlm.model, cfg.vlm.cache_dir)
    elif needs_vlm(name):
        log.info("VLM endpoint %s serves %s (checked: model listed, %s-sized requests accepted)",
                 cfg.vlm.base_url, cfg.vlm.model, role)
    with ZenohBus.from_settings(cfg.zenoh) as bus:
        return asyncio.run(serve_async(bus, policy, cfg.run.run_id, stop, concurrency=concurrency,
                                       reconnect_grace_s=cfg.run.reconnect_grace_s))
