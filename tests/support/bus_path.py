"""The process path of an episode without processes: a world worker and two agent services in this
process, over an in-memory bus (runtime/bus.py's MemoryBus), as ``agos eval`` wires them over zenoh.

What crosses the bus is what crosses zenoh (every message encoded and decoded, the job grant's
configuration read back, the agents' answers checked as the world checks them); only the transport
and the orchestrator differ.
"""

from __future__ import annotations

import asyncio
import threading
from types import TracebackType

from agos.agents.agent_service import serve_async
from agos.agents.registry import make_policy
from agos.runtime import keys
from agos.runtime.bus import MemoryBus
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.health import announced
from agos.runtime.process import StopFlag
from agos.runtime.schemas import EpisodeRecord, EpisodeSpec, JobGrant, Role
from agos.runtime.settings import AgosConfig
from agos.world import expert
from agos.world.sim.scene import Scene
from agos.world.sim.worker import WorldWorker
from agos.world.towns.asset import Town

from support.waiting import wait_until

WORKER = "w-bus"


class BusPath:
    """:meth:`play` serves one episode on a fresh MemoryBus: a world worker and agent services of the
    given policies, and returns the record the worker submitted (there is no evaluator). The workers
    share their scenes, closed on exit (a context manager). Agent services write their health file
    where ``AGOS_HEALTH_DIR`` says: point it at a temporary folder around this object."""

    def __init__(self) -> None:
        self.cfg = AgosConfig()
        self.scenes: dict[tuple[str, str, str], tuple[Town, Scene]] = {}
        expert.install()  # as `agos world` does

    def play(self, spec: EpisodeSpec, config: EpisodeConfig, policies: dict[Role, str]) -> EpisodeRecord:
        bus, stop, submitted = MemoryBus(), StopFlag(), []
        worker = WorldWorker(self.cfg, bus, StopFlag(), WORKER)
        worker._scenes = self.scenes  # the world worker's scene cache, shared by this object's workers
        worker.submit = lambda record: submitted.append(record) is None  # type: ignore[method-assign]
        threads: list[threading.Thread] = []
        try:
            for role in ("uav", "ugv"):  # one after the other: each writes the one health file of its kind
                threads.append(threading.Thread(target=asyncio.run, daemon=True, args=(serve_async(
                    bus, make_policy(policies[role], role), self.cfg.run.run_id, stop, concurrency=1),)))
                threads[-1].start()
                serving = len(threads)
                assert wait_until(lambda n=serving: _announced_agents(bus, self.cfg.run.run_id) == n), \
                    f"the {role} agent never served"
            worker.run_episode(spec, JobGrant(worker_id=WORKER, episode=spec, config=config.model_dump(mode="json")))
            assert len(submitted) == 1, "the worker submitted no record"
            return submitted[0]
        finally:
            stop.set()
            for thread in threads:
                thread.join(10)
            bus.close()

    def __enter__(self) -> BusPath:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        for _, scene in self.scenes.values():
            scene.close()


def _announced_agents(bus: MemoryBus, run_id: str) -> int:
    """Agent services serving the run, once the last one's health file is written (it names its token)."""
    alive = bus.alive_tokens(keys.live(run_id, "agent", "*"))
    said = announced("agent")
    return len(alive) if said is not None and any(t.endswith(f"/{said['id']}") for t in alive) else 0
