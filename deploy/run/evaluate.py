"""``agos eval`` (and ``agos demo``, which is eval on the embedded defaults): one run.

A run directory holds ``run.json`` (policies, comm profile, timing mode, episode source),
``episodes.jsonl`` (the exact episodes), ``results.sqlite`` (written by the evaluator) and
``logs/``. ``agos eval --resume DIR`` re-reads the first two and leases only the episodes not yet
stored. The local processes (router, evaluator, agents, world workers) are started as children
unless ``--connect`` attaches to processes started elsewhere.
"""

from __future__ import annotations

import json
import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from agos.agents.names import needs_vlm
from agos.deploy.certs import RunCredentials
from agos.deploy.configure import episode_config
from agos.deploy.human import CONSOLE_NAMES, start_console
from agos.deploy.launcher import Launcher, free_port, wait_listening
from agos.deploy.orchestrator import Orchestrator
from agos.deploy.presence import LOST_IN_A_ROW, LossStreak, Stall, look, missing_lines
from agos.evaluator.metrics import by_difficulty
from agos.evaluator.store import ResultStore, results_path
from agos.evaluator.table import results_table
from agos.runtime.bus import ZenohBus
from agos.runtime.episode_config import EpisodeConfig, StoredConfigError, read_config
from agos.runtime.process import install_stop_handlers
from agos.runtime.schemas import EpisodeRecord, EpisodeSpec
from agos.runtime.settings import AgosConfig

log = logging.getLogger("agos.eval")
RUN_FILE = "run.json"
STANDIN_MODEL = "agos-standin"


class RunDirError(ValueError):
    """A run directory that cannot be created or resumed; the message names it and why."""


@dataclass
class RunPlan:
    run_dir: Path
    episodes: list[EpisodeSpec]
    policies: dict[str, str]
    config: EpisodeConfig
    """Everything that shapes the run's episodes; sent whole in every job grant."""
    resumed: bool = False
    vlm: dict[str, Any] = field(default_factory=dict)
    """VLM policies: ``base_url`` and ``model``, or ``standin`` (its fault string) for a stand-in server
    the run starts itself. Stored in run.json (never an API key)."""
    workers: int | str | None = None
    """``--workers`` as the run was started with (a count or ``auto``): what ``--resume`` uses again."""
    dataset_out: Path | None = None
    """A dataset build (deploy/dataset.py): the agents it starts write every decision there."""

    @property
    def run_id(self) -> str:
        return self.run_dir.name


def generated_episodes(cfg: AgosConfig) -> list[EpisodeSpec]:
    from agos.world.episodes.sampling import generate_episodes
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import open_town

    town = open_town(cfg.run.town)
    scene = Scene(town.layout, look=cfg.world.look)  # episodes are checked solvable by rendering, in the run's look
    try:
        return generate_episodes(town, scene, per_difficulty=cfg.run.per_difficulty, seed=cfg.run.episode_seed)
    finally:
        scene.close()


def vlm_plan(cfg: AgosConfig, policies: dict[str, str], standin: str | None) -> dict[str, Any]:
    """Where the run's VLM policies get their model; {} when no policy needs one."""
    if not any(needs_vlm(p) for p in policies.values()):
        return {}
    if standin is not None:
        return {"standin": standin, "model": STANDIN_MODEL}
    if not cfg.vlm.base_url or not cfg.vlm.model:
        names = ", ".join(sorted({p for p in policies.values() if needs_vlm(p)}))
        raise RunDirError(f"policy {names} asks a VLM: give --vlm-base-url URL --model NAME, or --vlm-standin for the "
                          "offline stand-in server")
    return {"base_url": cfg.vlm.base_url, "model": cfg.vlm.model}


