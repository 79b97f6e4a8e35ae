"""The control plane at scale: one orchestrator, one evaluator and one router against N world workers.

Started here, as a deployment starts them by hand (docs/DEPLOY.md): ``agos router``, ``agos evaluator``
and the orchestrator as ``agos eval --connect`` (the real processes, unchanged), and N *simulated*
world workers. A simulated worker is :class:`~agos.world.sim.worker.WorldWorker` itself with one
method replaced: ``serve`` (its liveliness token, presence file, manifest watch, job requests, the
1 s back-off, give-backs, the end of the run) and ``submit`` (the record published until its ack) are
the real code, and so are the worker's slot (``WorkerSlot``, declared once for its session: the
action and ack subscriptions, the agents' ``ready`` watch, the slot's liveliness token; no key names an
episode, runtime/keys.py), each episode's ``BusDecisionSource`` on it and ``BusSink`` (step events on
the reliable and the lossy stream). Only ``run_episode`` renders nothing and asks no agent:
it announces the episode started, publishes one step event every ``--decision-s`` for ``--episode-s``
and submits a valid ``finished`` record of ``--record-decisions`` decisions a role (step log, ledger,
the run's configuration and provenance), which the evaluator checks and stores like any other.

Each simulated worker has its own zenoh session, as a world worker process has: the router sees N
clients, N liveliness tokens, N job queries at a time. The workers are threads, ``--hosts``
processes of them (default one per 250 workers), because 1,000 Python processes of ~60 MB do not fit
a 2-core machine; a session costs its host process 0.12-0.18 MB and the router 0.04-0.06 MB (measured
here). What that costs in realism: the simulated workers share the machine's cores with the
processes measured (their CPU is in the tables), they share a GIL per host (a late reply to a job
query can be a busy host, so the lease latency is an upper bound), all traffic is loopback TCP, and
nothing of the agents' path (observations, actions, coordination state) is sent: bench_runtime.py
and bench_mesh.py measure that.

Per N: lease latency (a job request's round trip when it was granted an episode, measured in the
workers; the first lease of each worker, the run-start burst, apart), records stored per second
(rows of the run's ``results.sqlite`` counted every 0.5 s, between 10 % and 90 % of the episodes
stored), lost episodes (in the split, not stored when ``agos eval`` ended), the CPU (cores) and RSS
of the orchestrator, the evaluator, the router and the worker hosts (``/proc``), the machine's load
from processes outside the bench, and what saturates. Goals at N = 1,000: lease p99 <= 1 s, >= 200
records/s stored with none lost, the orchestrator and the evaluator each <= 1 core.

    .venv/bin/python bench/bench_control_plane.py                      # N = 10, 100, 1000
    .venv/bin/python bench/bench_control_plane.py --workers 1000 --episodes-per-worker 8
    .venv/bin/python bench/bench_control_plane.py --quick              # N = 5 (make bench, its test)
    .venv/bin/python bench/bench_control_plane.py --soak               # N = 20, 20,000 episodes
    .venv/bin/python bench/bench_control_plane.py --soak --quick       # N = 20, 2,000 episodes (make bench)

Prints one line per N (``control plane N=1000: lease p50 12 ms p99 340 ms, 250 records/s, lost 0``),
then the tables, then per N what the router's zenoh log says of the sessions (``router sessions N=...``:
opened, reopened, closed during the run (before its last 0.5 s) and why, job queries
unanswered in time, late replies dropped) and the orchestrator's re-leases by why. ``--json``: also one
machine-readable line per figure (bench/figures.py).

``--soak``: does the control plane's cost per episode stay flat over a long run through one router
(issue 38)? N = 20 workers, 1,000 episodes each (``--quick``: 100) of ``SOAK_EPISODE_S`` with a step
event every ``SOAK_DECISION_S``. The run is cut in quarters by stored records (the first from the
first stored record, so start-up is left out); per quarter it prints the CPU per stored record (ms)
of the router, the orchestrator, the evaluator (and the worker hosts, for information) and the
router's RSS at the quarter's end. Goals: each CPU figure's last quarter <= 1.2x its first; the
router's RSS grows <= 10 % from the first quarter's end to the last's. PASS/FAIL per goal; the exit
status is 1 when one is missed. Any other run that stored ``QUARTERS_MIN_RECORDS`` (1,000) records is
shown by quarter too, its goals printed (no figures, no effect on the exit status).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import re
import signal
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from figures import Figures
from rich.console import Console
from rich.table import Table

AGOS = [sys.executable, "-m", "agos.deploy.cli"]
TOWN = "grid-s7"
WORKERS_PER_HOST = 250
POLL_S = 0.5
GOAL_LEASE_P99_S = 1.0
GOAL_RECORDS_PER_S = 200.0
GOAL_CORES = 1.0
RUN_LIMIT_S = 600.0
"""``agos eval`` still running this long after its start is interrupted (its unstored episodes are lost;
``--limit-s``)."""
TICK = os.sysconf("SC_CLK_TCK")
SOAK_WORKERS = 20
SOAK_EPISODES_PER_WORKER = 1000
"""``--soak``: 20,000 episodes; ``--soak --quick``: ``SOAK_QUICK_EPISODES_PER_WORKER`` a worker (2,000)."""
SOAK_QUICK_EPISODES_PER_WORKER = 100
SOAK_EPISODE_S = 0.2
SOAK_DECISION_S = 0.1
SOAK_LIMIT_S = 3600.0
SOAK_ROLES = ("router", "orchestrator", "evaluator")
"""The processes whose CPU per stored record must stay flat (the worker hosts' is printed beside them)."""
GOAL_SOAK_CPU_RATIO = 1.2
GOAL_SOAK_RSS_GROWTH = 0.10
QUARTERS_MIN_RECORDS = 1000
"""A run without ``--soak`` that stored this many records is also shown by quarter (its goals printed)."""
ROUTER_ZENOH_LOG = ("warn,zenoh_transport::unicast::manager=debug,zenoh_transport::unicast::universal::transport=debug,"
                    "zenoh_transport::unicast::universal::link=debug")
"""The router's zenoh log (``RUST_LOG``): its warnings, and one line each when a client's transport (its
session) opens, fails and closes (zenoh logs those at debug; nothing per message)."""
ROUTER_WITH_ZENOH_LOG = ("import sys, zenoh; zenoh.try_init_log_from_env(); from agos.deploy.cli import main; "
                         "sys.exit(main(sys.argv[1:]))")
"""``agos router`` with zenoh's own log on (it is off unless the process asks for it)."""


# --------------------------------------------------------------------------------------------------
# The simulated world workers (run inside a worker host process: ``--host FILE``)
# --------------------------------------------------------------------------------------------------

@dataclass
class HostPlan:
    """What one worker host runs (written by the bench as JSON, read by ``--host``)."""

    endpoint: str
    run_id: str
    worker_ids: list[str]
    episode_s: float
    decision_s: float
    record_decisions: int
    out: str
    nice: int = 0
    """Scheduling niceness of the host (``--workers-nice``): below the measured processes."""


def host_main(plan_path: Path) -> int:
    """Open one session per worker, run each worker's real ``serve`` loop on a thread until the run is
    over (or SIGTERM), then write the host's figures to the plan's ``out`` as JSON."""
    plan = HostPlan(**json.loads(plan_path.read_text()))
    os.nice(plan.nice)  # on a cluster the workers have cores of their own: here they yield to the measured processes
    logging.basicConfig(level=logging.WARNING, format=f"%(asctime)s host[{os.getpid()}] %(levelname)s %(name)s: %(message)s")
    counts = _WarningCounts()
    logging.getLogger("agos").addHandler(counts)

    from agos.runtime.process import StopFlag
    from agos.runtime.settings import AgosConfig

    stop = StopFlag()
    signal.signal(signal.SIGTERM, stop.set)
    signal.signal(signal.SIGINT, stop.set)
    cfg = AgosConfig()
    cfg = cfg.model_copy(update={"run": cfg.run.model_copy(update={"run_id": plan.run_id})})
    sim = _sim_worker_class()
    rss_before = _rss_mb()
    workers, failed = [], 0
    opened = time.monotonic()
    for worker_id in plan.worker_ids:
        try:
            bus = TimedBus.connect(plan.endpoint, plan.run_id, connect_timeout_s=30.0)
        except Exception as exc:  # counted and reported: a router refusing sessions is a finding
            failed += 1
            print(f"host {os.getpid()}: session for {worker_id} refused: {exc}", file=sys.stderr, flush=True)
            continue
        workers.append(sim(cfg, bus, stop, worker_id, plan))
    threads = [threading.Thread(target=w.serve_counted, name=w.worker_id, daemon=True) for w in workers]
    for t in threads:
        t.start()
    print(f"ready {len(workers)} {failed} {time.monotonic() - opened:.2f} {_rss_mb() - rss_before:.1f}", flush=True)
    for t in threads:
        while t.is_alive():
            t.join(0.5)
    leases = [lease for w in workers for lease in w.bus.leases]
    refused = [lat for w in workers for lat in w.bus.refused]
    usage = os.times()
    Path(plan.out).write_text(json.dumps({
        "workers": len(workers), "failed_sessions": failed, "leases": leases, "none_replies": refused,
        "episodes": sum(w.played for w in workers), "acked": sum(w.acked for w in workers),
        "unacked": sum(w.unacked for w in workers), "resubmits": counts.resubmits, "warnings": counts.other,
        "crashed": sum(w.crashed for w in workers),
        "cpu_s": usage.user + usage.system, "peak_rss_mb": _peak_rss_mb(),
    }))
    for w in workers:
        w.close()
    return 0


class _WarningCounts(logging.Handler):
    """Counts the workers' record resubmissions (``no ack ... resubmitting``) and other warnings."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.resubmits = self.other = 0

    def emit(self, record: logging.LogRecord) -> None:
        if "resubmitting" in record.getMessage():
            self.resubmits += 1
        else:
            self.other += 1


def _rss_mb() -> float:
    got = proc_cpu_rss(os.getpid())
    return got[1] if got else 0.0


def _peak_rss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _bus_class() -> type:
    from agos.runtime.bus import ZenohBus
    from agos.runtime.codec import DecodeError, decode
    from agos.runtime.schemas import JobGrant

    class _TimedBus(ZenohBus):
        """A worker's own zenoh session that times its job requests: (wall time sent, round trip s,
        first lease of this worker) for each granted one, the round trip of each refused one."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.leases: list[tuple[float, float, bool]] = []
            self.refused: list[float] = []
            self.jobs_key = ""
            """The run's job queryable (runtime/keys.py): the requests timed."""

        def request(self, key: str, message: Any, timeout_s: float) -> list[bytes]:
            if key != self.jobs_key:
                return super().request(key, message, timeout_s)
            sent, started = time.time(), time.perf_counter()
            replies = super().request(key, message, timeout_s)
            took = time.perf_counter() - started
            granted = False
            for payload in replies:
                try:
                    grant = decode(payload)
                except DecodeError:
                    continue
                granted = granted or (isinstance(grant, JobGrant) and grant.episode is not None)
            if granted:
                self.leases.append((sent, took, not self.leases))
            elif replies:
                self.refused.append(took)
            return replies

    return _TimedBus


