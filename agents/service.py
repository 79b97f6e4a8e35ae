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
from concurrent.futures import ThreadPoolExecutor

from agos.agents.policy import Policy, action_for, make_policy
from agos.runtime import keys
from agos.runtime.bus import Sample, ZenohBus, zenoh_config
from agos.runtime.codec import DecodeError, decode
from agos.runtime.process import StopFlag, install_stop_handlers, setup_logging
from agos.runtime.schemas import Action, EpisodeRecord, Observation, Role
from agos.runtime.settings import AgosConfig

log = logging.getLogger("agos.agent")


class _LoopInbox:
    """Hands zenoh samples (from its callback thread) to an asyncio queue, doing nothing else."""

    def __init__(self, loop: asyncio.AbstractEventLoop, queue: asyncio.Queue) -> None:
        self.loop, self.queue = loop, queue

    def put(self, sample: Sample) -> None:
        self.loop.call_soon_threadsafe(self.queue.put_nowait, sample)


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
    queue: asyncio.Queue[Sample | None] = asyncio.Queue()
    inbox = _LoopInbox(loop, queue)
    bus.subscribe(keys.obs(run_id, "*", policy.role), inbox)  # type: ignore[arg-type]
    bus.subscribe(keys.result(run_id, "*"), inbox)  # type: ignore[arg-type]
    bus.declare_token(keys.live(run_id, "agent", f"{policy.role}-{os.getpid()}"))
    limit = asyncio.Semaphore(concurrency)
    executor = ThreadPoolExecutor(max_workers=concurrency, thread_name_prefix="policy")
    tasks: set[asyncio.Task] = set()

    async def handle(obs: Observation) -> None:
        async with limit:
            action = await answer(policy, obs, executor)
        bus.publish(keys.act(run_id, obs.episode_id, policy.role), action)

    async def watch_stop() -> None:
        while not stop.is_set():
            await asyncio.sleep(0.25)
        queue.put_nowait(None)  # wakes the loop below; no per-message timers on the hot path

    watcher = asyncio.create_task(watch_stop())
    log.info("%s agent (%s) serving run %s, up to %d decisions at once", policy.role, policy.name, run_id, concurrency)
    try:
        while True:
            sample = await queue.get()
            if sample is None:
                break
            try:
                message = decode(sample.payload)
            except DecodeError as exc:
                log.warning("ignoring undecodable payload on %s: %s", sample.key, exc)
                continue
            if isinstance(message, EpisodeRecord):
                policy.end_episode(message.episode_id)
            elif isinstance(message, Observation):
                task = asyncio.create_task(handle(message))
                tasks.add(task)
                task.add_done_callback(tasks.discard)
    finally:
        watcher.cancel()
        for task in tasks:
            task.cancel()
        executor.shutdown(wait=False, cancel_futures=True)
    return 0


def main(cfg: AgosConfig, *, role: Role, policy_name: str | None = None, concurrency: int = 32) -> int:
    setup_logging(f"agent-{role}")
    stop = install_stop_handlers()
    name = policy_name or (cfg.run.policy_uav if role == "uav" else cfg.run.policy_ugv)
    policy = make_policy(name, role)
    bus = ZenohBus(zenoh_config(connect=[cfg.zenoh.connect], multicast_scouting=cfg.zenoh.multicast_scouting,
                                connect_timeout_s=cfg.zenoh.connect_timeout_s))
    try:
        return asyncio.run(serve_async(bus, policy, cfg.run.run_id, stop, concurrency=concurrency))
    finally:
        bus.close()
