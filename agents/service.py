"""The agent service process: one role, one policy, many episodes at once.

    agos agent --role uav --policy heuristic --connect tcp/HOST:PORT --run RUN [--concurrency 32]

Every observation on ``agos/<run>/ep/<ep>/obs/<role>`` is answered on the matching
``.../act/<role>`` key, for each episode a world announces with its liveliness token
(``agos/<run>/ep/<ep>/live/<worker>``). Observations are handled concurrently on an asyncio loop, at most
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
from agos.runtime.settings import AgosConfig

log = logging.getLogger("agos.agent")


class _Dispatch:
    """Takes each payload on the zenoh thread that received it: decodes it there (tens of
    microseconds, bounded) and then either answers at once, for ``inline`` policies (microseconds,
    no I/O), or hands the decoded message to the asyncio loop. Answering inline saves a thread
    hand-over per decision (docs/ARCHITECTURE.md, "Decision round trip").

    The observation and result subscriptions may call in from different threads: one lock
    serialises decoding and, for inline policies, every policy call."""

    def __init__(self, bus: Bus, policy: Policy, run_id: str, loop: asyncio.AbstractEventLoop,
                 on_loop: Callable[[Observation], None]) -> None:
        self.bus, self.policy, self.run_id, self.loop, self.on_loop = bus, policy, run_id, loop, on_loop
        self.inline = policy.inline
        self.lock = threading.Lock()
        self.attempts: dict[str, int] = {}  # episode -> the latest attempt observed
        self.rejections = Rejections(log)

    def _current(self, obs: Observation) -> bool:
        """Whether ``obs`` belongs to the episode's latest attempt. A newer attempt (the episode was
        re-leased) starts afresh: the policy forgets what it kept of the earlier one, before this
        observation is answered. A late observation of an older attempt is ignored."""
        latest = self.attempts.get(obs.episode_id, obs.attempt)
        if obs.attempt < latest:
            log.info("ignoring %s decision %d of attempt %d: attempt %d is running", obs.episode_id,
                     obs.decision_index, obs.attempt, latest)
            return False
        self.attempts[obs.episode_id] = obs.attempt
        if obs.attempt > latest:
            log.info("%s re-leased (attempt %d): its earlier attempt is forgotten", obs.episode_id, obs.attempt)
            if self.inline:
                self.policy.end_episode(obs.episode_id)
            else:  # on the loop, like every other call of a non-inline policy, before this observation
                self.loop.call_soon_threadsafe(self.policy.end_episode, obs.episode_id)
        return True

    def take(self, payload: bytes, key: str) -> None:
        """One payload received on the observation key ``key``: answered when it is an observation
        of this run for that key's episode and role, with finite numbers, of the episode's latest
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
            if message.run_id != self.run_id or key != keys.obs(self.run_id, message.episode_id, message.role):
                self.rejections.reject(key, "names another run, episode or role than its key")
                return
            if where := non_finite_field(message):
                self.rejections.reject(key, "a number that is not finite", where)
                return
            if not self._current(message):
                return
            if self.inline:
                started = time.monotonic()
                publish_action(self.bus, self.run_id, message, decide(self.policy, message), started)
                return
        with contextlib.suppress(RuntimeError):  # the loop is closed: the service is stopping
            self.loop.call_soon_threadsafe(self.on_loop, message)

    def episode_over(self, episode_id: str) -> None:
        """No world runs the episode any more (its liveliness token is gone: finished, or the world
        died): the policy forgets it. Not a result on the bus, which anyone could publish."""
        with self.lock:
            self.attempts.pop(episode_id, None)
            if self.inline:
                end_episode(self.bus, self.policy, self.run_id, episode_id)
                return
        with contextlib.suppress(RuntimeError):
            self.loop.call_soon_threadsafe(end_episode, self.bus, self.policy, self.run_id, episode_id)