class TimedBus:
    """Made on first use inside a host (importing zenoh in the bench's own process is not needed)."""

    _cls: Any = None

    @classmethod
    def connect(cls, endpoint: str, run_id: str, *, connect_timeout_s: float) -> Any:
        from agos.runtime import keys

        if cls._cls is None:
            cls._cls = _bus_class()
        bus = cls._cls.connect(endpoint, connect_timeout_s=connect_timeout_s)
        bus.jobs_key = keys.jobs(run_id)
        return bus


def _sim_worker_class() -> type:
    from agos.runtime import keys
    from agos.runtime.codec import encode
    from agos.runtime.episode_config import read_config
    from agos.runtime.provenance import provenance
    from agos.runtime.schemas import (
        CandidateOutcome,
        EpisodeRecord,
        EpisodeSpec,
        EpisodeStarted,
        JobGrant,
        LedgerEntry,
        LinkStats,
        LoggedStep,
        Pose,
        Role,
        StepEvent,
    )
    from agos.world.sim import worker as world_worker
    from agos.world.sim.worker import BusDecisionSource, WorldWorker

    # A worker process writes its presence file once (runtime/health.py, a temporary file named by its
    # pid); here many workers share a process, so they write it one at a time.
    announce, announcing = world_worker.announce, threading.Lock()

    def announce_once_at_a_time(*args: Any) -> None:
        with announcing:
            announce(*args)

    world_worker.announce = announce_once_at_a_time  # type: ignore[assignment]

    class SimWorker(WorldWorker):
        """A world worker that plays no episode: the lease, the episode's declarations, its step events
        and its record are the real worker's; the simulation is a sleep."""

        def __init__(self, cfg: Any, bus: Any, stop: Any, worker_id: str, plan: HostPlan) -> None:
            super().__init__(cfg, bus, stop, worker_id)
            self.plan = plan
            self.played = self.acked = self.unacked = 0
            self.crashed = False

        def serve_counted(self) -> None:
            try:
                self.serve()
            except Exception:  # logged and counted; its session ends, as a dead process's
                self.crashed = True
                logging.getLogger("agos.world").exception("simulated worker %s crashed", self.worker_id)
                self.bus.close()

        def close(self) -> None:
            self.bus.close()

        def run_episode(self, spec: EpisodeSpec, grant: JobGrant) -> None:
            # As WorldWorker.run_episode: the slot (self.slot) and the sink (self.sink) were declared once
            # for the worker's session; an episode declares nothing and forgets nothing.
            started = time.monotonic()
            config = read_config(grant.config, where="job grant")
            started_msg = encode(EpisodeStarted(run_id=self.run_id, episode_id=spec.episode_id, difficulty=spec.difficulty,
                                                worker_id=self.worker_id, town_id=spec.town.town_id,
                                                asset_sha256=spec.asset_sha256))
            self.bus.publish(self.sink.events_key, started_msg)
            self.bus.publish_viz(self.sink.viz_events_key, started_msg)
            self.bus.publish_viz(keys.viz_spec(self.run_id, self.worker_id), spec)
            source = BusDecisionSource(self.slot, spec.episode_id, timeout_s=config.decision_timeout_s, stop=self.stop,
                                       agent_wait_s=self.cfg.run.agent_wait_s, frames=self.frames,
                                       attempt=grant.attempt, rejections=self.rejections)
            steps = max(1, round(self.plan.episode_s / self.plan.decision_s)) if self.plan.decision_s > 0 else 0
            wait_s = self.plan.episode_s / max(1, steps)
            try:
                for step in range(steps):
                    if self.stop.wait(wait_s):
                        return  # interrupted: never submitted, as a real worker
                    role: Role = "uav" if step % 2 == 0 else "ugv"
                    self.sink.step(StepEvent(run_id=self.run_id, episode_id=spec.episode_id, role=role,
                                             decision_index=step // 2 + 1, episode_step=step + 1, sim_time_s=2.0 * step,
                                             requested=None, applied="WAIT",
                                             pose_after=Pose(position_world_m=(0.0, 0.0, 0.0), yaw_rad=0.0)))
                if steps == 0 and self.stop.wait(self.plan.episode_s):
                    return
            finally:
                source.close()
            record = synthetic_record(self.run_id, spec, self.worker_id, config, self.plan.record_decisions,
                                      time.monotonic() - started)
            self.played += 1
            self.bus.publish(keys.viz_result(self.run_id, self.worker_id), record)
            if self.submit(record):
                self.acked += 1
            else:
                self.unacked += 1

    def synthetic_record(run_id: str, spec: EpisodeSpec, worker_id: str, config: Any, decisions: int,
                         wall_s: float) -> EpisodeRecord:
        """A ``finished`` record as a played episode's (``decisions`` a role, its step log and ledger),
        valid for the evaluator: this run, episode and lease holder, finite numbers."""
        seed = spec.seed
        success = seed % 3 != 0
        steps = [LoggedStep(role=role, decision_index=i + 1, sim_time_s=round(4.0 * i + (role == "ugv"), 3),
                            applied="MOVE_TO_UAV_WAYPOINT" if role == "uav" else "MOVE_TO_ROAD_WAYPOINT",
                            position_world_m=(round(1.5 * i - 60.0, 3), round(0.7 * i + 20.0, 3)),
                            road_path_world_m=[] if role == "uav" else [(round(1.5 * i - 61.0, 3), 20.5)])
                 for i in range(decisions) for role in ("uav", "ugv")]
        ledger = [LedgerEntry(seq=i + 1, kind="sync", sender=("uav", "ugv")[i % 2], receiver=("ugv", "uav")[i % 2],
                              sent_s=4.0 * i, size_bytes=92, delivered=True, arrive_s=4.0 * i, delay_s=0.0)
                  for i in range(decisions)]
        return EpisodeRecord(
            run_id=run_id, episode_id=spec.episode_id, difficulty=spec.difficulty, status="finished",
            termination="confirmed" if success else "budget_exhausted", success=success, ground_observed=success,
            n_confirm=int(success), ugv_path_length_m=120.5, shortest_path_length_m=98.25, final_distance_m=4.5,
            uav_budget=config.decision_budget or spec.decision_budget, uav_first_visible_step=3,
            candidates=[CandidateOutcome(candidate_id="C001", cell="B2", center_world_m=(10.0, 12.0),
                                         status="confirmed" if success else "pending", distance_to_polygon_m=0.0,
                                         center_error_m=2.5)],
            decisions_uav=decisions, decisions_ugv=decisions, sim_time_s=4.0 * decisions, wall_time_s=round(wall_s, 3),
            worker_id=worker_id, town_id=spec.town.town_id, asset_sha256=spec.asset_sha256, seed=seed,
            renderer=config.renderer, comm_profile=config.comm.name, timing_mode=config.timing_mode,
            link=LinkStats(profile=config.comm.name, sent=decisions, delivered=decisions, dropped={}, delivery_rate=1.0,
                           mean_delay_s=0.0, max_delay_s=0.0, bytes_sent=92 * decisions,
                           mean_info_age_s={"uav": 4.0, "ugv": 4.0}, candidates_delivered=1, candidates_lost=0),
            ledger=ledger, tools=config.tools.model_dump(), step_log=steps, config=config.model_dump(mode="json"),
            config_hash=config.config_hash(), provenance=provenance())

    return SimWorker


