"""A run always ends (issue 30, item 2): whatever the bus brings, the orchestrator and the evaluator
converge, every episode stored once or recorded failed with a reason after its bounded attempts.

In-process on a MemoryBus and a simulated clock: the orchestrator and the evaluator are the real
ones, the world workers are played by the test (a job request, then the record the worker publishes).
What each case did before the fix is said in its docstring. The same cases through a real run:
tests/test_e2e_faults.py::test_a_hostile_client_changes_no_record replays the run's genuine records and
lease notices while it runs.
"""

from __future__ import annotations

import io
import time
from pathlib import Path

import msgspec
import pytest
from rich.console import Console

from agos.deploy.run.evaluate import Absences
from agos.deploy.run.orchestrator import LEASE_REPEAT_S, Orchestrator
from agos.deploy.run.plan import RunPlan
from agos.evaluator.evaluator_service import Evaluator
from agos.evaluator.store import ResultStore, results_path
from agos.runtime import keys
from agos.runtime.bus import Inbox, MemoryBus, _MemoryQuery
from agos.runtime.codec import decode, encode
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.failure_records import failure_record
from agos.runtime.schemas import EpisodeRecord, EpisodeSpec, JobGrant, JobRequest, LeaseNotice
from agos.runtime.settings import AgosConfig

from support.episodes import minimal_spec

RUN = "r1"
POLICIES = {"uav": "heuristic", "ugv": "heuristic"}
TURNS = 200
"""How many turns of 1 simulated second a case may take to converge: far beyond any case's need, far
below forever."""


class Bench:
    """A run's orchestrator and evaluator on one MemoryBus, on a clock the test moves."""

    def __init__(self, tmp: Path, episodes: list[EpisodeSpec], *, bus: MemoryBus | None = None,
                 evaluator: Evaluator | None = None, resumed: bool = False) -> None:
        self.now = 0.0
        self.bus = bus or MemoryBus()
        self.evaluator = evaluator or Evaluator(self.bus, tmp)
        self.heard = Inbox()
        if evaluator is None:
            for expr in (keys.result("*", "*"), keys.lease("*"), keys.manifest("*")):
                self.bus.subscribe(expr, self.heard)
        self.orch = Orchestrator(self.bus, RUN, episodes, policies=POLICIES, resumed=resumed, clock=lambda: self.now)
        self.stored: list[EpisodeRecord] = []
        self.tokens: dict[str, object] = {}

    def exit(self, worker: str) -> None:
        """``worker`` exits: its liveliness token goes (and does not come back within the grace)."""
        self.bus.undeclare_token(self.tokens.pop(worker))
        self.turn(0.0)
        self.turn(self.orch.reconnect_grace_s)
        self.turn(0.0)

    def job(self, worker: str) -> JobGrant:
        """What ``worker`` (its token declared here) is granted when it asks for a job."""
        if worker not in self.tokens:
            self.tokens[worker] = self.bus.declare_token(keys.live(RUN, "world", worker))
            self.turn(0.0)  # the orchestrator hears of the token
        query = _MemoryQuery(keys.jobs(RUN), encode(JobRequest(worker_id=worker)))
        self.orch._queries.put(query)
        self.turn(0.0)
        grant = decode(query.replies[-1])
        assert isinstance(grant, JobGrant)
        return grant

    def play(self, worker: str, **fields: object) -> EpisodeRecord:
        """``worker`` asks for a job and publishes the record of the episode it is granted."""
        grant = self.job(worker)
        assert grant.episode is not None, grant
        record = self.record(grant.episode.episode_id, worker, **fields)
        self.bus.publish(keys.result(RUN, record.worker_id), record)
        return record

    @staticmethod
    def record(episode_id: str, worker: str, **fields: object) -> EpisodeRecord:
        """A finished episode's record as ``worker`` publishes it."""
        played = failure_record(RUN, minimal_spec(episode_id), status="world_crashed", worker_id=worker, error="x",
                                config=EpisodeConfig())
        return msgspec.structs.replace(played, status="finished", termination="confirmed", success=True, error=None,
                                       **fields)

    def turn(self, seconds: float = 1.0) -> None:
        """Move the clock, then let both sides read what the bus holds until neither has anything left."""
        self.now += seconds
        for _ in range(50):
            self.stored += self.orch.pump(0.0)
            heard = self.heard.drain()
            for sample in heard:
                self.evaluator.handle(sample.key, sample.payload)
            if not heard:
                return
        raise AssertionError("the bus never went quiet")

    def until_finished(self) -> int:
        """Turns of 1 s until the orchestrator says the run is over (at most ``TURNS``)."""
        for turns in range(TURNS):
            if self.orch.finished:
                return turns
            self.turn()
        raise AssertionError(f"not finished after {TURNS} s: stored {sorted(self.orch.stored)}, "
                             f"leases {sorted(self.orch.leases)}, unacknowledged {self.orch.unacknowledged()}")

    def rows(self) -> list[EpisodeRecord]:
        with ResultStore(results_path(self.evaluator.runs_dir, RUN), create=False) as store:
            return store.records(RUN)


