"""``agos eval`` (and ``agos demo``, which is eval on the embedded defaults): one run to its end.

:func:`run` starts the run's processes (deploy/run/local.py) unless ``--connect`` attaches to
processes started elsewhere, hosts the orchestrator, and follows the run until every episode is
stored, Ctrl-C, or a reason to stop: episodes lost in a row to one cause, processes missing for
several presence checks (deploy/run/presence.py), a child that exited. A child that dies by a signal
or a non-zero exit meanwhile is named once, with how it died and the last lines of its log
(deploy/run/launcher.py, :class:`~agos.deploy.run.launcher.Deaths`). Then it stops every child and
prints the results. Its plan and run directory are deploy/run/plan.py's.
"""

from __future__ import annotations

import json
import logging
import re
import shlex
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from agos.deploy.ops.certs import RunCredentials
from agos.deploy.run.budget import EXIT_CAPPED, Budget
from agos.deploy.run.human import CONSOLE_NAMES
from agos.deploy.run.launcher import ROUTER_PORT, STOP_GRACE_S, Deaths, Launcher, free_port
from agos.deploy.run.local import Recording, launch_all, start_attached_recorder
from agos.deploy.run.orchestrator import STUCK_AFTER_S, Orchestrator
from agos.deploy.run.plan import RunPlan, stored_episodes
from agos.deploy.run.presence import LOST_IN_A_ROW, LossStreak, Stall, missing_lines, started_kinds, who_is_here
from agos.evaluator.cost import cost_of, tokens_of
from agos.evaluator.metrics import by_difficulty
from agos.evaluator.store import ResultStore, results_path
from agos.evaluator.table import results_table
from agos.runtime.bus import Bus, ZenohBus
from agos.runtime.deaths import short_how
from agos.runtime.process import Interrupted, install_stop_handlers
from agos.runtime.schemas import EpisodeRecord
from agos.runtime.settings import AgosConfig, ZenohSettings
from agos.runtime.traces import record_usage

log = logging.getLogger("agos.eval")

PUMP_S = 0.25
"""How long each turn of the run's loop waits for the orchestrator's traffic."""
RATE_WINDOW_S = 10.0
"""The progress bar's decisions per second are over this many seconds."""
EVALUATOR_TABLE_S = 0.3
"""How long a finished run waits before it stops the evaluator, which logs its table first."""
DEATH_NOTES = {"recorder": "; the run goes on without recording"}
"""What a child's death means for the run, where the run goes on (:class:`~agos.deploy.run.launcher.Deaths`)."""
STOP_ORDER = ["agent-uav", "agent-ugv", *CONSOLE_NAMES, "vlm-standin", "evaluator", "recorder", "router"]
"""The order children stop in after the world workers: the processes that serve others last."""


@dataclass(frozen=True)
class Halt:
    """Why a run stops before its end: the line to print, the exit status, and whether to announce
    the run interrupted (attached workers then stop asking for jobs)."""

    line: str
    code: int
    announce: bool = True


class Bar:
    """The progress bar: episodes stored, the success rate of this invocation's episodes so far, and
    decisions per second over the last ``RATE_WINDOW_S``."""

    COLUMNS = (TextColumn("[bold]episodes"), BarColumn(), MofNCompleteColumn(),
               TextColumn("SR so far {task.fields[sr]}"), TextColumn("{task.fields[dps]} decisions/s"),
               TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn())

    def __init__(self, progress: Progress, orch: Orchestrator) -> None:
        self.progress, self.orch = progress, orch
        self.task = progress.add_task("episodes", total=orch.total, completed=len(orch.stored), sr="-", dps="-")
        self.fresh = self.successes = 0
        self.window: deque[tuple[float, int]] = deque()  # (time, decisions seen)

    def stored(self, record: EpisodeRecord) -> None:
        self.fresh += 1
        self.successes += record.success
        self.progress.update(self.task, completed=len(self.orch.stored), sr=f"{100 * self.successes / self.fresh:.0f}%")

    def decisions(self) -> None:
        window = self.window
        window.append((time.monotonic(), self.orch.decisions))
        while window[-1][0] - window[0][0] > RATE_WINDOW_S:
            window.popleft()
        if window[-1][0] > window[0][0]:
            rate = (window[-1][1] - window[0][1]) / (window[-1][0] - window[0][0])
            self.progress.update(self.task, dps=f"{rate:.1f}")