# --------------------------------------------------------------------------------------------------
# The bench: processes, monitoring, figures
# --------------------------------------------------------------------------------------------------

def synthetic_split(path: Path, n: int) -> Path:
    """``n`` episodes on grid-s7 that pass ``agos eval``'s checks of a split (real waypoints of the town,
    a target the flat look draws); nobody plays them, so they are not sampled by rendering (seconds
    instead of minutes). Ids ``cp-<difficulty>-<k>``."""
    from agos.runtime.codec import to_json
    from agos.runtime.schemas import Difficulty, EpisodeSpec, VehicleSpec
    from agos.world.episodes.sampling import town_ref
    from agos.world.towns.asset import open_town

    town = open_town(TOWN)
    uav = sorted(town.uav_grid.nodes)
    anchors = sorted(town.roads.anchors)
    lines = []
    for k in range(n):
        difficulties: tuple[Difficulty, ...] = ("easy", "mid", "hard")
        difficulty = difficulties[k % 3]
        active = [uav[(k + j) % len(uav)] for j in range(6)]
        spec = EpisodeSpec(
            episode_id=f"cp-{difficulty}-{k:05d}", town=town_ref(town), asset_sha256=town.sha256, difficulty=difficulty,
            region_world_m=(-50.0, -50.0, 50.0, 50.0),
            target=VehicleSpec(model="sedan", colour="red", position_world_m=(10.0, 12.0, 0.0), yaw_rad=0.0),
            uav_start_waypoint=active[0], ugv_start_waypoint=town.roads.anchor_id(anchors[k % len(anchors)]),
            active_uav_waypoints=active, seed=1000 + k)
        lines.append(to_json(spec))
    path.write_bytes(b"\n".join(lines) + b"\n")
    return path


def proc_cpu_rss(pid: int) -> tuple[float, float] | None:
    """(CPU seconds, RSS MB) of a live process from /proc; None when it is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()
    cpu = (int(fields[11]) + int(fields[12])) / TICK
    rss = next((int(line.split()[1]) / 1024 for line in status.splitlines() if line.startswith("VmRSS:")), 0.0)
    return cpu, rss


def machine_busy_s() -> float:
    """CPU seconds the machine spent busy so far (user, nice, system, irq, softirq; /proc/stat)."""
    fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    user, nice, system, _idle, _iowait, irq, softirq = (fields + [0] * 7)[:7]
    return (user + nice + system + irq + softirq) / TICK


def count_rows(db: Path) -> int:
    if not db.exists():
        return 0
    try:
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=1.0) as conn:
            return int(conn.execute("SELECT count(*) FROM episodes").fetchone()[0])
    except sqlite3.Error:
        return -1  # the evaluator is creating it: try again next poll


@dataclass
class Sample:
    t: float
    rows: int
    busy_s: float
    procs: dict[str, tuple[float, float]]
    """role -> (CPU s, RSS MB), summed over the role's processes (the worker hosts are one role)."""


