"""The run orchestrator: leases episodes to world workers, notices dead and stuck ones, and
tracks which episodes are stored.

* Workers ask on ``agos/<run>/ctl/jobs`` (a queryable) and get the next episode with its attempt
  number and the run's whole episode configuration (runtime/episode_config.py); ``None`` while others are still running; or
  ``run_finished``. Only a worker whose liveliness token is up gets an episode: a stray client
  asking for jobs cannot take episodes away from the workers.
* Every lease is announced on ``agos/<run>/ctl/lease`` (and again every ``LEASE_REPEAT_S``
  while it lasts): the evaluator stores a result only from the worker named there.
* A worker whose liveliness token (``agos/<run>/live/world/<id>``) vanishes and does not come back
  within ``reconnect_grace_s`` (a router restarted, or this orchestrator's own session reconnected:
  every token then vanishes and comes back), or whose episode
  shows no step event for ``stuck_after_s`` of wall time, loses its leases: those episodes go back
  to the front of the queue with attempt + 1. After ``max_attempts`` the orchestrator submits an
  infrastructure-failure record itself (``world_crashed``), so the run still ends. A lease whose
  holder's record is in is never taken back: the episode is played, and only its storage is awaited
  (the record is published again every ``LEASE_REPEAT_S``; ``agos eval`` stops a run whose records
  stay unstored, deploy/run/evaluate.py).
* An episode given back because an agent's model endpoint gave no answer (``JobRequest.outage``)
  pauses: it and every other episode wait ``infra_wait_s`` before anything is leased again (the
  endpoint is down for all of them), then it is leased again, first, as a fresh attempt. After
  ``max_infra_attempts`` such attempts the orchestrator submits an ``infra_error`` record, which no
  metric scores. These attempts do not count towards ``max_attempts``. :attr:`Orchestrator.notices`
  holds one console line per pause, infra error and recovery (``agos eval`` prints them).
* An episode is done when the evaluator's ack for it is seen, and is then never leased again;
  whatever arrives about it later (its record again, a late duplicate from a worker thought dead,
  another ack, its old lease notice) changes nothing here, and the evaluator stores nothing twice.
  So every episode ends stored once, or failed with the reason after ``max_attempts``.
* Imported town assets are served on ``agos/assets/<sha256>`` from the local asset cache.
"""

from __future__ import annotations

import logging
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Literal

import msgspec

from agos.runtime import keys
from agos.runtime.bus import Bus, Inbox, Sample
from agos.runtime.codec import DecodeError, decode, encode
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.failure_records import failure_record
from agos.runtime.health import announce
from agos.runtime.rejections import Rejections, non_finite_field
from agos.runtime.schemas import (
    EpisodeRecord,
    EpisodeSpec,
    EpisodeStarted,
    JobGrant,
    JobRequest,
    LeaseNotice,
    ResultAck,
    RunManifest,
    StepEvent,
)
from agos.runtime.settings import DEFAULTS
from agos.runtime.traces import record_usage

log = logging.getLogger("agos.orchestrator")

LEASE_REPEAT_S = 5.0
"""How often current lease notices (and records not yet acknowledged) are published again, for an
evaluator that started, or restarted, after they were first sent."""
STUCK_AFTER_S = 180.0
"""Wall time without a step event after which a leased episode counts as stuck and is leased again
(``agos eval --stuck-after``), unless its decision timeout and ``STUCK_MARGIN_S`` are longer."""
STUCK_MARGIN_S = 60.0
"""An episode counts as stuck only after its decision timeout and this much more without progress."""


def summary_of(record: EpisodeRecord) -> EpisodeRecord:
    """``record`` without its per-decision lists (step log, traces, link ledger) and configuration: what
    a stored episode still needs here (the results table, the model usage a budget totals), at about a
    hundredth of the memory. Kept whole, a campaign's records grew the orchestrator by ~52 KB an episode
    (2.3 GB after 20,000: bench/bench_control_plane.py --soak)."""
    return msgspec.structs.replace(record, usage=record_usage(record), decision_traces=[], step_log=[], ledger=[],
                                   config={})


@dataclass
class Lease:
    spec: EpisodeSpec
    worker: str
    attempt: int
    leased_at: float
    last_progress: float