def new_plan(cfg: AgosConfig, *, run_dir: Path | None, comm: str, timing_mode: str, stamp: bool,
             vlm_standin: str | None = None, workers: int | str | None = None, dataset_out: Path | None = None) -> RunPlan:
    """A new run directory with its run.json and episodes.jsonl. ``workers``: the command's
    ``--workers`` (a count or ``auto``), stored for ``--resume``; ``dataset_out``: see :class:`RunPlan`."""
    from agos.world.episodes.sampling import read_episodes, write_episodes

    # Everything that can be wrong with the command fails before episodes are generated.
    if run_dir is None:
        run_id = f"{cfg.run.run_id}-{datetime.now(UTC).strftime('%Y%m%d-%H%M%S')}" if stamp else cfg.run.run_id
        run_dir = cfg.run.runs_dir / run_id
    if (run_dir / "results.sqlite").exists():
        raise RunDirError(f"{run_dir}: already holds results; resume it with: agos eval --resume {run_dir}")
    policies = {"uav": cfg.run.policy_uav, "ugv": cfg.run.policy_ugv}
    config = episode_config(cfg, policies=policies, comm=comm, timing_mode=timing_mode)  # bad names fail here
    vlm = vlm_plan(cfg, policies, vlm_standin)
    if cfg.run.episodes_file:
        from agos.world.towns.asset import check_towns

        episodes = read_episodes(cfg.run.episodes_file)
        check_towns(episodes, str(cfg.run.episodes_file))
    else:
        episodes = generated_episodes(cfg)
    run_dir.mkdir(parents=True, exist_ok=True)
    write_episodes(run_dir / "episodes.jsonl", episodes)
    plan = RunPlan(run_dir, episodes, policies, config, vlm=vlm, workers=workers, dataset_out=dataset_out)
    (run_dir / RUN_FILE).write_text(json.dumps({
        "run_id": plan.run_id, "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "policies": plan.policies, "comm": config.comm.name, "timing_mode": config.timing_mode, "episodes": len(episodes),
        "vlm": vlm, "workers": workers, "config_hash": config.config_hash(),
        **({"dataset_out": str(dataset_out)} if dataset_out is not None else {}),
        "episode_config": config.model_dump(mode="json"),
        "episode_source": str(cfg.run.episodes_file or f"generated: {cfg.run.town}, {cfg.run.per_difficulty}/difficulty, "
                                                         f"seed {cfg.run.episode_seed}"),
    }, indent=2) + "\n")
    return plan


def resume_plan(run_dir: Path) -> RunPlan:
    from agos.world.episodes.sampling import read_episodes

    path = run_dir / RUN_FILE
    if not path.exists():
        raise RunDirError(f"{run_dir}: no {RUN_FILE}; not an agos run directory")
    meta = json.loads(path.read_text())
    if "episode_config" not in meta:
        raise RunDirError(f"{path}: made by an agos without episode configurations; start a new run")
    try:
        config = read_config(meta["episode_config"], where=str(path))
    except StoredConfigError as exc:
        raise RunDirError(str(exc)) from None
    return RunPlan(run_dir, read_episodes(run_dir / "episodes.jsonl"), meta["policies"], config, resumed=True,
                   vlm=meta.get("vlm", {}), workers=meta.get("workers"),
                   dataset_out=Path(meta["dataset_out"]) if meta.get("dataset_out") else None)


def stored_episodes(run_dir: Path) -> set[str]:
    """Episodes of a run directory with a ``finished`` record: a resume skips them and plays the rest,
    including episodes stored as infrastructure failures (a missing agent, a crashed world)."""
    path = run_dir / "results.sqlite"
    if not path.exists():
        return set()
    store = ResultStore(path, create=False)
    try:
        return store.finished_ids()
    finally:
        store.close()


@dataclass(frozen=True)
class Recording:
    """``--record DIR [--record-full]``: a recorder process writes one rerun file per episode to ``out_dir``."""

    out_dir: Path
    full: bool = False


def _start_recorder(launcher: Launcher, recording: Recording, endpoint: str, run_id: str, config_path: Path | None,
                    env: dict[str, str] | None) -> float:
    """Start ``agos record`` (its own process and zenoh session, the observer identity on a secured
    bus); returns when it started (epoch seconds), for :func:`agos.deploy.record.wait_ready`."""
    since = time.time()
    launcher.start("recorder", ["record", "--connect", endpoint, "--run", run_id, "--out", str(recording.out_dir),
                                *(["--full"] if recording.full else []),
                                *(["--config", str(config_path)] if config_path else [])], env=env)
    return since


def _recorder_ready(recording: Recording, since: float, launcher: Launcher, console: Console) -> None:
    """Wait (at most 30 s) until the recorder has subscribed, so it sees the first episode start;
    a recorder that does not come up is reported and the run goes on without it."""
    from agos.deploy.record import wait_ready

    if wait_ready(recording.out_dir, 30.0, since, alive=lambda: "recorder" not in launcher.dead()):
        console.print(f"recording to {recording.out_dir} ({'full resolution' if recording.full else 'thumbnails'})",
                      highlight=False)
    else:
        console.print(f"[yellow]the recorder did not come up; the run goes on; see {launcher.log_dir / 'recorder.log'}")


