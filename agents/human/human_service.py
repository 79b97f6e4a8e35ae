"""``agos human``: an agent service whose policy is a person, and the read-only spectator.

    agos human --role uav|ugv|both --connect tcp/HOST:PORT --run RUN [--port 8765] [--host 127.0.0.1]
    agos human --spectate --connect tcp/HOST:PORT [--run RUN] [--port 8766]

Playing, it is an agent service like ``agos agent`` for each role it plays (agents/agent_service.py:
the same episode subscriptions, ``ready`` tokens, attempt handling and answer checks), but each
observation goes on a :class:`~agos.agents.human.board.DecisionBoard` and the answer is what the
person chooses on the page. The world re-sends an unanswered observation every 5 s: a repeated
observation joins the decision already on the board (or gets the answer already given), so the
person decides once. When the world gives up on a decision (its ``decision_timeout_s``) it
applies WAIT and asks the next one; the board then closes the old one. Two people play the two
roles with one ``agos human --role uav`` and one ``--role ugv``, on any hosts that reach the
router; one person plays both with ``--role both``.

Spectating, it observes ``agos/<run>/viz/**`` only (runtime/observer.py) and serves the same
page read-only.
"""

from __future__ import annotations

import asyncio
import logging
import sys
import time
from pathlib import Path
from typing import Any

from agos.agents.agent_service import _Dispatch, _SlotSubscriptions
from agos.agents.contract import Policy
from agos.agents.human.board import DecisionBoard, PageBoard
from agos.agents.human.server import ConsoleServer
from agos.agents.human.spectator import SpectatorBoard
from agos.runtime import keys
from agos.runtime.bus import Bus, ZenohBus
from agos.runtime.codec import encode
from agos.runtime.health import announce, unique_id
from agos.runtime.process import StopFlag, install_stop_handlers, setup_logging
from agos.runtime.schemas import Action, Observation, Role
from agos.runtime.settings import AgosConfig

log = logging.getLogger("agos.human")


class HumanPolicy(Policy):
    """The policy the service's dispatch holds for one role: a person, through the board. Its
    decisions are taken in :func:`serve_async` (never through :meth:`act`)."""

    name = "human"
    inline = False

    def __init__(self, role: Role, board: DecisionBoard) -> None:
        self.role, self.board = role, board

    def act(self, obs: Observation) -> Action:
        raise RuntimeError("a person answers through the console page, not act()")

    def end_episode(self, episode_id: str) -> None:
        self.board.forget(episode_id, self.role)


async def serve_async(bus: Bus, board: DecisionBoard, run_id: str, stop: StopFlag, *,
                      reconnect_grace_s: float) -> int:
    """Serve every role of ``board`` on the bus until ``stop``."""
    loop = asyncio.get_running_loop()
    tasks: set[asyncio.Task[None]] = set()
    dispatches: dict[str, _Dispatch] = {}

    async def handle(worker: str, obs: Observation, future: Any, started: float) -> None:
        try:
            action = await asyncio.wrap_future(future)
        except asyncio.CancelledError:  # the world moved on, or the episode ended
            return
        dispatches[obs.role].send(worker, obs, action, started)  # stamps the person's latency, checks, sends

    def on_loop(worker: str, obs: Observation) -> None:
        asked = board.ask(obs)
        if asked.kind == "new":
            task = loop.create_task(handle(worker, obs, asked.future, time.monotonic()))
            tasks.add(task)
            task.add_done_callback(tasks.discard)
        elif asked.kind == "decided" and asked.action is not None:  # the world asks again: send it again
            bus.publish(keys.act(run_id, worker, obs.role), encode(asked.action))

    subscriptions = []
    for role in board.roles:
        agent_id = unique_id(role)
        dispatch = dispatches[role] = _Dispatch(bus, HumanPolicy(role, board), run_id, loop, on_loop)
        episodes = _SlotSubscriptions(bus, run_id, role, agent_id, dispatch, loop, reconnect_grace_s=reconnect_grace_s)
        bus.watch_liveliness(keys.slot_live(run_id, "*"), episodes)
        bus.declare_token(keys.live(run_id, "agent", agent_id))
        announce("agent", agent_id, run_id)
        subscriptions.append((episodes, dispatch))
    log.info("human console serving the %s of run %s", " and ".join(r.upper() for r in board.roles), run_id)
    try:
        while not stop.is_set():
            await asyncio.sleep(0.25)
    finally:
        for episodes, dispatch in subscriptions:
            episodes.close()
            dispatch.rejections.log_summary()
        for task in tasks:
            task.cancel()
    return 0


def _serve_page(source: PageBoard, host: str, port: int, what: str) -> ConsoleServer | None:
    try:
        server = ConsoleServer(source, host, port).start()
    except OSError as exc:
        print(f"agos human: cannot serve the page on {host}:{port}: {exc.strerror or exc}", file=sys.stderr)
        return None
    # On stdout, whole, for the person (and for `agos eval`, which shows it): where to point a browser.
    print(f"human console: {server.url(host)} ({what})", flush=True)
    return server


def main(cfg: AgosConfig, *, roles: tuple[Role, ...], host: str = "127.0.0.1", port: int = 8765,
         player: str = "person", trace_file: Path | None = None) -> int:
    """Play ``roles`` of the configured run through a page on ``host:port`` until stopped: 130 after
    Ctrl-C (also while it still connects), 0 after SIGTERM (its launcher ending the run)."""
    setup_logging("human")
    stop = install_stop_handlers()
    board = DecisionBoard(roles, player=player, trace_file=trace_file)
    what = f"{' and '.join(r.upper() for r in roles)} of run {cfg.run.run_id}"
    server = _serve_page(board, host, port, what)
    if server is None:
        return 2
    try:
        with ZenohBus.from_settings(cfg.zenoh) as bus:
            asyncio.run(serve_async(bus, board, cfg.run.run_id, stop, reconnect_grace_s=cfg.run.reconnect_grace_s))
    finally:
        server.close()
    return stop.exit_code()


def spectate(cfg: AgosConfig, *, run_id: str | None, host: str = "127.0.0.1", port: int = 8766) -> int:
    """Serve the read-only page of the visualisation stream of ``run_id`` (every run when None) until
    stopped: 130 after Ctrl-C, 0 after SIGTERM."""
    from agos.runtime.observer import Observer

    setup_logging("spectator")
    stop = install_stop_handlers()
    board = SpectatorBoard(run_id)
    server = _serve_page(board, host, port, f"spectating {'run ' + run_id if run_id else 'every run'}, read-only")
    if server is None:
        return 2
    try:
        # The observer's own key expressions (the light visualisation stream of every run); the board
        # keeps only ``run_id``'s samples.
        observer = Observer(cfg.zenoh, board.take)
        try:
            while not stop.wait(0.25):
                pass
        finally:
            observer.close()
    finally:
        server.close()
    return stop.exit_code()