class Monitor:
    """Samples the processes, the machine and the store every ``POLL_S`` on a thread."""

    def __init__(self, db: Path, roles: dict[str, list[int]], census: KeyCensus | None = None) -> None:
        self.db, self.roles, self.census = db, roles, census
        self.samples: list[Sample] = []
        self._last: dict[int, float] = {}
        """pid -> CPU seconds when last seen: a process that ended keeps what it spent."""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="monitor", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        self._sample()

    def _run(self) -> None:
        while not self._stop.wait(POLL_S):
            self._sample()

    def _sample(self) -> None:
        procs: dict[str, tuple[float, float]] = {}
        for role, pids in list(self.roles.items()):
            cpu = rss = 0.0
            for pid in pids:
                got = proc_cpu_rss(pid)
                if got is not None:
                    self._last[pid] = got[0]
                    rss += got[1]
                cpu += self._last.get(pid, 0.0)
            procs[role] = (cpu, rss)
        rows = count_rows(self.db)
        if rows < 0:
            rows = self.samples[-1].rows if self.samples else 0
        self.samples.append(Sample(time.time(), rows, machine_busy_s(), procs))
        if self.census is not None:
            self.census.offer(rows)


class KeyCensus:
    """The key space a run uses, as the router sees it: every key expression the router holds a
    declaration of (subscribers, publishers, queryables, liveliness tokens: its admin space,
    ``@/<zid>/router/<kind>/<key>``) and every key a sample was put on (a subscriber on ``agos/**``),
    snapshot when the store first holds each of ``at`` records. A bounded key space gives the same
    set at every snapshot (docs/ARCHITECTURE.md §2, "Why no key names an episode")."""

    ADMIN_KINDS = ("subscriber", "publisher", "queryable", "token")

    def __init__(self, endpoint: str, at: list[int]) -> None:
        import msgspec
        import zenoh

        from agos.runtime import keys
        from agos.runtime.bus import zenoh_config

        class EpisodeField(msgspec.Struct):
            episode_id: str | None = None

        self._decoder = msgspec.msgpack.Decoder(EpisodeField)
        self._undecodable = (msgspec.ValidationError, msgspec.DecodeError)
        self.root = keys.ROOT
        self.at = sorted(at)
        self.snapshots: dict[int, set[str]] = {}
        self.put_keys: set[str] = set()
        self.episodes: set[str] = set()
        self._lock = threading.Lock()
        self.session = zenoh.open(zenoh_config(connect=[endpoint]))
        self._sub = self.session.declare_subscriber(f"{self.root}/**", self._heard)

    def _heard(self, sample) -> None:
        key = str(sample.key_expr)
        try:
            episode = self._decoder.decode(sample.payload.to_bytes()).episode_id
        except self._undecodable:
            episode = None
        with self._lock:
            self.put_keys.add(key)
            if episode:
                self.episodes.add(episode)

    def declared(self) -> set[str]:
        """The key expressions the router holds declarations of now, as ``<kind> <key>``."""
        found = set()
        for reply in self.session.get("@/*/router/**", timeout=5.0):
            if reply.ok is None:
                continue
            parts = str(reply.ok.key_expr).split("/", 4)
            if len(parts) == 5 and parts[3] in self.ADMIN_KINDS and parts[4].startswith(f"{self.root}/"):
                found.add(f"{parts[3]} {parts[4]}")
        return found

    def offer(self, rows: int) -> None:
        """Take each snapshot the store's ``rows`` have reached."""
        for at in self.at:
            if rows >= at and at not in self.snapshots:
                with self._lock:
                    put = {f"put {k}" for k in self.put_keys}
                self.snapshots[at] = self.declared() | put

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()

    def verdict(self) -> str:
        """One line: the snapshot sizes, what appeared between the first and the last, keys naming an episode."""
        if len(self.snapshots) < 2:
            return f"key census: only {len(self.snapshots)} of {len(self.at)} snapshots taken"
        first, last = self.snapshots[min(self.snapshots)], self.snapshots[max(self.snapshots)]
        naming = sorted(k for k in last if set(k.split(" ", 1)[1].split("/")) & self.episodes)
        sizes = ", ".join(f"{len(v)} after {at} records" for at, v in sorted(self.snapshots.items()))
        new = sorted(last - first)
        return (f"key census: {sizes}; {len(new)} new{': ' + ', '.join(new[:5]) if new else ''}; "
                f"{len(naming)} naming an episode{': ' + ', '.join(naming[:3]) if naming else ''}")


def percentile(values: list[float], q: float) -> float:
    """The q-quantile (0..1) by the nearest rank; nan for no values."""
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, math.ceil(q * len(ordered)) - 1))]


@dataclass
class Result:
    n: int
    episodes: int
    stored: int = 0
    lost: int = 0
    invalid: int = 0
    leases: list[tuple[float, float, bool]] = field(default_factory=list)
    none_replies: int = 0
    records_per_s: float = float("nan")
    ideal_per_s: float = float("nan")
    window_s: float = float("nan")
    cores: dict[str, float] = field(default_factory=dict)
    """Mean cores of each role over the window."""
    peak_cores: dict[str, float] = field(default_factory=dict)
    """Highest 2 s mean of each role during the run."""
    rss_mb: dict[str, float] = field(default_factory=dict)
    machine_cores: float = float("nan")
    other_cores: float = float("nan")
    sessions: int = 0
    failed_sessions: int = 0
    router_mb_per_session: float = float("nan")
    host_mb_per_worker: float = float("nan")
    resubmits: int = 0
    unacked: int = 0
    crashed: int = 0
    """Simulated workers whose thread raised (a bench fault, reported, never hidden)."""
    wall_s: float = 0.0
    eval_rc: int | None = None
    census: str = ""
    """The key census's line (``--census``), or ''."""
    sessions_log: RouterSessions | None = None
    """What the router's log says of its clients' sessions (opened, closed during the run, reopened)."""
    releases: dict[str, int] = field(default_factory=dict)
    """``re-leasing`` lines in the orchestrator's log by why: its holder's token vanished for longer than
    ``[run] reconnect_grace_s`` ("vanished"), no progress for the stuck timeout ("no progress"), other."""
    load: tuple[float, float] = (0.0, 0.0)
    samples: list[Sample] = field(default_factory=list, repr=False)
    """The monitor's samples of the run (also in its ``samples.json``)."""

    def lease_ms(self, q: float, which: str = "all") -> float:
        pick = {"all": lambda f: True, "first": lambda f: f, "later": lambda f: not f}[which]
        return 1000 * percentile([lat for _, lat, first in self.leases if pick(first)], q)

    def line(self) -> str:
        return (f"control plane N={self.n}: lease p50 {self.lease_ms(0.5):.0f} ms p99 {self.lease_ms(0.99):.0f} ms, "
                f"{self.records_per_s:.0f} records/s, lost {self.lost}")


ROLES = ("orchestrator", "evaluator", "router", "worker hosts")