def test_replayed_records_and_lease_notices_of_stored_episodes_change_nothing(tmp_path: Path) -> None:
    """A genuine record published again after it was stored, its lease notice again, and the evaluator's
    ack of every copy: one row per episode, the run over, nothing held or published again afterwards."""
    bench = Bench(tmp_path, [minimal_spec("e1"), minimal_spec("e2")])
    first = bench.play("w1")
    bench.turn()
    assert bench.orch.stored == {first.episode_id}
    notice = LeaseNotice(run_id=RUN, episode_id=first.episode_id, worker_id="w1", attempt=1)
    for _ in range(3):
        bench.bus.publish(keys.result(RUN, first.worker_id), first)
        bench.bus.publish(keys.lease(RUN), notice)
    second = bench.play("w1")
    bench.bus.publish(keys.result(RUN, second.worker_id), second)  # a duplicate before the ack
    bench.until_finished()
    for _ in range(3):
        bench.bus.publish(keys.result(RUN, second.worker_id), second)
    bench.turn(LEASE_REPEAT_S)
    published = len(bench.bus.published)
    bench.turn(3 * LEASE_REPEAT_S)
    assert bench.bus.published[published:] == []  # nothing repeated: no lease, nothing unacknowledged
    assert [r.episode_id for r in bench.rows()] == ["e1", "e2"]
    assert [r.episode_id for r in bench.stored] == ["e1", "e2"] and bench.orch.releases == 0
    assert not bench.orch.leases and not bench.orch.pending and not bench.orch.unacknowledged()


def test_a_finished_episode_waiting_for_its_ack_is_not_leased_again(tmp_path: Path) -> None:
    """The holder's record is in but the evaluator has not stored it yet (absent, or it refused a copy):
    the episode is done, so neither the stuck clock nor its worker's exit lease it again (before: it was
    re-leased after 180 s and played once more, or re-leased at once when the worker exited)."""
    bench = Bench(tmp_path, [minimal_spec("e1"), minimal_spec("e2")])
    bench.evaluator.handle = lambda key, payload: None  # type: ignore[method-assign]  # the evaluator is away
    first = bench.play("w1")
    bench.turn(bench.orch.stuck_after_s + 1)
    bench.exit("w1")
    assert bench.orch.releases == 0 and bench.orch.unacknowledged() == [first.episode_id]
    assert bench.job("w2").episode.episode_id == "e2"  # type: ignore[union-attr]
    del bench.evaluator.handle  # it is back: the orchestrator's repeat of the record is stored
    bench.bus.publish(keys.result(RUN, "w2"), bench.record("e2", "w2"))
    bench.until_finished()
    assert [(r.episode_id, r.worker_id) for r in bench.rows()] == [("e1", "w1"), ("e2", "w2")]
    assert bench.orch.releases == 0


def test_a_stored_episode_is_never_leased_again(tmp_path: Path) -> None:
    """Whatever put it back in the queue, an episode the evaluator acknowledged is not handed out again
    (before: it was leased, played, and its ack ignored, so its lease was never let go)."""
    bench = Bench(tmp_path, [minimal_spec("e1"), minimal_spec("e2")])
    bench.play("w1")
    bench.turn()
    bench.orch.pending.appendleft((minimal_spec("e1"), 2))
    assert bench.job("w1").episode.episode_id == "e2"  # type: ignore[union-attr]
    assert not bench.orch.pending


def test_episodes_a_run_gives_up_on_are_stored_failed_with_the_reason(tmp_path: Path) -> None:
    """Every attempt's worker exits: after the third the orchestrator records the infrastructure failure
    itself, under the last holder's name, and the run ends with it stored once."""
    bench = Bench(tmp_path, [minimal_spec("e1")])
    for attempt in (1, 2, 3):
        grant = bench.job(f"w{attempt}")
        assert (grant.episode is not None and grant.attempt) == attempt
        bench.exit(f"w{attempt}")
    bench.until_finished()
    [row] = bench.rows()
    assert (row.status, row.worker_id) == ("world_crashed", "w3")
    assert row.error is not None and row.error.startswith("gave up after 3 attempts: worker w3: its liveliness token")


@pytest.mark.parametrize("before", ["an earlier invocation's attempt 3", "a forged notice of attempt 99"])
def test_the_newest_lease_notice_names_the_holder(tmp_path: Path, before: str) -> None:
    """A long-lived evaluator (started by hand) heard attempt 3 of e1 in the run's first invocation and
    stored its failure; ``agos eval --resume`` leases e1 again as attempt 1. Or a forged lease notice
    with a high attempt arrived. The newest notice names the holder (the orchestrator repeats its own
    every 5 s), so the resumed run's record is stored (before: the highest attempt won, the new holder's
    record was refused for ever and the run never ended)."""
    bus = MemoryBus()
    evaluator = Evaluator(bus, tmp_path)
    heard = Inbox()
    for expr in (keys.result("*", "*"), keys.lease("*"), keys.manifest("*")):
        bus.subscribe(expr, heard)
    attempt, holder = (3, "w-old") if before.startswith("an earlier") else (99, "forger")
    bus.publish(keys.lease(RUN), LeaseNotice(run_id=RUN, episode_id="e1", worker_id=holder, attempt=attempt))
    if holder == "w-old":
        bus.publish(keys.result(RUN, holder), failure_record(RUN, minimal_spec("e1"), status="world_crashed",
                                                           worker_id=holder, error="gave up after 3 attempts",
                                                           config=EpisodeConfig()))
    for sample in heard.drain():
        evaluator.handle(sample.key, sample.payload)
    bench = Bench(tmp_path, [minimal_spec("e1")], bus=bus, evaluator=evaluator, resumed=True)
    bench.heard = heard
    bench.play("w-new")
    bench.until_finished()
    [row] = bench.rows()
    assert (row.status, row.worker_id) == ("finished", "w-new")