def _launch_all(cfg: AgosConfig, plan: RunPlan, launcher: Launcher, endpoint: str, port: int, workers: int,
                config_path: Path | None, console: Console, creds: RunCredentials | None = None,
                recording: Recording | None = None) -> bool:
    def env(identity: str) -> dict[str, str] | None:
        return creds.env(identity) if creds is not None else None

    common = ["--connect", endpoint, "--run", plan.run_id] + (["--config", str(config_path)] if config_path else [])
    launcher.start("router", ["router", "--listen", endpoint], env=env("router"))
    if not wait_listening("127.0.0.1", port, 15.0):
        console.print(f"[red]router did not listen on {endpoint}; see {launcher.log_dir / 'router.log'}")
        return False
    console.print(f"zenoh endpoint: {endpoint}" + (" (mutual TLS, access control)" if creds else ""), highlight=False)
    recorder_since = None if recording is None else _start_recorder(launcher, recording, endpoint, plan.run_id,
                                                                     config_path, env("observer"))
    launcher.start("evaluator", ["evaluator", "--connect", endpoint, "--runs-dir", str(plan.run_dir.parent)]
                   + (["--config", str(config_path)] if config_path else []), env=env("evaluator"))
    vlm_args = _start_vlm(cfg, plan, launcher, console)
    if vlm_args is None:
        return False
    # Every episode in flight may wait on an agent at once: decisions answered at once >= workers.
    at_once = ["--concurrency", str(max(32, workers))]
    if plan.dataset_out is not None:
        at_once += ["--dataset-out", str(plan.dataset_out)]
    people = start_console(launcher, plan.policies, common, plan.config, console, env)  # roles a person plays
    if people is None:
        return False
    for role in (r for r in ("uav", "ugv") if r not in people):
        launcher.start(f"agent-{role}", ["agent", "--role", role, "--policy", plan.policies[role], *common, *vlm_args,
                                         *at_once], env=env(f"agent-{role}"))
    if recording is not None and recorder_since is not None:
        _recorder_ready(recording, recorder_since, launcher, console)
    for k in range(workers):
        launcher.start(f"world-{k}", ["world", *common, "--worker-id", f"w{k}"], env=env("world"))
    return True


def _client_flags(cfg: AgosConfig) -> list[str]:
    """The VLM client settings of this command, as flags for the agent processes it starts."""
    v = cfg.vlm
    flags = ["--vlm-api-key-env", v.api_key_env, "--vlm-timeout", str(v.timeout_s), "--vlm-max-retries", str(v.max_retries)]
    if not v.structured:
        flags.append("--vlm-no-structured")
    if v.trace_file is not None:
        flags += ["--vlm-trace", str(v.trace_file)]
    return flags


def _start_vlm(cfg: AgosConfig, plan: RunPlan, launcher: Launcher, console: Console) -> list[str] | None:
    """Agent flags for the run's model endpoint; starts the stand-in server when the plan asks for it.
    None when the stand-in did not come up."""
    if not plan.vlm:
        return []
    if "standin" not in plan.vlm:
        return ["--vlm-base-url", plan.vlm["base_url"], "--model", plan.vlm["model"], *_client_flags(cfg)]
    port = free_port(8000)
    faults = ["--faults", plan.vlm["standin"]] if plan.vlm["standin"] else []
    launcher.start("vlm-standin", ["vlm-standin", "--port", str(port), "--model", STANDIN_MODEL, *faults,
                                   "--retry-after-s", "0.2", "--hang-s", "5"])
    if not wait_listening("127.0.0.1", port, 30.0):
        console.print(f"[red]the VLM stand-in did not listen on port {port}; see {launcher.log_dir / 'vlm-standin.log'}")
        return None
    url = f"http://127.0.0.1:{port}/v1"
    console.print(f"VLM stand-in: {url} (faults: {plan.vlm['standin'] or 'none'})", highlight=False)
    # Injected timeouts hang 5 s; a 2 s attempt timeout makes the client retry them quickly, and ten
    # retries make a decision that never gets an answer rare even at high injected fault rates.
    return ["--vlm-base-url", url, "--model", STANDIN_MODEL, *_client_flags(cfg), "--vlm-timeout", "2",
            "--vlm-max-retries", "10"]


