"""Outages are not the model's failures (issue 31, item 1): a decision whose model endpoint gave no
answer after its retries is answered with ``Action.outage`` by the agent service, ends the world's
attempt without a decision, and the orchestrator pauses the episode (nothing leased for
``infra_wait_s``), leases it again as a fresh attempt, and after ``max_infra_attempts`` stores it as
``infra_error``, which no metric scores. In-process, on the in-memory bus and a simulated clock;
the whole path through a real run: tests/test_e2e_vlm.py::test_an_outage_window_pauses_episodes_and_resume_finishes_them.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from agos.agents.agent_service import answer, decide
from agos.agents.contract import EndpointOutage, Policy
from agos.deploy.run.evaluate import infra_error_line
from agos.evaluator.metrics import by_difficulty
from agos.runtime import keys
from agos.runtime.bus import Inbox, MemoryBus, Sample, _MemoryQuery
from agos.runtime.codec import decode, encode
from agos.runtime.process import StopFlag
from agos.runtime.schemas import Action, CoordinationState, JobGrant, JobRequest, Observation, Pose
from agos.world.sim.worker import BusDecisionSource, ModelOutage, WorkerSlot
from tests.test_run_converges import RUN, Bench

from support.episodes import minimal_spec

WHY = "UAV agent: http://127.0.0.1:8000/v1: no answer after 5 attempts (HTTP 503)"


def _obs(role: str = "uav", attempt: int = 1) -> Observation:
    return Observation(run_id="r", episode_id="e1", role=role, decision_index=1, attempt=attempt, sim_time_s=0.0,
                       pose=Pose(position_world_m=(0.0, 0.0, 80.0), yaw_rad=0.0), mode="aerial", images=[], references=[],
                       legal_actions=["WAIT"], waypoint_options=[], region_world_m=(0.0, 0.0, 1.0, 1.0),
                       coordination=CoordinationState(run_id="r", episode_id="e1", sim_time_s=0.0))


class _Down(Policy):
    """A policy whose endpoint is down."""

    def act(self, obs: Observation) -> Action:
        raise EndpointOutage("http://127.0.0.1:8000/v1: no answer after 5 attempts (ConnectError)")


def test_the_agent_service_answers_an_outage_never_a_wait_decision() -> None:
    obs = _obs()
    for action in (asyncio.run(answer(_Down("uav"), obs)), decide(_Down("uav"), obs)):
        assert action.outage == "http://127.0.0.1:8000/v1: no answer after 5 attempts (ConnectError)"
        assert (action.episode_id, action.role, action.decision_index, action.attempt) == ("e1", "uav", 1, 1)
        assert decode(encode(action)) == action  # it crosses the wire as it is


def test_an_outage_answer_ends_the_world_attempt_without_a_decision() -> None:
    """The world takes the outage answer to the decision it asked (its attempt) and raises ModelOutage
    at once: nothing is applied, the UGV's answer is not waited for, and the worker gives the attempt back."""
    bus = MemoryBus()
    source = BusDecisionSource(WorkerSlot(bus, "r", "w1"), "e1", timeout_s=30.0, stop=StopFlag(), agent_wait_s=0.2)
    for role in ("uav", "ugv"):
        bus.declare_token(keys.slot_ready("r", "w1", role, f"{role}-1"))

    class DownAgent(Inbox):
        def put(self, sample: Sample) -> None:
            obs = decode(sample.payload)
            bus.publish(keys.act("r", "w1", "uav"), encode(Action(
                run_id="r", episode_id="e1", role="uav", decision_index=obs.decision_index, attempt=obs.attempt,
                action="WAIT", outage="http://x/v1: no answer after 2 attempts (HTTP 500)")))

    bus.subscribe(keys.obs("r", "w1", "uav"), DownAgent())
    with pytest.raises(ModelOutage) as raised:
        source.decide({"uav": _obs("uav"), "ugv": _obs("ugv")})  # the UGV never answers: not waited for 30 s
    assert str(raised.value) == "UAV agent: http://x/v1: no answer after 2 attempts (HTTP 500)"
    source.close()


