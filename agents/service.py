"""The agent service process: one role, one policy, many episodes at once.

    agos agent --role uav --policy heuristic --connect tcp/HOST:PORT --run RUN [--concurrency 32]

Every observation on ``agos/<run>/ep/*/obs/<role>`` is answered on the matching
``.../act/<role>`` key. Observations are handled concurrently on an asyncio loop, at most
``concurrency`` at a time: policies with an ``act_async`` coroutine (remote models, the
fixed-latency stand-in) overlap their waiting; plain ``act`` policies run in worker threads.
A policy that raises is logged and answered with a legal WAIT, so an agent bug costs a
decision, never the episode. A restarted service simply answers what the world re-requests.
"""

from __future__ import annotations

import asyncio
import logging
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

from agos.agents.policy import Policy, action_for, make_policy
from agos.runtime import keys
from agos.runtime.bus import Sample, ZenohBus, zenoh_config
from agos.runtime.codec import DecodeError, Decoder
from agos.runtime.process import StopFlag, install_stop_handlers, setup_logging
from agos.runtime.schemas import Action, EpisodeRecord, Observation, Role
from agos.runtime.settings import AgosConfig

log = logging.getLogger("agos.agent")


class _LoopInbox:
    """Hands zenoh samples (from its callback thread) to a function on the asyncio loop, doing
    nothing else in the callback."""

    def __init__(self, loop: asyncio.AbstractEventLoop, handle: Callable[[Sample], None]) -> None:
        self.loop, self.handle = loop, handle

    def put(self, sample: Sample) -> None:
        self.loop.call_soon_threadsafe(self.handle, sample)


async def answer(policy: Policy, obs: Observation, executor: ThreadPoolExecutor) -> Action:
    started = time.monotonic()
    try:
        if hasattr(policy, "act_async"):
            action = await policy.act_async(obs)
        else:
            action = await asyncio.get_running_loop().run_in_executor(executor, policy.act, obs)
    except Exception:
        log.exception("policy failed on %s #%d; answering WAIT", obs.episode_id, obs.decision_index)
        action = action_for(obs, "WAIT", rationale="policy error (see agent log)")
    action.agent_wall_latency_s = round(time.monotonic() - started, 4)
    return action


async def serve_async(bus: ZenohBus, policy: Policy, run_id: str, stop: StopFlag, *, concurrency: int) -> int:
    loop = asyncio.get_running_loop()
    # Observations repeat their reference views and searchable area every decision: validated once.
    decoder = Decoder()
    limit = asyncio.Semaphore(concurrency)
    executor = ThreadPoolExecutor(max_workers=concurrency, thread_name_prefix="policy")
    tasks: set[asyncio.Task] = set()

    async def handle(obs: Observation) -> None:
        async with limit:
            action = await answer(policy, obs, executor)
        bus.publish(keys.act(run_id, obs.episode_id, policy.role), action)

    def on_sample(sample: Sample) -> None:
        """Runs on the loop for every sample: decode and start answering (no queue in between)."""
        try:
            message = decoder.decode(sample.payload)
        except DecodeError as exc:
            log.warning("ignoring undecodable payload on %s: %s", sample.key, exc)
            return
        if isinstance(message, EpisodeRecord):
            policy.end_episode(message.episode_id)
            decoder.forget(message.episode_id)
            bus.forget(keys.episode_prefix(run_id, message.episode_id))
        elif isinstance(message, Observation):
            task = loop.create_task(handle(message))
            tasks.add(task)
            task.add_done_callback(tasks.discard)

    inbox = _LoopInbox(loop, on_sample)
    bus.subscribe(keys.obs(run_id, "*", policy.role), inbox)  # type: ignore[arg-type]
    bus.subscribe(keys.result(run_id, "*"), inbox)  # type: ignore[arg-type]
    bus.declare_token(keys.live(run_id, "agent", f"{policy.role}-{os.getpid()}"))
    log.info("%s agent (%s) serving run %s, up to %d decisions at once", policy.role, policy.name, run_id, concurrency)
    try:
        while not stop.is_set():
            await asyncio.sleep(0.25)  # samples arrive through on_sample; this only watches the stop flag
    finally:
        for task in tasks:
            task.cancel()
        executor.shutdown(wait=False, cancel_futures=True)
    return 0


def main(cfg: AgosConfig, *, role: Role, policy_name: str | None = None, concurrency: int = 32) -> int:
    setup_logging(f"agent-{role}")
    stop = install_stop_handlers()
    name = policy_name or (cfg.run.policy_uav if role == "uav" else cfg.run.policy_ugv)
    policy = make_policy(name, role, vlm=cfg.vlm)
    if hasattr(policy, "preflight"):
        from agos.agents.vlm.client import VlmError

        try:
            asyncio.run(policy.preflight())
        except VlmError as exc:
            log.error("VLM preflight failed: %s", exc)
            return 3
        log.info("VLM endpoint %s serves %s (checked: model listed, %s-sized requests accepted)",
                 cfg.vlm.base_url, cfg.vlm.model, role)
    bus = ZenohBus(zenoh_config(connect=[cfg.zenoh.connect], multicast_scouting=cfg.zenoh.multicast_scouting,
                                connect_timeout_s=cfg.zenoh.connect_timeout_s))
    try:
        return asyncio.run(serve_async(bus, policy, cfg.run.run_id, stop, concurrency=concurrency))
    finally:
        bus.close()
