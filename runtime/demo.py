"""``agos demo``: the whole system on one machine, as separate OS processes.

Starts a zenoh router, the evaluator, the UAV and UGV agent services and world worker(s),
leases the episodes to the workers, shows progress, then prints the results table and the
path of the results file. Ctrl-C stops everything and still prints what was stored.
"""

from __future__ import annotations

import logging
import time
from datetime import UTC, datetime
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from agos.evaluator.metrics import by_difficulty
from agos.evaluator.store import ResultStore, results_path
from agos.evaluator.table import results_table
from agos.runtime.bus import ZenohBus
from agos.runtime.launcher import Launcher, free_port, wait_listening
from agos.runtime.orchestrator import Orchestrator
from agos.runtime.process import install_stop_handlers
from agos.runtime.schemas import EpisodeSpec
from agos.runtime.settings import AgosConfig

log = logging.getLogger("agos.demo")


def load_episodes(cfg: AgosConfig) -> list[EpisodeSpec]:
    from agos.world.episodes import read_episodes

    if cfg.run.episodes_file is not None:
        return read_episodes(cfg.run.episodes_file)
    from agos.world.asset import open_town
    from agos.world.episodes import generate_episodes
    from agos.world.scene import Scene

    town = open_town(cfg.run.town)
    scene = Scene(town.layout)  # episodes are checked solvable by rendering
    try:
        return generate_episodes(town, scene, per_difficulty=cfg.run.per_difficulty, seed=cfg.run.episode_seed)
    finally:
        scene.close()


def _launch_all(cfg: AgosConfig, launcher: Launcher, endpoint: str, port: int, run_id: str,
                config_path: Path | None, console: Console) -> bool:
    common = ["--connect", endpoint, "--run", run_id] + (["--config", str(config_path)] if config_path else [])
    launcher.start("router", ["router", "--listen", endpoint])
    if not wait_listening("127.0.0.1", port, 15.0):
        console.print(f"[red]router did not listen on {endpoint}; see {launcher.log_dir / 'router.log'}")
        return False
    console.print(f"zenoh endpoint: {endpoint}", highlight=False)
    launcher.start("evaluator", ["evaluator", *common, "--runs-dir", str(cfg.run.runs_dir)])
    launcher.start("agent-uav", ["agent", "--role", "uav", "--policy", cfg.run.policy_uav, *common])
    launcher.start("agent-ugv", ["agent", "--role", "ugv", "--policy", cfg.run.policy_ugv, *common])
    for k in range(cfg.run.workers):
        launcher.start(f"world-{k}", ["world", *common, "--worker-id", f"w{k}"])
    return True


def main(cfg: AgosConfig, *, config_path: Path | None = None, port: int | None = None, attach: bool = False,
         console: Console | None = None) -> int:
    """Launch everything locally; with ``attach``, only orchestrate the run on ``cfg.zenoh.connect``
    for processes started by hand (router, evaluator, agents, workers with the same ``--run``)."""
    console = console or Console()
    stop = install_stop_handlers()
    episodes = load_episodes(cfg)
    run_id = cfg.run.run_id if attach else f"{cfg.run.run_id}-{datetime.now(UTC).strftime('%Y%m%d-%H%M%S')}"
    run_dir = cfg.run.runs_dir / run_id
    launcher = Launcher(None if attach else run_dir / "logs")
    started = time.monotonic()
    bus = None
    try:
        if attach:
            endpoint = cfg.zenoh.connect
            console.print(f"zenoh endpoint: {endpoint} (attached; run {run_id})", highlight=False)
        else:
            port = port or free_port(7447)
            endpoint = f"tcp/127.0.0.1:{port}"
            if not _launch_all(cfg, launcher, endpoint, port, run_id, config_path, console):
                return 1
        bus = ZenohBus.connect(endpoint, connect_timeout_s=cfg.zenoh.connect_timeout_s)
        orch = Orchestrator(bus, run_id, episodes, policies={"uav": cfg.run.policy_uav, "ugv": cfg.run.policy_ugv})
        orch.publish_manifest("running")
        successes = 0
        columns = (TextColumn("[bold]episodes"), BarColumn(), MofNCompleteColumn(), TextColumn("SR so far {task.fields[sr]}"),
                   TimeElapsedColumn())
        with Progress(*columns, console=console, transient=False) as progress:
            task = progress.add_task("episodes", total=orch.total, sr="-")
            while not orch.finished and not stop.is_set():
                for record in orch.pump(0.25):
                    successes += record.success
                    progress.update(task, completed=len(orch.stored),
                                    sr=f"{100 * successes / max(1, len(orch.stored)):.0f}%")
                dead = launcher.dead()
                if dead:
                    names = ", ".join(f"{n} (exit {c})" for n, c in dead.items())
                    console.print(f"[red]process exited early: {names}; logs in {run_dir / 'logs'}")
                    return 1
        if stop.is_set():
            console.print("[yellow]interrupted: stopping all processes")
            orch.publish_manifest("interrupted")
        else:
            orch.publish_manifest("finished")
            time.sleep(0.3)  # let the evaluator log its table before it is stopped
    finally:
        if launcher.children:
            launcher.stop_all(order=[n for n in launcher.children if n.startswith("world")]
                              + ["agent-uav", "agent-ugv", "evaluator", "router"])
        if bus is not None:
            bus.close()
    path = results_path(cfg.run.runs_dir, run_id)
    if path.exists() or attach:
        if path.exists():
            store = ResultStore(path)
            records = store.records(run_id)
            store.close()
        else:  # the evaluator stores elsewhere: show what was acknowledged
            records = [orch.records[e] for e in sorted(orch.stored) if e in orch.records]
        processes = "attached" if attach else f"{len(launcher.children) + 1} processes"
        console.print(results_table(by_difficulty(records), title=f"agos demo: {len(records)} episodes, "
                                    f"{cfg.run.policy_uav}/{cfg.run.policy_ugv} policies, {processes}"))
    console.print(f"results: {path}", highlight=False)
    if not attach:
        console.print(f"logs:    {run_dir / 'logs'}", highlight=False)
    console.print(f"wall time: {time.monotonic() - started:.1f} s", highlight=False)
    return 0