@dataclass
class RouterSessions:
    """The client sessions as the router's zenoh log tells them (``ROUTER_ZENOH_LOG``)."""

    opened: int = 0
    peers: int = 0
    """Distinct client ids among the opened: a session that lost its transport and got it back keeps its id."""
    closed_in_run: int = 0
    """Transports closed during the run, before its last 0.5 s (when the run's last record is stored and
    processes start to leave): a router expiring a link, or a client gone."""
    closed: int = 0
    why: dict[str, int] = field(default_factory=dict)
    """The first words of each ``RX task failed`` (why a link ended) during the run, counted."""
    warnings: int = 0
    """zenoh WARN and ERROR lines."""
    unanswered: int = 0
    """Of those, queries the router gave up on (``Didn't receive final reply``: the queryable, here the
    orchestrator's job queryable, did not answer within the query's timeout)."""
    late_replies: int = 0
    """Of those, replies that came after their query was given up (``Route reply: Query not found``):
    dropped by the router; a job grant among them is a lease its worker never hears of."""

    @property
    def reopened(self) -> int:
        return self.opened - self.peers

    def line(self, n: int) -> str:
        why = "; ".join(f"{k}: {v}" for k, v in sorted(self.why.items(), key=lambda kv: -kv[1])[:3])
        return (f"router sessions N={n}: {self.opened} opened by {self.peers} clients ({self.reopened} reopened), "
                f"{self.closed_in_run} closed during the run{f' ({why})' if why else ''}, {self.closed} closed in all; "
                f"{self.warnings} zenoh warnings: {self.unanswered} queries unanswered in time, {self.late_replies} late "
                f"replies dropped")


_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_OPENED = re.compile(r"New transport opened between \S+ and (\w+)")
_CLOSING = re.compile(r"Closing transport with peer: (\w+)")
_FAILED = re.compile(r"RX task failed: (.*)")


def router_sessions(log_path: Path, until: float) -> RouterSessions:
    """Count the router's client sessions from its zenoh log: those opened (and by how many clients), and
    those closed before ``until`` (epoch seconds)."""
    got = RouterSessions()
    if not log_path.exists():
        return got
    seen: set[str] = set()
    for raw in log_path.read_text(errors="replace").splitlines():
        line = _ANSI.sub("", raw).strip()
        if not line[:4].isdigit() or "zenoh" not in line:
            continue
        try:
            at = datetime.fromisoformat(line.split(" ", 1)[0]).timestamp()
        except ValueError:
            continue
        if (m := _OPENED.search(line)) is not None:
            got.opened += 1
            seen.add(m.group(1))
        elif _CLOSING.search(line):
            got.closed += 1
            got.closed_in_run += at < until
        elif (m := _FAILED.search(line)) is not None and at < until:
            why = re.sub(r" on TCP link \S+ => \S+?:(?= )", ":", m.group(1).rsplit("}: ", 1)[-1].split(" at /", 1)[0])[:60]
            got.why[why] = got.why.get(why, 0) + 1
        if " WARN " in line or " ERROR " in line:
            got.warnings += 1
            got.unanswered += "Didn't receive final reply" in line
            got.late_replies += "Route reply: Query not found" in line
    got.peers = len(seen)
    return got


def start(cmd: list[str], log: Path, env: dict[str, str], **kwargs: Any) -> subprocess.Popen:
    with log.open("ab") as out:
        return subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, start_new_session=True, **kwargs)


def stop_process(proc: subprocess.Popen, timeout_s: float = 15.0) -> None:
    """SIGTERM, then SIGKILL after ``timeout_s``; waits for it."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def measure(n: int, args: argparse.Namespace, work: Path, console: Console) -> Result:
    """One control plane against ``n`` simulated workers, from start to the run's end."""
    from agos.deploy.run.launcher import free_port, wait_listening

    stamp = datetime.now(UTC).strftime("%H%M%S")
    run_id = f"cp-n{n}-{stamp}"
    here = work / run_id
    logs = here / "logs"
    logs.mkdir(parents=True)
    total = n * args.episodes_per_worker
    split = synthetic_split(here / "episodes.jsonl", total)
    runs = here / "runs"
    env = {**os.environ, "AGOS_HEALTH_DIR": str(here / "health"), "PYTHONUNBUFFERED": "1"}
    port = free_port(0)  # never 7447: a router started by hand (the README's) may want it
    endpoint = f"tcp/127.0.0.1:{port}"
    result = Result(n, total, load=os.getloadavg()[:2])
    procs: list[subprocess.Popen] = []
    hosts: list[subprocess.Popen] = []
    monitor: Monitor | None = None
    try:
        router = start([sys.executable, "-c", ROUTER_WITH_ZENOH_LOG, "router", "--listen", endpoint], logs / "router.log",
                       {**env, "RUST_LOG": ROUTER_ZENOH_LOG, "NO_COLOR": "1"})
        procs.append(router)
        if not wait_listening("127.0.0.1", port, 60.0):
            raise RuntimeError(f"agos router did not listen on {endpoint} within 60 s; see {logs / 'router.log'}")
        evaluator = start([*AGOS, "evaluator", "--connect", endpoint, "--runs-dir", str(runs), "--run", run_id],
                          logs / "evaluator.log", env)
        procs.append(evaluator)
        router_before = (proc_cpu_rss(router.pid) or (0.0, 0.0))[1]
        n_hosts = args.hosts or max(1, math.ceil(n / WORKERS_PER_HOST))
        ids = [f"sim{k:04d}" for k in range(n)]
        for h in range(n_hosts):
            plan = HostPlan(endpoint, run_id, ids[h::n_hosts], args.episode_s, args.decision_s, args.record_decisions,
                            str(here / f"host-{h}.json"), nice=args.workers_nice)
            plan_path = here / f"host-{h}.plan.json"
            plan_path.write_text(json.dumps(plan.__dict__))
            hosts.append(subprocess.Popen([sys.executable, __file__, "--host", str(plan_path)], stdout=subprocess.PIPE,
                                          stderr=(logs / f"host-{h}.log").open("ab"), env=env, text=True,
                                          start_new_session=True))
        workers_mb = 0.0
        for host in hosts:  # each says "ready <sessions> <refused> <seconds> <MB>" once its workers ask for jobs
            line = host.stdout.readline() if host.stdout else ""
            while line and not line.startswith("ready"):  # anything a library printed first
                line = host.stdout.readline() if host.stdout else ""
            parts = line.split()
            if len(parts) != 5 or parts[0] != "ready":
                raise RuntimeError(f"a worker host exited before its workers were up; see {logs}")
            result.sessions += int(parts[1])
            result.failed_sessions += int(parts[2])
            workers_mb += float(parts[4])
        result.host_mb_per_worker = workers_mb / max(1, result.sessions)
        time.sleep(2.0)  # the sessions' declarations settle at the router
        router_after = (proc_cpu_rss(router.pid) or (0.0, 0.0))[1]
        result.router_mb_per_session = (router_after - router_before) / max(1, result.sessions)
        console.print(f"N={n}: {result.sessions} worker sessions in {n_hosts} host processes"
                      + (f", [red]{result.failed_sessions} refused" if result.failed_sessions else "")
                      + f"; {total} episodes", highlight=False)
        cmd = [*AGOS, "eval", "--connect", endpoint, "--run", run_id, "--run-dir", str(runs / run_id), "--split", str(split)]
        (logs / "command.txt").write_text(" ".join(cmd) + "\n")
        t0 = time.time()
        orchestrator = start(cmd, logs / "eval.log", {**env, "COLUMNS": "120"})
        procs.append(orchestrator)
        census = KeyCensus(endpoint, args.census) if args.census else None
        monitor = Monitor(runs / run_id / "results.sqlite", {
            "orchestrator": [orchestrator.pid], "evaluator": [evaluator.pid], "router": [router.pid],
            "worker hosts": [h.pid for h in hosts]}, census)
        monitor.start()
        try:
            result.eval_rc = orchestrator.wait(args.limit_s)
        except subprocess.TimeoutExpired:
            console.print(f"[red]N={n}: agos eval still running after {args.limit_s:.0f} s: interrupted", highlight=False)
            orchestrator.send_signal(signal.SIGINT)
            result.eval_rc = orchestrator.wait(60.0)
        result.wall_s = time.time() - t0
        monitor.stop()
        if census is not None:
            result.census = census.verdict()
            census.close()
            console.print(result.census, highlight=False)
        for host in hosts:  # they end themselves once the run is over (the real workers' way)
            try:
                host.wait(30.0)
            except subprocess.TimeoutExpired:
                stop_process(host)
    finally:
        for proc in reversed(procs):
            stop_process(proc)
        for host in hosts:
            stop_process(host)
    for h in range(len(hosts)):
        path = here / f"host-{h}.json"
        if path.exists():
            data = json.loads(path.read_text())
            result.leases += [(float(t), float(lat), bool(first)) for t, lat, first in data["leases"]]
            result.none_replies += len(data["none_replies"])
            result.resubmits += data["resubmits"]
            result.unacked += data["unacked"]
            result.crashed += data["crashed"]
    samples = result.samples = monitor.samples if monitor else []
    (here / "samples.json").write_text(json.dumps([s.__dict__ for s in samples]))  # rows, CPU and RSS every 0.5 s
    # Sessions closed during the run: before the last sample that had not seen the run's last record yet
    # (the run's end, when processes close their sessions, falls in the 0.5 s after it).
    last = max((s.rows for s in samples), default=0)
    before_last = [s.t for s in samples if s.rows < last]
    result.sessions_log = router_sessions(logs / "router.log", before_last[-1] if before_last else time.time())
    eval_log = (logs / "eval.log").read_text(errors="replace") if (logs / "eval.log").exists() else ""
    for line in eval_log.splitlines():
        if line.startswith("re-leasing "):
            why = "vanished" if "token vanished" in line else "no progress" if "no progress for" in line else "other"
            result.releases[why] = result.releases.get(why, 0) + 1
    summarize(result, samples, runs / run_id, run_id, args)
    return result