class Orchestrator:
    """The leases of one run's episodes, driven by :meth:`pump`. ``episodes`` must name each episode
    once (``ValueError`` otherwise: a run waiting for two stored episodes of one id never ends)."""

    def __init__(self, bus: Bus, run_id: str, episodes: list[EpisodeSpec], *, policies: dict[str, str],
                 config: EpisodeConfig | None = None,
                 stuck_after_s: float = STUCK_AFTER_S, max_attempts: int = 3, already_stored: set[str] | None = None,
                 resumed: bool = False, max_infra_attempts: int = DEFAULTS.run.max_infra_attempts,
                 infra_wait_s: float = DEFAULTS.run.infra_wait_s, reconnect_grace_s: float = DEFAULTS.run.reconnect_grace_s,
                 clock=time.monotonic) -> None:
        self.bus, self.run_id = bus, run_id
        self.policies = policies
        self.config = config or EpisodeConfig()
        self._config_map = self.config.model_dump(mode="json")  # sent whole in every grant
        # A world waiting for a decision shows no progress for up to the decision timeout (a person may
        # be given hours: docs/HUMAN.md), so it is stuck only after that and a margin.
        stuck_after_s = max(stuck_after_s, self.config.decision_timeout_s + STUCK_MARGIN_S)
        self.stuck_after_s, self.max_attempts, self.resumed = stuck_after_s, max_attempts, resumed
        self.max_infra_attempts, self.infra_wait_s = max_infra_attempts, infra_wait_s
        self._clock = clock
        done = already_stored or set()
        self.total = len(episodes)
        self.episode_ids = {e.episode_id for e in episodes}
        if len(self.episode_ids) != self.total:
            twice = next(e for e, n in Counter(e.episode_id for e in episodes).items() if n > 1)
            raise ValueError(f"episode {twice} twice in the run's episodes: every episode needs its own id")
        self.stored: set[str] = {e.episode_id for e in episodes if e.episode_id in done}
        self.already = len(self.stored)
        self.pending: deque[tuple[EpisodeSpec, int]] = deque((e, 1) for e in episodes if e.episode_id not in done)
        self.leases: dict[str, Lease] = {}
        self._newly: list[EpisodeRecord] = []
        """Records acknowledged since :meth:`pump` last returned."""
        self.regrants = 0
        """Grants sent again: the first never reached its worker (a reply lost on a busy router)."""
        self.records: dict[str, EpisodeRecord] = {}
        """The lease holders' records: whole until acknowledged, then their summary (:func:`summary_of`)."""
        self.releases = 0
        self.decisions = 0
        """Step events seen (decisions applied, both roles), for the progress bar."""
        self.first_lease_s: float | None = None
        self.last_stored_s: float | None = None
        self.live_workers: set[str] = set()
        """World workers whose liveliness token is up: the only ones that get episodes."""
        self.reconnect_grace_s = reconnect_grace_s
        self.vanished: dict[str, float] = {}
        """World workers whose token vanished -> when (clock): their leases are kept ``reconnect_grace_s``."""
        self.gave_up: dict[str, EpisodeRecord] = {}
        """Infrastructure-failure records this orchestrator submitted, until acknowledged."""
        self.outages: Counter[str] = Counter()
        """Episode -> attempts it lost to a model endpoint outage."""
        self.paused: dict[str, tuple[EpisodeSpec, int]] = {}
        """Episodes given back for an outage, waiting to be leased again: spec and next attempt, in order."""
        self.hold_until = 0.0
        """Nothing is leased before this (clock time): the wait after the latest outage."""
        self.outage_line: str | None = None
        """The latest outage's line while it lasts (None once an episode decided again after it)."""
        self.notices: list[str] = []
        """Console lines about outages, taken and printed by ``agos eval`` (deploy/run/evaluate.py)."""
        self.rejections = Rejections(log)
        self.may_lease: Callable[[int], bool] | None = None
        """A gate asked before each lease with the episodes in flight (leased, no record yet); False
        holds the episode back (``agos eval``'s caps, deploy/run/budget.py). None: always lease."""
        self._repeat_at = clock() + LEASE_REPEAT_S
        self.created_utc = datetime.now(UTC).isoformat(timespec="seconds")
        self._queries = bus.serve(keys.jobs(run_id))
        # Imported towns travel by hash: workers without the file ask agos/assets/<sha256>.
        self._asset_queries = bus.serve(keys.asset("*"))
        self._inbox = Inbox()
        bus.subscribe(keys.result(run_id, "*"), self._inbox)  # every worker's slot
        bus.subscribe(keys.result_ack(run_id, "*"), self._inbox)
        bus.subscribe(keys.events(run_id, "*"), self._inbox)
        self._live = Inbox()
        bus.watch_liveliness(keys.live(run_id, "world", "*"), self._live)
        bus.declare_token(keys.live(run_id, "orchestrator", "main"))
        announce("orchestrator", "main", run_id)

    def episodes_per_minute(self, fresh: int) -> float | None:
        """Throughput from the first lease to the last stored episode (process start-up excluded)."""
        if self.first_lease_s is None or self.last_stored_s is None or self.last_stored_s <= self.first_lease_s:
            return None
        return 60.0 * fresh / (self.last_stored_s - self.first_lease_s)

    @property
    def finished(self) -> bool:
        return len(self.stored) >= self.total

    def publish_manifest(self, status: Literal["running", "finished", "interrupted"]) -> None:
        self.bus.publish(keys.manifest(self.run_id), RunManifest(
            run_id=self.run_id, status=status, policies=self.policies, n_episodes=self.total,
            comm_profile=self.config.comm.name, timing_mode=self.config.timing_mode, config_hash=self.config.config_hash(),
            created_utc=self.created_utc, resumed=self.resumed))

    def pump(self, timeout_s: float) -> list[EpisodeRecord]:
        """Answer job and asset queries, read results, acks, events and liveliness for up to
        ``timeout_s``; return the records whose storage was acknowledged in this call."""
        self._answer_queries()
        sample = self._inbox.get(timeout_s)
        self._read([sample] if sample else [])
        now = self._clock()
        for s in self._live.drain():
            worker = keys.live_of(s.key).ident
            if s.payload == b"+":
                self.live_workers.add(worker)
                if self.vanished.pop(worker, None) is not None:
                    log.info("world worker %s is back; it keeps its leases", worker)
            else:
                self.live_workers.discard(worker)
                self.vanished[worker] = now
        for worker, since in list(self.vanished.items()):
            if now - since >= self.reconnect_grace_s:
                del self.vanished[worker]
                self._release_worker(worker, f"its liveliness token vanished (not back within "
                                             f"{self.reconnect_grace_s:g} s)")
        for episode_id, lease in list(self.leases.items()):
            if now - lease.last_progress > self.stuck_after_s and episode_id not in self.records:
                self._release(episode_id, f"no progress for {self.stuck_after_s:.0f} s on {lease.worker}")
        if now >= self._repeat_at:
            self._repeat_at = now + LEASE_REPEAT_S
            for lease in self.leases.values():
                self._announce(lease)
            # Every record not yet acknowledged goes out again: this orchestrator's failure records, and
            # a holder's record whose ack came first (a small ack can overtake a large record on another
            # key) and was refused above, so the evaluator acknowledges it once more, in order.
            unacked = {e: self.records[e] for e in self.unacknowledged()} | self.gave_up
            for record in unacked.values():
                self.bus.publish(keys.result(self.run_id, record.worker_id), record, once=True)
        self._answer_queries()
        newly, self._newly = self._newly, []
        return newly

    def _read(self, samples: list[Sample]) -> None:
        """Read results, acks and events (``samples`` and whatever else the inbox holds); records whose
        storage is acknowledged go to ``self._newly``, for :meth:`pump` to return."""
        now = self._clock()
        for s in samples + self._inbox.drain():
            if s.key.endswith("/events"):
                try:
                    event = decode(s.payload)
                except DecodeError as exc:
                    self.rejections.reject(s.key, "unreadable", exc)
                    continue
                if not isinstance(event, (StepEvent, EpisodeStarted)) or event.episode_id not in self.episode_ids:
                    self.rejections.reject(s.key, "not an event of an episode of this run")
                    continue
                lease = self.leases.get(event.episode_id)
                if lease is not None and lease.worker != keys.slot_of(s.key):
                    self.rejections.reject(s.key, "not from the episode's lease holder")
                    continue
                if lease is not None:
                    lease.last_progress = now
                self.decisions += isinstance(event, StepEvent)
                if isinstance(event, StepEvent) and self.outage_line is not None and lease is not None \
                        and lease.leased_at >= self.hold_until:
                    self._recovered(event.episode_id, lease.attempt)
                continue
            try:
                message = decode(s.payload)
            except DecodeError as exc:
                self.rejections.reject(s.key, "unreadable", exc)
                continue
            # A message counts only for an episode of this run's split, a record only on the slot of the
            # worker it names: anything else on these keys is a mistake or a forgery.
            if getattr(message, "run_id", None) != self.run_id or getattr(message, "episode_id", None) \
                    not in self.episode_ids:
                self.rejections.reject(s.key, "not an episode of this run")
                continue
            if isinstance(message, EpisodeRecord):
                if message.worker_id != keys.slot_of(s.key):
                    self.rejections.reject(s.key, "names another worker than its key")
                elif not self._from_holder(message):
                    self.rejections.reject(s.key, "not from the lease holder")
                elif non_finite_field(message):  # the evaluator refuses it too: it must not count here
                    self.rejections.reject(s.key, "a number that is not finite")
                else:
                    self.records.setdefault(message.episode_id, message)
            elif isinstance(message, ResultAck) and message.episode_id not in self.records:
                # The evaluator acknowledges only a record it stored, and it stores only the holder's; an
                # honest ack overtakes its (larger) record now and then, so this is not a hostile sign: the
                # holder's record is published again (republish_unacknowledged) and acknowledged again.
                log.debug("ack of %s before its record; waiting for the record", message.episode_id)
            elif isinstance(message, ResultAck) and message.episode_id not in self.stored:
                self.stored.add(message.episode_id)
                self.last_stored_s = now
                self.leases.pop(message.episode_id, None)
                self.gave_up.pop(message.episode_id, None)
                if message.episode_id in self.records:
                    self._newly.append(self.records[message.episode_id])
                    self.records[message.episode_id] = summary_of(self.records[message.episode_id])

    def in_flight(self) -> int:
        """Episodes leased whose record has not come in yet."""
        return sum(1 for e in self.leases if e not in self.records)

    def unacknowledged(self) -> list[str]:
        """Episodes whose record (from the lease holder) was seen but whose storage nobody acknowledged."""
        return sorted(e for e in self.records if e not in self.stored)

    def _from_holder(self, record: EpisodeRecord) -> bool:
        lease = self.leases.get(record.episode_id)
        given_up = self.gave_up.get(record.episode_id)
        return (lease is not None and record.worker_id == lease.worker) or record == given_up

    def _announce(self, lease: Lease) -> None:
        self.bus.publish(keys.lease(self.run_id), LeaseNotice(
            run_id=self.run_id, episode_id=lease.spec.episode_id, worker_id=lease.worker, attempt=lease.attempt))

    def _release_worker(self, worker: str, why: str) -> None:
        """Take back ``worker``'s leases but those whose record is in (played: only storage is awaited)."""
        for episode_id, lease in list(self.leases.items()):
            if lease.worker == worker and episode_id not in self.records:
                self._release(episode_id, f"worker {worker}: {why}")

    def _release(self, episode_id: str, why: str, status: Literal["world_crashed", "agent_crashed"] = "world_crashed") -> None:
        lease = self.leases.pop(episode_id)
        self.releases += 1
        if lease.attempt - self.outages[episode_id] >= self.max_attempts:  # outages are counted apart
            log.error("%s failed %d times (%s); recording an infrastructure failure", episode_id, lease.attempt, why)
            # Under the last holder's name: the evaluator stores a result only from the lease holder.
            record = self.gave_up[episode_id] = failure_record(
                self.run_id, lease.spec, status=status, worker_id=lease.worker,
                error=f"gave up after {lease.attempt} attempts: {why}", config=self.config)
            self.bus.publish(keys.result(self.run_id, lease.worker), record, once=True)  # another's slot
            return
        log.warning("re-leasing %s (attempt %d): %s", episode_id, lease.attempt + 1, why)
        self.pending.appendleft((lease.spec, lease.attempt + 1))

    def _pause(self, episode_id: str, why: str) -> None:
        """The lease holder gave ``episode_id`` back because a model endpoint gave no answer (``why``:
        the agent's line): pause leasing for ``infra_wait_s`` and lease the episode again first after it,
        or, after ``max_infra_attempts`` such attempts, submit its ``infra_error`` record."""
        lease = self.leases.pop(episode_id)
        self.releases += 1
        self.outages[episode_id] += 1
        lost = self.outages[episode_id]
        self.outage_line = why
        self.hold_until = max(self.hold_until, self._clock() + self.infra_wait_s)  # down for every episode
        if lost >= self.max_infra_attempts:  # logged at INFO: agos eval prints the notice (a warning would double it)
            log.info("%s: the model endpoint gave no answer in %d attempts (%s); recording infra_error", episode_id,
                     lost, why)
            record = self.gave_up[episode_id] = failure_record(
                self.run_id, lease.spec, status="infra_error", worker_id=lease.worker,
                error=f"the model endpoint gave no answer in {lost} attempts: {why}", config=self.config)
            self.bus.publish(keys.result(self.run_id, lease.worker), record, once=True)  # another's slot
            self.notices.append(f"{episode_id}: stored as infra_error after {lost} attempts without an answer from the "
                                f"model endpoint (not scored; --resume plays it again){self._waiting_text('; ')}")
            return
        self.paused[episode_id] = (lease.spec, lease.attempt + 1)
        log.info("%s paused (attempt %d lost to a model endpoint outage: %s); leasing again in %g s", episode_id,
                 lease.attempt, why, self.infra_wait_s)
        self.notices.append(f"model endpoint outage: {why} (episode {episode_id}, attempt {lease.attempt}); "
                            f"{self._waiting_text()}, leased again in {self.infra_wait_s:g} s as a fresh attempt "
                            f"({lost} of {self.max_infra_attempts} attempts lost)")

    def _waiting_text(self, before: str = "") -> str:
        """How many episodes are paused, after ``before``; '' when none is and ``before`` is given."""
        n = len(self.paused)
        if before and not n:
            return ""
        return f"{before}{n} episode{'' if n == 1 else 's'} wait{'s' if n == 1 else ''}"

    def _recovered(self, episode_id: str, attempt: int) -> None:
        """An episode leased after the latest outage's wait made a decision: the endpoint answers again."""
        self.outage_line = None
        self.notices.append(f"model endpoint answers again: {episode_id} (attempt {attempt}) decided"
                            f"{self._waiting_text('; ')}")

    def _unpause(self) -> None:
        """Once the wait after the latest outage is over, paused episodes go first in the queue."""
        if self.paused and self._clock() >= self.hold_until:
            for spec, attempt in reversed(list(self.paused.values())):
                self.pending.appendleft((spec, attempt))
            self.paused.clear()

    def _answer_queries(self) -> None:
        for query in self._queries.drain():
            self._answer(query)
        for query in self._asset_queries.drain():
            self._answer_asset(query)

    def _answer(self, query) -> None:
        try:
            request = decode(query.payload)
        except DecodeError:
            request = None
        if not isinstance(request, JobRequest):
            self.rejections.reject(query.key, "not a job request")
            return
        worker = request.worker_id
        given_back = self.leases.get(request.give_back or "")
        if given_back is not None and given_back.worker == worker and request.outage:
            self._pause(given_back.spec.episode_id, request.why)
        elif given_back is not None and given_back.worker == worker:
            self._release(given_back.spec.episode_id, f"{worker} gave it back: {request.why}", status="agent_crashed")
        if worker not in self.live_workers:
            # No world worker of this run, or one whose token is still on its way (it asks again in a
            # second): no episode for it, so a stray client cannot take episodes from the workers.
            log.debug("no job for %s: no liveliness token of that world worker", worker)
            query.reply(encode(JobGrant(worker_id=worker, episode=None, run_finished=self.finished)))
            return
        if (held := self._lost_grant(worker)) is not None:
            self.regrants += 1
            log.warning("granting %s to %s again (attempt %d): its grant did not reach it", held.spec.episode_id,
                        worker, held.attempt)
            query.reply(encode(JobGrant(worker_id=worker, episode=held.spec, attempt=held.attempt,
                                        config=self._config_map)))
            return
        self._unpause()
        while self.pending and self.pending[0][0].episode_id in self.stored:
            self.pending.popleft()  # never lease a stored episode again
        if self.pending and self._clock() >= self.hold_until and (self.may_lease is None
                                                                  or self.may_lease(self.in_flight())):
            spec, attempt = self.pending.popleft()
            now = self._clock()
            if self.first_lease_s is None:
                self.first_lease_s = now
            lease = self.leases[spec.episode_id] = Lease(spec, worker, attempt, now, now)
            log.info("leased %s to %s (attempt %d)", spec.episode_id, worker, attempt)
            self._announce(lease)
            query.reply(encode(JobGrant(worker_id=worker, episode=spec, attempt=attempt, config=self._config_map)))
        else:
            query.reply(encode(JobGrant(worker_id=worker, episode=None, run_finished=self.finished)))

    def _lost_grant(self, worker: str) -> Lease | None:
        """A lease of ``worker``'s that it cannot be playing: a worker asks for a job only between
        episodes, so a lease of its with no record and no event since it was granted (what it has sent is
        read first) is one whose grant never reached it: the reply came after its request had timed out,
        or its session dropped (bench_control_plane.py at N = 1,000: up to 7 such leases a worker, each
        waiting for the stuck timeout). It is granted again, the same episode and attempt."""
        self._read([])
        return next((lease for lease in self.leases.values() if lease.worker == worker
                     and lease.last_progress == lease.leased_at and lease.spec.episode_id not in self.records), None)

    def _answer_asset(self, query) -> None:
        """Serve a town asset from the local asset cache; unknown hashes get no reply."""
        from agos.world.towns.asset import cache_dir

        sha = keys.asset_of(query.key)
        path = cache_dir() / sha / "asset.msgpack"
        if path.exists():
            log.info("serving asset %s (%d bytes)", sha[:12], path.stat().st_size)
            query.reply(path.read_bytes())