def run(cfg: AgosConfig, plan: RunPlan, *, workers: int, attach: bool = False, port: int | None = None,
        config_path: Path | None = None, console: Console | None = None, stuck_after_s: float = 180.0,
        secure: bool = False, recording: Recording | None = None,
        on_record: Callable[[EpisodeRecord], None] | None = None) -> int:
    """Run ``plan`` to the end. ``secure``: the processes it starts talk mutual TLS through a router
    enforcing access control, with a throwaway CA made for this run (deploy/certs.py). ``recording``:
    a recorder process writes the run's episodes as rerun files (deploy/record.py); an attached run
    starts one too, connected as this command's settings say. ``on_record``: called with each record
    stored during the run, on this thread (a dataset build assembles the episode's files)."""
    console = console or Console()
    stop = install_stop_handlers()
    done_before = stored_episodes(plan.run_dir)
    launcher = Launcher(None if attach else plan.run_dir / "logs")
    side = Launcher(plan.run_dir / "logs") if attach and recording is not None else None  # an attached run's recorder
    started = time.monotonic()
    bus = None
    orch = None
    interrupted = False
    creds = RunCredentials() if secure and not attach else None
    try:
        if attach:
            own = cfg.zenoh
            console.print(f"zenoh endpoint: {own.connect} (attached; run {plan.run_id})", highlight=False)
            if side is not None and recording is not None:
                since = _start_recorder(side, recording, own.connect, plan.run_id, config_path, None)
                _recorder_ready(recording, since, side, console)
        else:
            port = port or free_port(7447)
            endpoint = f"{'tls' if creds else 'tcp'}/127.0.0.1:{port}"
            own = creds.settings(cfg.zenoh, "orchestrator", endpoint) if creds else cfg.zenoh.model_copy(
                update={"connect": endpoint})
            if not _launch_all(cfg, plan, launcher, endpoint, port, workers, config_path, console, creds, recording):
                return 1
        bus = ZenohBus.from_settings(own)
        orch = Orchestrator(bus, plan.run_id, plan.episodes, policies=plan.policies,
                            config=plan.config,
                            already_stored=done_before, resumed=plan.resumed, stuck_after_s=stuck_after_s,
                            )
        orch.publish_manifest("running")
        if done_before:
            console.print(f"resuming {plan.run_dir}: {len(orch.stored)} of {orch.total} episodes already finished; "
                          "the others (infrastructure failures included) run now")
        successes = 0
        columns = (TextColumn("[bold]episodes"), BarColumn(), MofNCompleteColumn(),
                   TextColumn("SR so far {task.fields[sr]}"), TextColumn("{task.fields[dps]} decisions/s"),
                   TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn())
        with Progress(*columns, console=console, transient=False) as progress:
            task = progress.add_task("episodes", total=orch.total, completed=len(orch.stored), sr="-", dps="-")
            fresh = 0
            window: deque[tuple[float, int]] = deque()  # (time, decisions seen): the rate over the last 10 s
            watch = Stall(cfg.run.presence_check_s)
            losses = LossStreak(LOST_IN_A_ROW)
            unstored_checks = workerless_checks = 0
            while not orch.finished and not stop.is_set():
                for record in orch.pump(0.25):
                    cause = losses.add(record)
                    if cause is not None:
                        console.print(f"[red]stopping: {LOST_IN_A_ROW} episodes in a row lost to the same cause "
                                      f"({record.status}): {cause}", highlight=False)
                        orch.publish_manifest("interrupted")  # attached workers stop asking for jobs
                        return 3
                    if on_record is not None:
                        on_record(record)
                    fresh += 1
                    successes += record.success
                    progress.update(task, completed=len(orch.stored), sr=f"{100 * successes / fresh:.0f}%")
                window.append((time.monotonic(), orch.decisions))
                while window[-1][0] - window[0][0] > 10.0:
                    window.popleft()
                if window[-1][0] > window[0][0]:
                    rate = (window[-1][1] - window[0][1]) / (window[-1][0] - window[0][0])
                    progress.update(task, dps=f"{rate:.1f}")
                if watch.due(orch.decisions + len(orch.stored)):
                    present = look(bus, plan.run_id)
                    for line in missing_lines(present, plan.run_id, own.connect, plan.policies):
                        progress.console.print(f"[yellow]waiting: {line}", highlight=False)
                    # Records nobody stores are episodes lost to a missing evaluator (their worker gives up
                    # after a minute): after LOST_IN_A_ROW checks in a row, stop rather than lose them all.
                    unstored_checks = unstored_checks + 1 if not present.evaluator and orch.unacknowledged() else 0
                    workerless_checks = workerless_checks + 1 if not present.worlds else 0
                    missing = None  # (what is wrong, the command that starts what is missing)
                    if workerless_checks >= LOST_IN_A_ROW:
                        missing = (f"no world worker joined run {plan.run_id}", "world")
                    elif unstored_checks >= LOST_IN_A_ROW:
                        missing = (f"no evaluator stored the records of {', '.join(orch.unacknowledged())}", "evaluator")
                    if missing is not None:
                        console.print(f"[red]stopping: {missing[0]} ({LOST_IN_A_ROW} checks {cfg.run.presence_check_s:g} s "
                                      f"apart); start one with `agos {missing[1]} --connect {own.connect} --run "
                                      f"{plan.run_id}` and resume with `agos eval --resume {plan.run_dir}`", highlight=False)
                        orch.publish_manifest("interrupted")
                        return 3
                # A recorder that dies loses the recording, never the run (nothing waits for it).
                dead = {n: c for n, c in launcher.dead().items() if not n.startswith("world") and n != "recorder"}
                if dead:
                    names = ", ".join(f"{n} (exit {c})" for n, c in dead.items())
                    console.print(f"[red]process exited early: {names}; logs in {plan.run_dir / 'logs'}")
                    return 1
                if launcher.children and all(n in launcher.dead() for n in launcher.children if n.startswith("world")):
                    console.print(f"[red]every world worker exited; logs in {plan.run_dir / 'logs'}")
                    return 1
        interrupted = stop.is_set()
        orch.publish_manifest("interrupted" if interrupted else "finished")
        if not interrupted:
            time.sleep(0.3)  # let the evaluator log its table before it is stopped
    finally:
        if launcher.children:
            launcher.stop_all(order=[n for n in launcher.children if n.startswith("world")]
                              + ["agent-uav", "agent-ugv", *CONSOLE_NAMES, "vlm-standin", "evaluator", "recorder", "router"])
        if side is not None:
            side.stop_all()
        if bus is not None:
            bus.close()
        if creds is not None:
            creds.close()
    _summary(console, plan, orch, attach, len(launcher.children) + 1, time.monotonic() - started)
    if recording is not None:
        _recording_summary(console, recording)
    if interrupted:
        console.print(f"[yellow]interrupted: every process stopped; resume with: agos eval --resume {plan.run_dir}")
        return 130  # as a shell reports a command stopped by Ctrl-C: scripts must not take it for a finished run
    return 0