def summarize(result: Result, samples: list[Sample], run_dir: Path, run_id: str, args: argparse.Namespace) -> None:
    """Stored and lost episodes from the store, rates and CPU over the steady window."""
    from agos.evaluator.store import ResultStore

    db = run_dir / "results.sqlite"
    if db.exists():
        with ResultStore(db, create=False) as store:
            records = store.records(run_id)  # every row decodes as a record of the schema
        result.stored = len(records)
        result.invalid = sum(1 for r in records if r.status != "finished" or not r.worker_id.startswith("sim"))
    result.lost = result.episodes - result.stored
    result.ideal_per_s = result.n / args.episode_s if args.episode_s > 0 else float("inf")
    if len(samples) < 2:
        return
    lo, hi = 0.1 * result.episodes, 0.9 * result.episodes
    a = next((s for s in samples if s.rows >= lo), samples[0])
    b = next((s for s in samples if s.rows >= hi), samples[-1])
    if b.t - a.t < 2 * POLL_S:  # too few samples between 10 % and 90 % (a short quick run): the whole run
        a, b = samples[0], samples[-1]
    result.window_s = b.t - a.t
    if result.window_s > 0:
        result.records_per_s = (b.rows - a.rows) / result.window_s
        for role in ROLES:
            result.cores[role] = (b.procs[role][0] - a.procs[role][0]) / result.window_s
        result.machine_cores = (b.busy_s - a.busy_s) / result.window_s
        own = sum(result.cores.values())
        result.other_cores = max(0.0, result.machine_cores - own)
    step = max(1, round(2.0 / POLL_S))
    for role in ROLES:
        peaks = [(samples[i + step].procs[role][0] - samples[i].procs[role][0]) / (samples[i + step].t - samples[i].t)
                 for i in range(len(samples) - step) if samples[i + step].t > samples[i].t]
        result.peak_cores[role] = max(peaks, default=float("nan"))
        result.rss_mb[role] = max(s.procs[role][1] for s in samples)


def saturation(r: Result, cores: int) -> str:
    """Which resource held the stored rate below the workers' ideal, as far as the figures tell."""
    share = r.records_per_s / r.ideal_per_s if r.ideal_per_s > 0 else float("nan")
    busiest = max(("orchestrator", "evaluator", "router"), key=lambda role: r.peak_cores.get(role, 0.0))
    if share >= 0.85:
        return f"none: {100 * share:.0f} % of the workers' ideal rate"
    if r.machine_cores >= 0.9 * cores:
        return (f"the machine: {r.machine_cores:.2f} of {cores} cores busy ({r.cores.get('worker hosts', 0):.2f} the simulated "
                f"workers'); busiest service: {busiest} at {r.peak_cores.get(busiest, 0):.2f} cores")
    if r.peak_cores.get(busiest, 0.0) >= 0.9:
        return f"{busiest}: {r.peak_cores[busiest]:.2f} cores at its peak (one Python thread's worth)"
    return f"below {100 * share:.0f} % of the workers' ideal rate with no core full (lease round trips, back-off)"