class Losses:
    """Stops the run once ``LOST_IN_A_ROW`` episodes in a row were lost to the same cause."""

    def __init__(self, resume: str | None = None) -> None:
        self.streak = LossStreak(LOST_IN_A_ROW)
        self.resume = resume

    def check(self, record: EpisodeRecord) -> Halt | None:
        cause = self.streak.add(record)
        if cause is None:
            return None
        then = f"; resume with `{self.resume}` once it answers" if record.status == "infra_error" and self.resume else ""
        return Halt(f"[red]stopping: {LOST_IN_A_ROW} episodes in a row lost to the same cause ({record.status}): "
                    f"{escape(cause)}{escape(then)}", 3)


EXIT_INFRA = 6
"""``agos eval``'s exit status when the run ended with episodes stored as ``infra_error`` (their model
endpoint gave no answer in every attempt): not scored, and ``--resume`` plays them again."""


class Outages:
    """Prints the orchestrator's lines about model endpoint outages (an episode paused, stored as
    ``infra_error``, the endpoint answering again) as they come, one console line each."""

    def __init__(self, orch: Orchestrator, console: Console) -> None:
        self.orch, self.console = orch, console

    def check(self) -> Halt | None:
        for line in self.orch.notices:
            self.console.print(f"[yellow]{escape(line)}", highlight=False)
        self.orch.notices.clear()
        return None


def infra_error_line(records: list[EpisodeRecord], resume: str) -> str | None:
    """One line for a run that ended with ``infra_error`` episodes, naming how many, the last cause and
    the resume command; None without any."""
    lost = [r for r in records if r.status == "infra_error"]
    if not lost:
        return None
    return (f"{len(lost)} episode{'' if len(lost) == 1 else 's'} stored as infra_error (not scored; "
            f"{lost[-1].error}); play {'it' if len(lost) == 1 else 'them'} again once the endpoint answers: {resume}")


def resume_command(plan: RunPlan) -> str:
    """The command that resumes ``plan``'s run: ``agos eval --resume DIR`` (a caller whose run is part of
    more, as a dataset build, names its own)."""
    return f"agos eval --resume {shlex.quote(str(plan.run_dir))}"


class Absences:
    """While the run makes no progress, every ``[run] presence_check_s``: say which processes are
    missing, and stop once no world worker joined, or records stayed unstored, for ``LOST_IN_A_ROW``
    checks in a row (their worker gives up on unstored records after a minute; the orchestrator
    publishes them again every 5 s). Unstored records stop the run whether or not an evaluator is on
    the bus: one that is there and does not store them in that time never will, and a run waiting
    for it would never end."""

    def __init__(self, cfg: AgosConfig, plan: RunPlan, bus: Bus, orch: Orchestrator, endpoint: str,
                 console: Console, launcher: Launcher | None = None, resume: str | None = None) -> None:
        """``launcher``: the processes this command started (none when attached), which are said to be
        joining rather than missing while they run; ``resume``: the command that resumes the run
        (:func:`resume_command`)."""
        self.every_s, self.plan, self.bus, self.orch, self.endpoint = cfg.run.presence_check_s, plan, bus, orch, endpoint
        self.console, self.launcher = console, launcher
        self.resume = resume or resume_command(plan)
        self.stall = Stall(self.every_s)
        self.unstored = self.workerless = 0

    def check(self) -> Halt | None:
        if not self.stall.due(self.orch.decisions + len(self.orch.stored)):
            return None
        run_id = self.plan.run_id
        present = who_is_here(self.bus, run_id)
        launcher = self.launcher
        started = started_kinds(n for n in launcher.children if n not in launcher.dead()) if launcher else frozenset()
        logs = launcher.log_dir if launcher else None
        for line in missing_lines(present, run_id, self.endpoint, self.plan.policies, started, logs):
            self.console.print(f"[yellow]waiting: {line}", highlight=False)
        self.unstored = self.unstored + 1 if self.orch.unacknowledged() else 0
        self.workerless = self.workerless + 1 if not present.worlds else 0
        if self.workerless >= LOST_IN_A_ROW:
            what, kind, log = f"no world worker joined run {run_id}", "world", "world-0.log"
        elif self.unstored >= LOST_IN_A_ROW:
            unstored = ", ".join(self.orch.unacknowledged())
            what, kind, log = f"no evaluator stored the records of {unstored}", "evaluator", "evaluator.log"
        else:
            return None
        if kind in started and logs is not None:  # it runs but never joined or stored: another would not help
            fix = f"see {logs / log}"
        elif kind == "evaluator" and present.evaluator:
            fix = "see the log of the evaluator serving it"
        else:
            fix = f"start one with `agos {kind} --connect {self.endpoint} --run {run_id}`"
        return Halt(f"[red]stopping: {what} ({LOST_IN_A_ROW} checks {self.every_s:g} s apart); {fix} and resume with "
                    f"`{self.resume}`", 3)