def test_an_orchestrator_refuses_a_split_with_an_episode_twice(tmp_path: Path) -> None:
    """One episode id twice could never finish (the run waited for two stored episodes of one id); the
    episode files refuse it first (world/episodes/files.py), and so does the orchestrator."""
    with pytest.raises(ValueError, match="e1 twice"):
        Orchestrator(MemoryBus(), RUN, [minimal_spec("e1"), minimal_spec("e1")], policies=POLICIES)


def test_records_an_evaluator_on_the_bus_never_stores_stop_the_run(tmp_path: Path) -> None:
    """An evaluator is present but does not store the holder's record (before: only an absent one
    stopped the run, so this one waited for ever): after 3 presence checks the run stops, exit 3,
    with one line naming the records and the resume command."""
    cfg = AgosConfig().model_copy(update={"run": AgosConfig().run.model_copy(update={"presence_check_s": 0.01})})
    plan = RunPlan(tmp_path / "runs" / RUN, [minimal_spec("e1")], POLICIES, EpisodeConfig())
    bench = Bench(tmp_path, plan.episodes)
    bench.evaluator.serve_run(RUN)  # on the bus for the run
    bench.evaluator.handle = lambda key, payload: None  # type: ignore[method-assign]  # and storing nothing
    bench.play("w1")
    bench.turn()
    out = io.StringIO()
    absences = Absences(cfg, plan, bench.bus, bench.orch, "tcp/x", Console(file=out, width=300))
    halt = None
    for _ in range(100):
        halt = absences.check()
        if halt is not None:
            break
        time.sleep(0.005)
    assert halt is not None and halt.code == 3, out.getvalue()
    assert "no evaluator stored the records of e1 (3 checks" in halt.line
    assert "see the log of the evaluator serving it and resume with `agos eval --resume" in halt.line


def test_a_worker_back_within_the_grace_keeps_its_lease(tmp_path: Path) -> None:
    """A worker's token that vanishes and comes back within ``reconnect_grace_s`` (a router restarted, a
    session that reconnected) keeps its episode: stored as attempt 1, nothing re-leased."""
    bench = Bench(tmp_path, [minimal_spec("e1"), minimal_spec("e2")])
    grant = bench.job("w1")
    assert grant.episode is not None and grant.attempt == 1
    bench.bus.undeclare_token(bench.tokens.pop("w1"))
    bench.turn(bench.orch.reconnect_grace_s / 2)
    assert bench.job("w2").episode.episode_id == "e2"  # type: ignore[union-attr]
    bench.tokens["w1"] = bench.bus.declare_token(keys.live(RUN, "world", "w1"))  # back
    bench.turn(bench.orch.reconnect_grace_s)
    bench.bus.publish(keys.result(RUN, "w1"), bench.record("e1", "w1"))
    bench.bus.publish(keys.result(RUN, "w2"), bench.record("e2", "w2"))
    bench.until_finished()
    assert bench.orch.releases == 0 and not bench.orch.pending
    assert [(r.episode_id, r.worker_id) for r in bench.rows()] == [("e1", "w1"), ("e2", "w2")]


def test_a_grant_that_never_reached_its_worker_is_granted_again(tmp_path: Path) -> None:
    """A worker asks for a job only between episodes: asking again while it holds a lease that shows
    nothing (no event, no record) means the grant's reply was lost (a busy router). It gets the same
    episode and attempt again, not a second one, and nothing waits for the stuck timeout."""
    bench = Bench(tmp_path, [minimal_spec("e1"), minimal_spec("e2")])
    lost = bench.job("w1")
    again = bench.job("w1")
    assert again.episode == lost.episode and again.attempt == lost.attempt == 1
    assert bench.orch.regrants == 1 and list(bench.orch.leases) == ["e1"]
    bench.bus.publish(keys.result(RUN, "w1"), bench.record("e1", "w1"))  # played, its record on the way
    assert bench.job("w1").episode.episode_id == "e2"  # type: ignore[union-attr]  # read before answering
    bench.bus.publish(keys.result(RUN, "w1"), bench.record("e2", "w1"))
    bench.until_finished()
    assert bench.orch.releases == 0 and bench.orch.regrants == 1
    assert [r.episode_id for r in bench.rows()] == ["e1", "e2"]