def report(results: list[Result], args: argparse.Namespace, console: Console, work: Path, figures: Figures) -> None:
    cores = len(os.sched_getaffinity(0))
    for r in results:
        console.print(r.line(), highlight=False)
    t = Table(title=f"Control plane: episodes of {args.episode_s:g} s, a step event every {args.decision_s:g} s, "
                    f"records of {args.record_decisions} decisions a role; {cores} cores")
    for col in ("N", "lease p50 / p99", "first lease p50 / p99", "later p99", "records/s (ideal)", "lost",
                "orchestrator cores (peak), MB", "evaluator cores (peak), MB", "router cores (peak), MB"):
        t.add_column(col, justify="right")
    for r in results:
        def cell(role: str, r: Result = r) -> str:
            return f"{r.cores.get(role, float('nan')):.2f} ({r.peak_cores.get(role, float('nan')):.2f}), " \
                   f"{r.rss_mb.get(role, float('nan')):.0f}"
        t.add_row(str(r.n), f"{r.lease_ms(0.5):.0f} / {r.lease_ms(0.99):.0f} ms",
                  f"{r.lease_ms(0.5, 'first'):.0f} / {r.lease_ms(0.99, 'first'):.0f} ms", f"{r.lease_ms(0.99, 'later'):.0f} ms",
                  f"{r.records_per_s:.1f} ({r.ideal_per_s:.0f})", str(r.lost), cell("orchestrator"), cell("evaluator"),
                  cell("router"))
    console.print(t)
    u = Table(title="Load and realism: the simulated workers share the machine with what is measured")
    for col in ("N", "sessions (refused)", "worker hosts cores, MB", "MB a session: host / router", "machine cores busy",
                "other load (cores)", "loadavg 1/5 min", "episodes stored / invalid", "record resubmits", "wall"):
        u.add_column(col, justify="right")
    for r in results:
        u.add_row(str(r.n), f"{r.sessions} ({r.failed_sessions})",
                  f"{r.cores.get('worker hosts', float('nan')):.2f}, {r.rss_mb.get('worker hosts', float('nan')):.0f}",
                  f"{r.host_mb_per_worker:.2f} / {r.router_mb_per_session:.2f}", f"{r.machine_cores:.2f} of {cores}",
                  f"{r.other_cores:.2f}", f"{r.load[0]:.1f} / {r.load[1]:.1f}", f"{r.stored} / {r.invalid}",
                  str(r.resubmits), f"{r.wall_s:.0f} s")
    console.print(u)
    for r in results:
        console.print(f"N={r.n}: saturates: {saturation(r, cores)}", highlight=False)
    for r in results:
        if r.sessions_log is not None:
            releases = ", ".join(f"{v} {k}" for k, v in sorted(r.releases.items())) or "none"
            console.print(r.sessions_log.line(r.n) + f"; orchestrator re-leases: {releases}", highlight=False)
    console.print(f"work: {work}", highlight=False)
    if args.soak:  # its own figures (soak_report)
        return
    big = results[-1]
    tag = f"control plane N={big.n}"
    figures.add(f"{tag}: lease p99", big.lease_ms(0.99), f"{big.lease_ms(0.99):.0f} ms", f"<= {1000 * GOAL_LEASE_P99_S:.0f} ms",
                big.lease_ms(0.99) <= 1000 * GOAL_LEASE_P99_S)
    figures.add(f"{tag}: lost episodes", big.lost, str(big.lost), "0", big.lost == 0)
    if big.sessions_log is not None:
        closed = big.sessions_log.closed_in_run
        figures.add(f"{tag}: sessions closed during the run", closed,
                    f"{closed} ({big.sessions_log.reopened} reopened)", "0", closed == 0)
    at_scale = big.n >= 1000
    figures.add(f"{tag}: records stored/s", big.records_per_s, f"{big.records_per_s:.0f}/s (ideal {big.ideal_per_s:.0f})",
                f">= {GOAL_RECORDS_PER_S:.0f}/s at N=1000" if at_scale else "", big.records_per_s >= GOAL_RECORDS_PER_S
                if at_scale else None)
    for role in ("orchestrator", "evaluator"):
        c = big.cores.get(role, float("nan"))
        figures.add(f"{tag}: {role} cores", c, f"{c:.2f} (peak {big.peak_cores.get(role, float('nan')):.2f})",
                    f"<= {GOAL_CORES:g}", c <= GOAL_CORES)


@dataclass
class Quarter:
    """One quarter of a run by stored records: from the sample where ``rows[0]`` were stored to the one
    where ``rows[1]`` were."""

    rows: tuple[int, int]
    seconds: float
    ms_per_record: dict[str, float]
    """role -> CPU ms of its processes per record stored in the quarter."""
    rss_mb: dict[str, float]
    """role -> RSS at the quarter's end."""


def quarters(samples: list[Sample]) -> list[Quarter]:
    """The run in four quarters of the records stored (by the monitor's row counts): the first from the
    first sample with a stored record (start-up, the split's reading and the sessions' declarations
    left out), each to the first sample at or past its share of the count. The count is the one just
    before the run's last records: the 0.5 s in which the last ones land hold the end of the run (the
    evaluator's and orchestrator's closing work, 0.2-0.3 CPU s each, a third of a quarter's in a
    2,000-episode soak), not the work per record. [] when there are too few samples to cut (a run
    that stored nearly nothing)."""
    last = max((s.rows for s in samples), default=0)
    done = next((i for i, s in enumerate(samples) if s.rows >= last), 0)
    if done > 0 and samples[done - 1].rows > 0:
        samples = samples[:done]
    end = max((s.rows for s in samples), default=0)
    a = next((s for s in samples if s.rows > 0), None)
    if a is None or end - a.rows < 8:
        return []
    out = []
    for k in range(1, 5):
        b = next(s for s in samples if s.rows >= max(a.rows + 1, math.ceil(k * end / 4)))
        if b.rows <= a.rows:
            return []
        out.append(Quarter((a.rows, b.rows), b.t - a.t,
                           {role: 1000 * (b.procs[role][0] - a.procs[role][0]) / (b.rows - a.rows) for role in ROLES},
                           {role: b.procs[role][1] for role in ROLES}))
        a = b
    return out


def soak_report(r: Result, args: argparse.Namespace, console: Console, figures: Figures) -> bool:
    """The per-quarter table and the soak's goals, PASS/FAIL each (figures only with ``--soak``); True
    when every goal is met."""
    qs = quarters(r.samples)
    title = (f"{'Soak' if args.soak else 'By quarter'}: N={r.n}, {r.episodes:,} episodes of {args.episode_s:g} s (a step "
             f"event every {args.decision_s:g} s) through one router; CPU ms per stored record by quarter of the run")
    if len(qs) < 4:
        console.print(f"[red]{title}: too few records stored to cut the run in quarters ({r.stored})", highlight=False)
        return False
    t = Table(title=title)
    for col in ("quarter", "records", "wall", "records/s", *(f"{role} ms/rec" for role in (*SOAK_ROLES, "worker hosts")),
                "RSS MB at its end: router / orchestrator / evaluator"):
        t.add_column(col, justify="right")
    for k, q in enumerate(qs, 1):
        t.add_row(f"Q{k}", f"{q.rows[0]:,}-{q.rows[1]:,}", f"{q.seconds:.0f} s", f"{(q.rows[1] - q.rows[0]) / q.seconds:.1f}"
                  if q.seconds > 0 else "-", *(f"{q.ms_per_record[role]:.2f}" for role in (*SOAK_ROLES, "worker hosts")),
                  f"{q.rss_mb['router']:.1f} / {q.rss_mb['orchestrator']:.0f} / {q.rss_mb['evaluator']:.0f}")
    console.print(t)
    g = Table(title="Soak goals: the last quarter against the first")
    for col in ("figure", "Q1", "Q4", "Q4 / Q1", "goal", "result"):
        g.add_column(col, justify="left" if col == "figure" else "right")
    ok = True
    tag = f"soak N={r.n} x {r.episodes:,} episodes"
    if not args.soak:
        figures = Figures(False)  # the goals are printed, the figures are the soak's
    first, last = qs[0], qs[-1]
    for role in SOAK_ROLES:
        ratio = last.ms_per_record[role] / first.ms_per_record[role] if first.ms_per_record[role] > 0 else float("inf")
        met = ratio <= GOAL_SOAK_CPU_RATIO
        ok &= met
        g.add_row(f"{role} CPU per record", f"{first.ms_per_record[role]:.2f} ms", f"{last.ms_per_record[role]:.2f} ms",
                  f"{ratio:.2f}x", f"<= {GOAL_SOAK_CPU_RATIO:g}x", "PASS" if met else "[red]FAIL")
        figures.add(f"{tag}: {role} CPU per record, last / first quarter", ratio,
                    f"{ratio:.2f}x ({last.ms_per_record[role]:.2f} vs {first.ms_per_record[role]:.2f} ms)",
                    f"<= {GOAL_SOAK_CPU_RATIO:g}x", met)
    growth = last.rss_mb["router"] / first.rss_mb["router"] - 1 if first.rss_mb["router"] > 0 else float("inf")
    met = growth <= GOAL_SOAK_RSS_GROWTH
    ok &= met
    g.add_row("router RSS, end of Q1 to end of Q4", f"{first.rss_mb['router']:.1f} MB", f"{last.rss_mb['router']:.1f} MB",
              f"{100 * growth:+.1f} %", f"<= +{100 * GOAL_SOAK_RSS_GROWTH:.0f} %", "PASS" if met else "[red]FAIL")
    figures.add(f"{tag}: router RSS growth, end of Q1 to end of Q4", growth,
                f"{100 * growth:+.1f} % ({first.rss_mb['router']:.1f} -> {last.rss_mb['router']:.1f} MB)",
                f"<= +{100 * GOAL_SOAK_RSS_GROWTH:.0f} %", met)
    figures.add(f"{tag}: lost episodes", r.lost, str(r.lost), "0", r.lost == 0)
    # For reading the above: the worker hosts do the same work for every record (a fixed slot, fixed
    # episodes), so their ratio shows how the machine itself drifted; the other RSS are not goals.
    hosts = last.ms_per_record["worker hosts"] / first.ms_per_record["worker hosts"] \
        if first.ms_per_record["worker hosts"] > 0 else float("nan")
    g.add_row("[dim]worker hosts CPU per record (fixed work: the machine's drift)", f"{first.ms_per_record['worker hosts']:.2f} ms",
              f"{last.ms_per_record['worker hosts']:.2f} ms", f"{hosts:.2f}x", "", "info")
    for role in ("orchestrator", "evaluator"):
        g.add_row(f"[dim]{role} RSS, end of Q1 to end of Q4", f"{first.rss_mb[role]:.0f} MB", f"{last.rss_mb[role]:.0f} MB",
                  f"{100 * (last.rss_mb[role] / first.rss_mb[role] - 1):+.0f} %" if first.rss_mb[role] > 0 else "-", "", "info")
    console.print(g)
    what = "soak" if args.soak else f"N={r.n} by quarter"
    console.print(f"{what}: {'PASS' if ok else 'FAIL'}; load average {os.getloadavg()[0]:.1f} at the end "
                  f"({r.load[0]:.1f} at the start), other load {r.other_cores:.2f} cores", highlight=False)
    return ok