class Capped:
    """``--max-cost-usd`` and ``--max-tokens`` (deploy/run/budget.py): the orchestrator's gate, and the
    stop once the gate holds the next episode back and every played episode is stored."""

    def __init__(self, budget: Budget, orch: Orchestrator, resume: str) -> None:
        self.budget, self.orch, self.resume = budget, orch, resume
        orch.may_lease = self.may_lease

    def may_lease(self, in_flight: int) -> bool:
        self.budget.see(self.orch.records.values())
        return self.budget.may_lease(in_flight)

    def check(self) -> Halt | None:
        orch = self.orch
        if orch.finished or orch.leases or orch.gave_up:  # played episodes are stored before the run stops
            return None
        self.budget.see(orch.records.values())
        refused = self.budget.refusal(0)
        if refused is None:
            return None
        flag, why = refused
        left = orch.total - len(orch.stored)
        return Halt(f"[red]stopping: {escape(why)}; {left} of {orch.total} episodes not run; resume with a higher cap: "
                    f"{escape(self.resume)} {flag} N (or none)", EXIT_CAPPED)


LOG_RECORD = re.compile(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d")
"""How a child's log record starts (runtime/process.py's format: its time first); other lines continue one."""


def last_error(log: Path, tail_bytes: int = 32_768) -> str | None:
    """The message of the last ERROR record a child logged since its latest start (the launcher's
    ``=====`` line), its continuation lines joined into one line (a traceback left out); None when
    there is none (or no log)."""
    try:
        with log.open("rb") as f:
            f.seek(max(0, f.seek(0, 2) - tail_bytes))
            text = f.read().decode(errors="replace")
    except OSError:
        return None
    found: list[str] | None = None
    continues = False
    for line in text.splitlines():
        if line.startswith("===== agos "):
            found, continues = None, False
        elif LOG_RECORD.match(line):
            continues = " ERROR " in line
            if continues:
                found = [line.split(" ERROR ", 1)[1].split(": ", 1)[-1].strip()]
        elif continues and found is not None:
            if line.startswith("Traceback (most recent call last)"):
                continues = False
            elif line.strip():
                found.append(line.strip())
    return " ".join(found) if found else None


def exited_children(launcher: Launcher, logs: Path) -> Halt | None:
    """A child that must not die did (a recorder that dies loses the recording, never the run), or
    every world worker exited."""
    dead = {n: c for n, c in launcher.dead().items() if not n.startswith("world") and n != "recorder"}
    if dead:
        names = ", ".join(f"{n} ({short_how(c)})" for n, c in dead.items())
        reasons = dict.fromkeys(r for n in dead if (r := last_error(logs / f"{n}.log")))  # each once, in order
        why = f": {escape('; '.join(reasons))}" if reasons else ""
        return Halt(f"[red]process exited early: {names}{why}; logs in {logs}", 1, announce=False)
    if launcher.children and all(n in launcher.dead() for n in launcher.children if n.startswith("world")):
        return Halt(f"[red]every world worker exited; logs in {logs}", 1, announce=False)
    return None


def follow(orch: Orchestrator, bar: Bar, stop_is_set: Callable[[], bool], losses: Losses,
           watches: list[Callable[[], Halt | None]], on_record: Callable[[EpisodeRecord], None] | None) -> Halt | None:
    """Pump the orchestrator until every episode is stored, ``stop_is_set()``, or a :class:`Halt`."""
    while not orch.finished and not stop_is_set():
        for record in orch.pump(PUMP_S):
            halt = losses.check(record)
            if halt is not None:
                return halt
            if on_record is not None:
                on_record(record)
            bar.stored(record)
        bar.decisions()
        for watch in watches:
            halt = watch()
            if halt is not None:
                return halt
    return None


def _connect(cfg: AgosConfig, plan: RunPlan, launcher: Launcher, side: Launcher | None, *, attach: bool,
             port: int | None, workers: int, config_path: Path | None, console: Console,
             creds: RunCredentials | None, recording: Recording | None) -> ZenohSettings | None:
    """The orchestrator's own zenoh settings, once the run's processes are up (started here unless
    ``attach``); None when they did not come up."""
    if attach:
        console.print(f"zenoh endpoint: {cfg.zenoh.connect} (attached; run {plan.run_id})", highlight=False)
        if side is not None and recording is not None:
            start_attached_recorder(side, recording, cfg, config_path, plan.run_id, console)
        return cfg.zenoh
    port = port or free_port(ROUTER_PORT)
    endpoint = f"{'tls' if creds else 'tcp'}/127.0.0.1:{port}"
    own = creds.settings(cfg.zenoh, "orchestrator", endpoint) if creds else cfg.zenoh.model_copy(update={"connect": endpoint})
    if not launch_all(cfg, plan, launcher, endpoint, port, workers, config_path, console, creds, recording):
        return None
    return own


def run(cfg: AgosConfig, plan: RunPlan, *, workers: int, attach: bool = False, port: int | None = None,
        config_path: Path | None = None, console: Console | None = None, stuck_after_s: float = STUCK_AFTER_S,
        secure: bool = False, recording: Recording | None = None,
        on_record: Callable[[EpisodeRecord], None] | None = None, resume: str | None = None) -> int:
    """Run ``plan`` to the end. ``secure``: the processes it starts talk mutual TLS through a router
    enforcing access control, with a throwaway CA made for this run (deploy/ops/certs.py). ``recording``:
    a recorder process writes the run's episodes as rerun files (deploy/recording/recorder.py); an
    attached run starts one too, connected as this command's settings say. ``on_record``: called with
    each record stored during the run, on this thread (a dataset build assembles the episode's files).
    ``resume``: the command an interrupted or stopped run names to go on (default :func:`resume_command`)."""
    console = console or Console(soft_wrap=True)  # paths and commands it prints are never cut at the width
    stop = install_stop_handlers()
    done_before = stored_episodes(plan.run_dir)
    launcher = Launcher(None if attach else plan.run_dir / "logs")
    side = Launcher(plan.run_dir / "logs") if attach and recording is not None else None  # an attached run's recorder
    deaths = Deaths(launcher, side, notes=DEATH_NOTES)  # said while the run goes on, never for those stopped at its end
    started = time.monotonic()
    bus = None
    orch = None
    interrupted = False
    creds = RunCredentials() if secure and not attach else None
    if plan.endpoint:
        console.print(plan.endpoint, highlight=False)
    try:
        own = _connect(cfg, plan, launcher, side, attach=attach, port=port, workers=workers, config_path=config_path,
                       console=console, creds=creds, recording=recording)
        if own is None:
            return 1
        bus = ZenohBus.from_settings(own)
        orch = Orchestrator(bus, plan.run_id, plan.episodes, policies=plan.policies, config=plan.config,
                            already_stored=done_before, resumed=plan.resumed, stuck_after_s=stuck_after_s,
                            max_infra_attempts=cfg.run.max_infra_attempts, infra_wait_s=cfg.run.infra_wait_s,
                            reconnect_grace_s=cfg.run.reconnect_grace_s)
        orch.publish_manifest("running")
        if done_before:
            console.print(f"resuming {plan.run_dir}: {len(orch.stored)} of {orch.total} episodes already finished; "
                          "the others (infrastructure failures included) run now")
        watches = []
        if plan.caps:
            before = _stored_records(plan)
            watches.append(Capped(Budget(plan.caps, plan.prices, before), orch, resume or resume_command(plan)).check)
        with Progress(*Bar.COLUMNS, console=console, transient=False) as progress:
            absences = Absences(cfg, plan, bus, orch, own.connect, progress.console, None if attach else launcher,
                                resume)
            halt = follow(orch, Bar(progress, orch), stop.is_set, Losses(resume or resume_command(plan)),
                          [Outages(orch, progress.console).check, absences.check,
                           lambda: deaths.report(progress.console),
                           lambda: exited_children(launcher, plan.run_dir / "logs"), *watches],
                          on_record)
            if halt is not None:
                console.print(halt.line, highlight=False)
                if halt.announce:
                    orch.publish_manifest("interrupted")  # attached workers stop asking for jobs
                return halt.code
        interrupted = stop.is_set()
        orch.publish_manifest("interrupted" if interrupted else "finished")
        if not interrupted:
            time.sleep(EVALUATOR_TABLE_S)
    except Interrupted:  # Ctrl-C while this command's own session was still connecting
        interrupted = True
    finally:
        deaths.report(console)  # one that died since the last look; nothing is stopped yet
        # A recorder drains its queue for up to DRAIN_S after the stop and then writes its files: its
        # time on top of the usual grace, or a loaded machine kills it with its episodes unwritten.
        grace_s = STOP_GRACE_S
        if recording is not None:
            from agos.deploy.recording.recorder import DRAIN_S  # (rerun's import, only for runs that record)

            grace_s += DRAIN_S
        if launcher.children:
            launcher.stop_all(order=[n for n in launcher.children if n.startswith("world")] + STOP_ORDER, grace_s=grace_s)
        if side is not None:
            side.stop_all(grace_s=grace_s)
        if bus is not None:
            bus.close()
        if creds is not None:
            creds.close()
    records = _summary(console, plan, orch, attach, len(launcher.children) + 1, time.monotonic() - started)
    if recording is not None:
        _recording_summary(console, recording)
    if interrupted:
        console.print(f"[yellow]interrupted: every process stopped; resume with: {resume or resume_command(plan)}",
                      highlight=False)
        return 130  # as a shell reports a command stopped by Ctrl-C: scripts must not take it for a finished run
    line = infra_error_line(records, resume or resume_command(plan))
    if line is not None:
        console.print(f"[red]{escape(line)}", highlight=False)
        return EXIT_INFRA
    return 0


def _stored_records(plan: RunPlan) -> list[EpisodeRecord]:
    """The run's records stored before this invocation (what a resumed run already spent)."""
    path = results_path(plan.run_dir.parent, plan.run_id)
    if not path.exists():
        return []
    with ResultStore(path) as store:
        return store.records(plan.run_id)


def usage_line(records: list[EpisodeRecord], plan: RunPlan) -> str | None:
    """The run's model calls in one line (tokens, traced decisions, cost at its prices); None without tokens."""
    usage = [u for r in records for u in record_usage(r)]
    if not tokens_of(usage):
        return None
    prompt, completion = sum(u.prompt_tokens for u in usage), sum(u.completion_tokens for u in usage)
    decisions = sum(u.decisions for u in usage)
    cost = cost_of(usage, plan.prices)
    priced = (f", ${cost:.4f} at {plan.prices.describe()}" if cost is not None and plan.prices is not None
              else "; cost: give --price-in/--price-out or --prices to agos metrics or report")
    return (f"model calls: {prompt:,} prompt + {completion:,} completion tokens over {decisions:,} decisions "
            f"({(prompt + completion) / decisions:,.0f} a decision){priced}")


def _summary(console: Console, plan: RunPlan, orch: Orchestrator | None, attach: bool, processes: int,
             wall_s: float) -> list[EpisodeRecord]:
    """Print the run's results and figures; the records it showed (every stored one of the run)."""
    path = results_path(plan.run_dir.parent, plan.run_id)
    records = []
    if path.exists():
        with ResultStore(path) as store:
            records = store.records(plan.run_id)
    elif orch is not None:  # the evaluator stores elsewhere: show what was acknowledged
        records = [orch.records[e] for e in sorted(orch.stored) if e in orch.records]
    if records:
        where = "attached" if attach else f"{processes} processes"
        sensing = "".join(f", {what} {name}" for what, name, default in (
            ("pose error", plan.config.pose_error.name, "exact"),
            ("model", plan.config.model_link.name if plan.config.model_link else "onboard", "onboard")) if name != default)
        title = (f"{plan.run_id}: {len(records)} episodes, {plan.policies['uav']}/{plan.policies['ugv']} policies, "
                 f"comm {plan.config.comm.name}{sensing}, {where}")
        console.print(results_table(by_difficulty(records), title=title))
        line = usage_line(records, plan)
        if line is not None:
            console.print(line, highlight=False)
    if path.exists():
        console.print(f"results: {path}", highlight=False)
    elif records:
        console.print(f"results: {len(records)} episodes acknowledged by the run's evaluator, stored where it runs "
                      f"(not in {path.parent})", highlight=False)
    else:
        console.print(f"results: none stored (no episode finished), so no {path}", highlight=False)
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
    return records


def _recording_summary(console: Console, recording: Recording) -> None:
    """What the recorder wrote and lost (its ``recorder.json``), and how to open one."""
    from agos.deploy.recording.recorder import STATUS_FILE

    try:
        status = json.loads((recording.out_dir / STATUS_FILE).read_text())
    except (OSError, ValueError):
        console.print(f"[yellow]recordings: the recorder left no {STATUS_FILE} in {recording.out_dir}", highlight=False)
        return
    files = sorted(e["file"] for e in status.get("episodes", {}).values())
    dropped = sum(status.get("dropped_by_queue", {}).values()) + status.get("not_written", 0)
    console.print(f"recordings: {len(files)} episode{'' if len(files) == 1 else 's'} in {recording.out_dir}"
                  + (f"; the recorder fell behind and dropped {dropped} visualisation samples" if dropped else ""),
                  highlight=False)
    if files and files[0].endswith(".mcap"):
        console.print(f"look at one in Foxglove (File > Open local file): {recording.out_dir / files[0]}", highlight=False)
    elif files:
        console.print(f"look at one: agos view {recording.out_dir / files[0]}", highlight=False)