def _give_back(bench: Bench, worker: str, episode: str, why: str = WHY, *, outage: bool = True) -> JobGrant:
    """``worker`` asks for its next job, giving ``episode`` back (for an outage, as the world does)."""
    query = _MemoryQuery(keys.jobs(RUN), encode(JobRequest(worker_id=worker, give_back=episode, why=why, outage=outage)))
    bench.orch._queries.put(query)
    bench.turn(0.0)
    grant = decode(query.replies[-1])
    assert isinstance(grant, JobGrant)
    return grant


def test_an_outage_pauses_leasing_and_after_k_attempts_stores_infra_error(tmp_path: Path) -> None:
    """Episode a loses three attempts to the endpoint: each time nothing is leased for infra_wait_s, then a
    goes first as the next attempt; the third stores infra_error (not scored, counted), and the run goes on."""
    bench = Bench(tmp_path, [minimal_spec("a"), minimal_spec("b")])
    wait_s = bench.orch.infra_wait_s
    assert (bench.orch.max_infra_attempts, wait_s) == (3, 60.0)  # the defaults ([run] settings)
    first = bench.job("w1")
    assert (first.episode.episode_id, first.attempt) == ("a", 1)
    for attempt in (1, 2):
        paused = _give_back(bench, "w1", "a")
        assert paused.episode is None and not paused.run_finished  # nothing, b neither: the endpoint is down
        [line] = bench.orch.notices
        bench.orch.notices.clear()
        assert line == (f"model endpoint outage: {WHY} (episode a, attempt {attempt}); 1 episode waits, leased again in "
                        f"60 s as a fresh attempt ({attempt} of 3 attempts lost)")
        bench.turn(wait_s - 1)
        assert bench.job("w2").episode is None  # still waiting, whichever worker asks
        bench.turn(1)
        again = bench.job("w1")
        assert (again.episode.episode_id, again.attempt) == ("a", attempt + 1)  # first, before b, afresh
    assert _give_back(bench, "w1", "a").episode is None  # the third: infra_error, and the wait again
    assert bench.orch.notices[-1].startswith("a: stored as infra_error after 3 attempts without an answer")
    bench.turn(wait_s)
    bench.play("w1")  # b, finished
    bench.until_finished()
    rows = {r.episode_id: r for r in bench.rows()}
    assert rows["a"].status == "infra_error" and rows["b"].status == "finished"
    assert rows["a"].error == f"the model endpoint gave no answer in 3 attempts: {WHY}"
    overall = by_difficulty(list(rows.values()))["overall"]
    assert (overall.n, overall.SR, overall.excluded, overall.infra_errors) == (1, 1.0, 1, 1)  # a is no failure
    line = infra_error_line(list(rows.values()), "agos eval --resume runs/r1")
    assert line is not None and line.startswith("1 episode stored as infra_error (not scored; the model endpoint gave")
    assert line.endswith("play it again once the endpoint answers: agos eval --resume runs/r1")
    assert infra_error_line([rows["b"]], "x") is None


def test_outage_attempts_do_not_use_up_the_crash_attempts(tmp_path: Path) -> None:
    """An episode that lost an attempt to an outage still gets max_attempts attempts for crashes (agents
    vanishing): the two are counted apart, so one cannot turn into the other's failure."""
    bench = Bench(tmp_path, [minimal_spec("a")])
    bench.orch.infra_wait_s = 0.0
    bench.job("w1")
    attempts = [_give_back(bench, "w1", "a").attempt]  # attempt 1 lost to an outage; no wait: leased again at once
    for _ in range(2):  # attempts 2 and 3: the agents vanish
        attempts.append(_give_back(bench, "w1", "a", "the UAV agent service vanished", outage=False).attempt)
    assert attempts == [2, 3, 4] and not bench.orch.gave_up  # 2 crashes of 3 allowed: leased again
    _give_back(bench, "w1", "a", "the UAV agent service vanished", outage=False)  # the third crash
    bench.until_finished()
    [row] = bench.rows()
    assert row.status == "agent_crashed" and row.error.startswith("gave up after 4 attempts")