def run(args: argparse.Namespace) -> int:
    console = Console(width=200)
    work = Path(tempfile.mkdtemp(prefix="agos-bench-cp-")) if args.work is None else args.work
    work.mkdir(parents=True, exist_ok=True)
    console.print(f"[bold]bench_control_plane[/]: N = {', '.join(map(str, args.workers))}; {args.episodes_per_worker} "
                  f"episodes a worker of {args.episode_s:g} s; load average {os.getloadavg()[0]:.1f} on "
                  f"{len(os.sched_getaffinity(0))} cores", highlight=False)
    results = []
    for n in args.workers:
        results.append(measure(n, args, work, console))
        if results[-1].eval_rc:
            console.print(f"[red]N={n}: agos eval exited {results[-1].eval_rc}; see {work}", highlight=False)
    figures = Figures(args.json)
    report(results, args, console, work, figures)
    soak_ok = True
    for r in results:  # by quarter wherever the run is long enough to cut; goals gate only the soak
        if args.soak or r.stored >= QUARTERS_MIN_RECORDS:
            soak_ok &= soak_report(r, args, console, figures) or not args.soak
    for r in results:
        if r.crashed:
            console.print(f"[red]N={r.n}: {r.crashed} simulated workers crashed (their host logs say why)", highlight=False)
    bad = [r for r in results if r.lost or r.invalid or r.eval_rc or r.crashed or r.failed_sessions]
    return 1 if bad or not soak_ok else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workers", type=int, action="append", help="N simulated world workers (repeat; default 10, "
                                                                       "100, 1000; --quick 5)")
    parser.add_argument("--episodes-per-worker", type=int, help="episodes in the split per worker (default 4; --quick 2)")
    parser.add_argument("--episode-s", type=float, help="seconds a simulated episode lasts (default 2; --quick 0.3; "
                                                                  f"--soak {SOAK_EPISODE_S:g})")
    parser.add_argument("--decision-s", type=float,
                        help="a step event every this many seconds of an episode (default 1, a decision at model speed; "
                             f"--soak {SOAK_DECISION_S:g}; 0: none)")
    parser.add_argument("--record-decisions", type=int, default=40, help="decisions a role in each record (default 40)")
    parser.add_argument("--hosts", type=int, help=f"worker host processes (default one per {WORKERS_PER_HOST} workers)")
    parser.add_argument("--work", type=Path, help="directory for the runs and logs (default: a new temp dir)")
    parser.add_argument("--limit-s", type=float,
                        help=f"interrupt agos eval after this long (default {RUN_LIMIT_S:.0f} s, --soak {SOAK_LIMIT_S:.0f} s); "
                             "what it did not store is lost")
    parser.add_argument("--quick", action="store_true", help="N = 5, 2 episodes a worker of 0.3 s (with --soak: "
                                                             f"{SOAK_QUICK_EPISODES_PER_WORKER} episodes a worker)")
    parser.add_argument("--soak", action="store_true",
                        help=f"N = {SOAK_WORKERS}, {SOAK_EPISODES_PER_WORKER} episodes a worker of {SOAK_EPISODE_S:g} s, a step "
                             f"event every {SOAK_DECISION_S:g} s: CPU per stored record and router RSS by quarter of the run")
    parser.add_argument("--workers-nice", type=int, default=0, metavar="N",
                        help="run the simulated workers' hosts at this niceness (default 0: they compete with the "
                             "measured processes as equals; 10: the router, orchestrator and evaluator get the cores "
                             "first, as on a cluster where the workers have their own)")
    parser.add_argument("--census", type=lambda text: [int(x) for x in text.split(",")], metavar="A,B",
                        help="snapshot the key space the router holds and the keys put on when A, then B records are "
                             "stored, and print whether it grew (a bounded key space does not)")
    parser.add_argument("--json", action="store_true", help="also print each figure as a BENCH-FIGURE line")
    parser.add_argument("--host", type=Path, help=argparse.SUPPRESS)  # internal: run one worker host
    args = parser.parse_args()
    if args.host is not None:
        return host_main(args.host)
    if args.soak:
        args.workers = args.workers or [SOAK_WORKERS]
        args.episodes_per_worker = args.episodes_per_worker or (
            SOAK_QUICK_EPISODES_PER_WORKER if args.quick else SOAK_EPISODES_PER_WORKER)
        args.episode_s = args.episode_s if args.episode_s is not None else SOAK_EPISODE_S
        args.decision_s = args.decision_s if args.decision_s is not None else SOAK_DECISION_S
        args.limit_s = args.limit_s or SOAK_LIMIT_S
        if len(args.workers) != 1:
            parser.error("--soak runs one N")
    args.workers = args.workers or ([5] if args.quick else [10, 100, 1000])
    args.episodes_per_worker = args.episodes_per_worker or (2 if args.quick else 4)
    args.episode_s = args.episode_s if args.episode_s is not None else (0.3 if args.quick else 2.0)
    args.decision_s = args.decision_s if args.decision_s is not None else 1.0
    args.limit_s = args.limit_s or RUN_LIMIT_S
    if min(args.workers) < 1 or args.episodes_per_worker < 1 or args.episode_s < 0 or args.decision_s < 0 \
            or args.record_decisions < 0:
        parser.error("--workers and --episodes-per-worker >= 1; --episode-s, --decision-s, --record-decisions >= 0")
    try:
        return run(args)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
