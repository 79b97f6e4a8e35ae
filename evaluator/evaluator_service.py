"""The evaluator process: store every episode record once, acknowledge it, report metrics.

    agos evaluator --connect tcp/HOST:PORT [--runs-dir runs]

It listens to the results of every run (``agos/*/slot/*/result``: each world worker's slot), writes
them to ``<runs_dir>/<run>/results.sqlite`` and acknowledges each on the slot's ``.../ack``. When a run's
manifest says ``finished`` it logs the run's results table. It declares its liveliness token under a
run (what ``agos eval``'s presence check asks for) at start for its configured run (``--run``; ``agos
eval`` tells the evaluator it starts), and for any other run on first hearing of it: a manifest, a lease
notice (repeated every 5 s, so one started late joins within seconds) or a record.

What it stores is checked first, because anything on an open router can publish there: the
payload must be a record of this schema version, name the run and worker its key names, use
ids that are names (never paths), hold only finite numbers, and come from the worker that the
orchestrator's newest lease notice (``agos/<run>/ctl/lease``) names as the episode's current holder; an
episode that was never leased (not in the run's split) has no holder. Anything else is refused
(runtime/rejections.py), never stored, never acknowledged.
"""

from __future__ import annotations

import logging
from pathlib import Path

from rich.console import Console

from agos.evaluator.metrics import by_difficulty
from agos.evaluator.store import ResultStore, results_path
from agos.evaluator.table import results_table
from agos.runtime import keys
from agos.runtime.bus import Bus, Inbox, ZenohBus
from agos.runtime.codec import DecodeError, decode
from agos.runtime.health import announce
from agos.runtime.process import StopFlag, install_stop_handlers, setup_logging
from agos.runtime.rejections import Rejections, non_finite_field
from agos.runtime.schemas import EpisodeRecord, LeaseNotice, ResultAck, RunManifest
from agos.runtime.settings import AgosConfig

log = logging.getLogger("agos.evaluator")


class Evaluator:
    def __init__(self, bus: Bus, runs_dir: Path) -> None:
        self.bus, self.runs_dir = bus, runs_dir
        self._stores: dict[str, ResultStore] = {}
        self._serving: set[str] = set()
        self.leases: dict[tuple[str, str], LeaseNotice] = {}
        """(run, episode) -> the newest lease notice: whose result counts."""
        self.rejections = Rejections(log)

    def serve_run(self, run_id: str) -> None:
        """Declare the evaluator's liveliness token under ``run_id`` (once)."""
        if run_id not in self._serving:
            self._serving.add(run_id)
            self.bus.declare_token(keys.live(run_id, "evaluator", "main"))

    def store(self, run_id: str) -> ResultStore:
        """The run's store, opened (and the run's evaluator liveliness token declared) on first use."""
        if run_id not in self._stores:
            self._stores[run_id] = ResultStore(results_path(self.runs_dir, run_id))
            self.serve_run(run_id)
        return self._stores[run_id]

    def handle(self, key: str, payload: bytes) -> None:
        try:
            message = decode(payload)
        except DecodeError as exc:
            self.rejections.reject(key, "unreadable", exc)
            return
        reason = self._refusal(key, message)
        if reason:
            self.rejections.reject(key, reason, f"{type(message).__name__} from {getattr(message, 'worker_id', '?')}")
        elif isinstance(message, LeaseNotice):
            # The newest notice names the holder, whatever its attempt: a resumed run counts attempts from 1
            # again, and one forged notice of a high attempt would otherwise refuse the holder's record for
            # ever. One orchestrator's notices arrive in order, and it repeats them every 5 s (each just
            # before the records it still waits for), so any other notice holds for seconds at most.
            self.leases[(message.run_id, message.episode_id)] = message
            self.serve_run(message.run_id)  # repeated every 5 s: an evaluator that missed the manifest joins here
        elif isinstance(message, EpisodeRecord):
            newly = self.store(message.run_id).add(message)
            log.info("%s %s/%s (%s, %s)", "stored" if newly else "duplicate", message.run_id, message.episode_id,
                     message.status, "success" if message.success else "failure")
            self.bus.publish(keys.result_ack(message.run_id, message.worker_id),
                             ResultAck(run_id=message.run_id, episode_id=message.episode_id, newly_stored=newly),
                             once=True)  # one key per worker slot, of many: no publisher kept (runtime/bus.py)
        elif isinstance(message, RunManifest) and message.status == "running":
            # Present for the run at once, but no file yet: a manifest alone (perhaps forged) must not
            # make a run directory look as if it held results.
            self.serve_run(message.run_id)
        elif isinstance(message, RunManifest) and message.status == "finished" and message.run_id in self._stores:
            records = self._stores[message.run_id].records(message.run_id)
            console = Console(width=100)
            with console.capture() as cap:
                console.print(results_table(by_difficulty(records), title=f"run {message.run_id}"))
            log.info("run %s finished: %d records in %s\n%s", message.run_id, len(records),
                     results_path(self.runs_dir, message.run_id), cap.get())

    def _refusal(self, key: str, message: object) -> str:
        """Why ``message`` heard on ``key`` must not be acted on ('' when it may)."""
        expected = {"result": EpisodeRecord, "lease": LeaseNotice, "manifest": RunManifest}.get(keys.leaf(key))
        if expected is None or not isinstance(message, expected):
            return "wrong message type for the key"
        try:
            about_run = keys.check_chunk(keys.run_of(key), what="run id")
            if message.run_id != about_run:
                return "names another run than its key"
            if isinstance(message, (EpisodeRecord, LeaseNotice)):
                keys.check_chunk(message.episode_id, what="episode id")
                keys.check_chunk(message.worker_id, what="worker id")
            if isinstance(message, EpisodeRecord) and message.worker_id != keys.slot_of(key):
                return "names another worker than its key"
        except ValueError:
            return "an id that is not a name"
        if non_finite_field(message):
            return "a number that is not finite"
        if isinstance(message, EpisodeRecord):
            lease = self.leases.get((message.run_id, message.episode_id))
            if lease is None:
                return "no lease known for the episode"
            if message.worker_id != lease.worker_id:
                return "not from the lease holder"
        return ""

    def close(self) -> None:
        self.rejections.log_summary()
        for store in self._stores.values():
            store.close()


def serve(bus: Bus, runs_dir: Path, stop: StopFlag, *, announce_run: str | None = None) -> int:
    """Store every run's records until stopped. ``announce_run``: declare the token under this run at
    once (its healthcheck, before the run's first message) and say so for ``agos health evaluator``."""
    evaluator = Evaluator(bus, runs_dir)
    inbox = Inbox()
    bus.subscribe(keys.result("*", "*"), inbox)
    bus.subscribe(keys.lease("*"), inbox)
    bus.subscribe(keys.manifest("*"), inbox)
    if announce_run is not None:
        evaluator.serve_run(announce_run)
        announce("evaluator", "main", announce_run)
    log.info("evaluator storing under %s", runs_dir)
    try:
        while not stop.is_set():
            sample = inbox.get(timeout_s=0.5)
            if sample is not None:
                evaluator.handle(sample.key, sample.payload)
    finally:
        evaluator.close()
    return 0


def main(cfg: AgosConfig) -> int:
    setup_logging("evaluator")
    stop = install_stop_handlers()
    with ZenohBus.from_settings(cfg.zenoh) as bus:
        return serve(bus, cfg.run.runs_dir, stop, announce_run=cfg.run.run_id)
