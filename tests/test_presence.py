"""``agos eval``'s presence warnings are true (issue 30, item 4): the evaluator it starts knows its run
from the start, an evaluator that missed the run's first manifest joins at the next lease notice, and a
process the command started that has not joined yet is named as joining, with its log, never as one
to start by hand. In-process, on a MemoryBus (the e2e side: tests/test_e2e_presence.py)."""

from __future__ import annotations

import io
import threading
import time
from pathlib import Path

import pytest
from rich.console import Console

from agos.deploy.run.evaluate import Absences
from agos.deploy.run.launcher import Launcher
from agos.deploy.run.local import ChildSettings, evaluator_settings
from agos.deploy.run.orchestrator import Orchestrator
from agos.deploy.run.plan import RunPlan
from agos.deploy.run.presence import Presence, missing_lines, started_kinds, who_is_here
from agos.evaluator.evaluator_service import Evaluator, serve
from agos.runtime import keys
from agos.runtime.bus import MemoryBus
from agos.runtime.codec import encode
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.process import StopFlag
from agos.runtime.schemas import LeaseNotice, RunManifest
from agos.runtime.settings import AgosConfig

from support.episodes import minimal_spec
from support.waiting import wait_until

RUN = "r1"
POLICIES = {"uav": "heuristic", "ugv": "heuristic"}


@pytest.fixture
def plan(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> RunPlan:
    monkeypatch.setenv("AGOS_HEALTH_DIR", str(tmp_path / "health"))  # the evaluator says which token it declared
    return RunPlan(tmp_path / "runs" / RUN, [minimal_spec("e1")], POLICIES, EpisodeConfig())


def _manifest(status: str = "running") -> RunManifest:
    return RunManifest(run_id=RUN, status=status, policies=POLICIES, n_episodes=1, created_utc="2026-01-01T00:00:00")




def test_the_evaluator_eval_starts_is_present_though_it_missed_the_runs_start(plan: RunPlan) -> None:
    """A slow start: the run's manifest went out before the evaluator subscribed. Told its run (as
    ``agos evaluator`` reads it from its settings), it is present at once, with no record yet."""
    settings = evaluator_settings(ChildSettings(AgosConfig(), "tcp/127.0.0.1:7447", RUN), plan)
    assert settings.run.run_id == RUN and settings.run.runs_dir == plan.run_dir.parent
    with MemoryBus() as bus:
        bus.publish(keys.manifest(RUN), _manifest())  # heard by nobody
        stop = StopFlag()
        thread = threading.Thread(target=serve, args=(bus, settings.run.runs_dir, stop),
                                  kwargs={"announce_run": settings.run.run_id}, daemon=True)
        thread.start()
        try:
            assert wait_until(lambda: who_is_here(bus, RUN).evaluator)
            assert not [line for line in missing_lines(who_is_here(bus, RUN), RUN, "tcp/x", POLICIES) if "evaluator" in line]
        finally:
            stop.set()
            thread.join(5)
    assert not (plan.run_dir / "results.sqlite").exists()  # present, but nothing stored: no file


def test_an_evaluator_that_missed_the_manifest_joins_the_run_at_its_next_lease_notice(tmp_path: Path) -> None:
    """One started by hand without ``--run`` (it stores every run) after ``agos eval`` began: the
    orchestrator repeats each lease notice every 5 s, and the evaluator joins the run on hearing one."""
    with MemoryBus() as bus:
        evaluator = Evaluator(bus, tmp_path)
        assert not who_is_here(bus, RUN).evaluator
        notice = LeaseNotice(run_id=RUN, episode_id="e1", worker_id="w0", attempt=1)
        evaluator.handle(keys.lease(RUN), encode(notice))
        assert who_is_here(bus, RUN).evaluator
        evaluator.handle(keys.lease("other"), encode(LeaseNotice(run_id="r2", episode_id="e1", worker_id="w0",
                                                                        attempt=1)))  # names another run than its key
        assert not who_is_here(bus, "r2").evaluator and not who_is_here(bus, "other").evaluator
        evaluator.close()


def test_a_child_that_has_not_joined_yet_is_named_with_its_log_not_as_one_to_start() -> None:
    assert started_kinds(["world-0", "world-1", "agent-uav", "evaluator", "router", "recorder", "human"]) == \
        {"world", "uav", "evaluator"}
    nobody = Presence(worlds=0, evaluator=False, agents={"uav": 0, "ugv": 0})
    logs = Path("runs/r1/logs")
    lines = missing_lines(nobody, RUN, "tcp/x", POLICIES, started=frozenset({"world", "evaluator", "uav"}), logs=logs)
    assert lines == [
        f"the world worker this command started has not joined run r1 yet; see {logs / 'world-0.log'}",
        f"the evaluator this command started has not joined run r1 yet; see {logs / 'evaluator.log'}",
        f"the UAV agent this command started has not joined run r1 yet; see {logs / 'agent-uav.log'}",
        "no UGV agent serves run r1: start one with `agos agent --role ugv --policy heuristic --connect tcp/x --run r1`",
    ]
    attached = missing_lines(nobody, RUN, "tcp/x", POLICIES)  # agos eval --connect: nothing of its own
    assert "no evaluator stores run r1: start one with `agos evaluator --connect tcp/x --run r1`" in attached[1]


class _Running:
    """A child process that is still running (what :meth:`Launcher.dead` asks)."""

    returncode = None

    def poll(self) -> None:
        return None


def test_eval_waits_for_a_slow_evaluator_it_started_instead_of_asking_for_another(plan: RunPlan) -> None:
    """``Absences`` as ``agos eval`` runs it: while its own evaluator is still starting, the warning says
    so and where its log is; once the evaluator is up, no line about it."""
    cfg = AgosConfig().model_copy(update={"run": AgosConfig().run.model_copy(update={"presence_check_s": 0.01})})
    out = io.StringIO()
    launcher = Launcher(None)
    launcher.children = {"evaluator": _Running(), "world-0": _Running()}  # type: ignore[dict-item]
    with MemoryBus() as bus:
        orch = Orchestrator(bus, RUN, plan.episodes, policies=POLICIES)
        bus.declare_token(keys.live(RUN, "world", "w0"))
        absences = Absences(cfg, plan, bus, orch, "tcp/x", Console(file=out, width=300), launcher)
        absences.check()  # the first look starts the stall clock
        time.sleep(0.02)
        assert absences.check() is None
        said = out.getvalue()
        assert "the evaluator this command started has not joined run r1 yet; see" in said, said
        assert "agos evaluator --connect" not in said
        bus.declare_token(keys.live(RUN, "evaluator", "main"))  # it came up
        out.truncate(0)
        time.sleep(0.02)
        assert absences.check() is None and "evaluator" not in out.getvalue()