def _summary(console: Console, plan: RunPlan, orch: Orchestrator | None, attach: bool, processes: int,
             wall_s: float) -> None:
    path = results_path(plan.run_dir.parent, plan.run_id)
    records = []
    if path.exists():
        store = ResultStore(path)
        records = store.records(plan.run_id)
        store.close()
    elif orch is not None:  # the evaluator stores elsewhere: show what was acknowledged
        records = [orch.records[e] for e in sorted(orch.stored) if e in orch.records]
    if records:
        where = "attached" if attach else f"{processes} processes"
        title = (f"{plan.run_id}: {len(records)} episodes, {plan.policies['uav']}/{plan.policies['ugv']} policies, "
                 f"comm {plan.config.comm.name}, {where}")
        console.print(results_table(by_difficulty(records), title=title))
    console.print(f"results: {path}", highlight=False)
    if not attach:
        console.print(f"logs:    {plan.run_dir / 'logs'}", highlight=False)
    if orch is not None and orch.releases:
        console.print(f"re-leased episodes: {orch.releases}", highlight=False)
    if orch is not None and orch.rejections.total:
        console.print(f"orchestrator {orch.rejections.summary()} (see docs/ARCHITECTURE.md, 'A hostile bus')",
                      highlight=False)
    if orch is not None:
        rate = orch.episodes_per_minute(len(orch.stored) - orch.already)
        if rate is not None:
            console.print(f"throughput: {rate:.1f} episodes/min (first lease to last stored episode)", highlight=False)
    console.print(f"wall time: {wall_s:.1f} s", highlight=False)


def _recording_summary(console: Console, recording: Recording) -> None:
    """What the recorder wrote and lost (its ``recorder.json``), and how to look at it."""
    from agos.deploy.record import STATUS_FILE

    try:
        status = json.loads((recording.out_dir / STATUS_FILE).read_text())
    except (OSError, ValueError):
        console.print(f"[yellow]recordings: the recorder left no {STATUS_FILE} in {recording.out_dir}", highlight=False)
        return
    files = sorted(e["file"] for e in status.get("episodes", {}).values())
    dropped = sum(status.get("dropped_by_queue", {}).values()) + status.get("not_written", 0)
    console.print(f"recordings: {len(files)} episodes in {recording.out_dir}"
                  + (f"; the recorder fell behind and dropped {dropped} visualisation samples" if dropped else ""),
                  highlight=False)
    if files:
        console.print(f"look at one: agos view {recording.out_dir / files[0]}", highlight=False)