class _EpisodeSubscriptions:
    """Subscribes the dispatch to each running episode's observation key exactly, while a world
    holds that episode's liveliness token (``keys.episode_live``; tokens alive when the service
    starts count, so a restarted service picks up the episodes in flight), and then says so with
    its own token (``keys.episode_ready``), which the world waits for before the first observation.
    zenoh delivers to an exact key expression faster than to ``ep/*/obs/<role>``: 10-20 us per
    decision in situ (docs/ARCHITECTURE.md §6, "Decision round trip"). Token changes arrive on
    zenoh's threads; the (un)subscribing is done on the asyncio loop, outside zenoh's callbacks."""

    def __init__(self, bus: Bus, run_id: str, role: Role, agent_id: str, dispatch: _Dispatch,
                 loop: asyncio.AbstractEventLoop) -> None:
        self.bus, self.run_id, self.role, self.agent_id = bus, run_id, role, agent_id
        self.dispatch, self.loop = dispatch, loop
        self.holders: dict[str, set[str]] = {}  # episode -> the workers whose token for it is alive
        self.handles: dict[str, tuple[Any, Any]] = {}  # episode -> (subscription, ready token)

    def put(self, sample: Sample) -> None:
        with contextlib.suppress(RuntimeError):  # the loop is closed: the service is stopping
            self.loop.call_soon_threadsafe(self.update, sample.key, sample.payload == b"+")

    def update(self, key: str, alive: bool) -> None:
        episode, worker = keys.episode_of(key), key.rsplit("/", 1)[-1]
        holders = self.holders.setdefault(episode, set())
        if alive:
            holders.add(worker)
        else:
            holders.discard(worker)
        if holders and episode not in self.handles:
            obs_key = keys.obs(self.run_id, episode, self.role)
            try:
                subscription = self.bus.subscribe_payloads(obs_key, functools.partial(self.dispatch.take, key=obs_key))
                ready = self.bus.declare_token(keys.episode_ready(self.run_id, episode, self.role, self.agent_id))
            except Exception:  # e.g. the session is closing; the next token change tries again
                log.exception("could not subscribe to %s", obs_key)
                holders.discard(worker)
                return
            self.handles[episode] = (subscription, ready)
        elif not holders:
            del self.holders[episode]
            self._drop(episode)

    def _drop(self, episode: str) -> None:
        if episode in self.handles:
            subscription, ready = self.handles.pop(episode)
            self.bus.undeclare_token(ready)
            self.bus.unsubscribe(subscription)
            self.dispatch.episode_over(episode)

    def close(self) -> None:
        for episode in list(self.handles):
            self._drop(episode)


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


def publish_action(bus: Bus, run_id: str, obs: Observation, action: Action, started: float) -> None:
    """Stamp the policy's wall-clock latency (realtime mode charges it in simulated time), check the
    answer as the world will read it (structs are built without checks) and send it; one the world
    would refuse is logged and replaced by a legal WAIT."""
    latency = round(time.monotonic() - started, 4)
    try:
        payload = _stamped(action, latency)
    except Exception:
        action = _policy_failed(obs)
        payload = _stamped(action, latency)
    bus.publish(keys.act(run_id, action.episode_id, action.role), payload)


def _stamped(action: Action, latency_s: float) -> bytes:
    """``action`` with its latency, encoded and read back as an ``Action`` (in C), as the world
    reads it: raises when the world would refuse it (a wrong type, an unknown action name)."""
    action.agent_wall_latency_s = latency_s
    payload = encode(action)
    decode_as(payload, Action)
    return payload


def end_episode(bus: Bus, policy: Policy, run_id: str, episode_id: str) -> None:
    policy.end_episode(episode_id)
    bus.forget(keys.episode_prefix(run_id, episode_id))


async def serve_async(bus: Bus, policy: Policy, run_id: str, stop: StopFlag, *, concurrency: int) -> int:
    loop = asyncio.get_running_loop()
    limit = asyncio.Semaphore(concurrency)
    executor = ThreadPoolExecutor(max_workers=concurrency, thread_name_prefix="policy")
    loop.set_default_executor(executor)  # where the contract's default act_async runs act
    tasks: set[asyncio.Task] = set()
    fatal: list[FatalPolicyError] = []

    async def handle(obs: Observation) -> None:
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
        publish_action(bus, run_id, obs, action, started)

    def on_loop(message: Observation) -> None:
        """Start answering an observation."""
        task = loop.create_task(handle(message))
        tasks.add(task)
        task.add_done_callback(tasks.discard)

    agent_id = unique_id(policy.role)
    dispatch = _Dispatch(bus, policy, run_id, loop, on_loop)
    episodes = _EpisodeSubscriptions(bus, run_id, policy.role, agent_id, dispatch, loop)
    bus.watch_liveliness(keys.episode_live(run_id, "*", "*"), episodes)
    bus.declare_token(keys.live(run_id, "agent", agent_id))
    announce("agent", agent_id, run_id)
    log.info("%s agent (%s) serving run %s, up to %d decisions at once%s", policy.role, policy.name, run_id,
             concurrency, " (answered inline)" if dispatch.inline else "")
    try:
        while not stop.is_set():
            await asyncio.sleep(0.25)  # samples arrive through the dispatch; this only watches the stop flag
    finally:
        episodes.close()
        dispatch.rejections.log_summary()
        for task in tasks:
            task.cancel()
        executor.shutdown(wait=False, cancel_futures=True)
    return fatal[0].exit_code if fatal else 0


def main(cfg: AgosConfig, *, role: Role, policy_name: str | None = None, concurrency: int = 32,
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
        return asyncio.run(serve_async(bus, policy, cfg.run.run_id, stop, concurrency=concurrency))
