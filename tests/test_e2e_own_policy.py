"""The example policy of one's own (examples/my_policy.py) as remote agent processes on the bus: run
by ``agos eval --policy examples.my_policy:Explorer`` from the repository root (its agent processes
import it from there), and checked by ``agos check agent`` against agent services started
elsewhere with the root on ``PYTHONPATH`` (docs/AGENTS.md, "Write your own agent")."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from agos.deploy.run.launcher import free_port, wait_listening
from agos.evaluator.store import ResultStore

from support.processes import stop_all

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = "examples.my_policy:Explorer"
BUDGET = 8
FLAT_AND_SHORT = {"AGOS_WORLD__LOOK": "flat", "AGOS_WORLD__DECISION_BUDGET": str(BUDGET)}

pytestmark = pytest.mark.e2e
AGOS = [sys.executable, "-m", "agos.deploy.cli"]


def test_agos_eval_runs_the_example_as_agent_processes(tmp_path: Path) -> None:
    from agos.deploy.cli import main

    split = tmp_path / "eps.jsonl"  # flat look: the policy sees no pixels, and flat scenes build faster
    assert main(["episodes", "sample", "--town", "grid-s7", "--difficulty", "mid", "-n", "1", "--seed", "5",
                 "--look", "flat", "--out", str(split)]) == 0
    env = {**os.environ, **FLAT_AND_SHORT}
    out = subprocess.run([*AGOS, "eval", "--split", str(split), "--policy", EXAMPLE, "--run-dir", str(tmp_path / "run")],
                         cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    with ResultStore(tmp_path / "run" / "results.sqlite", create=False) as store:
        [record] = store.records()
    assert (record.status, record.termination, record.fallbacks) == ("finished", "budget_exhausted", 0)
    assert record.decisions_uav + record.decisions_ugv == BUDGET
    for role in ("uav", "ugv"):  # the agent processes served the example, not a built-in policy
        assert f"{role} agent (explorer) serving run" in (tmp_path / "run" / "logs" / f"agent-{role}.log").read_text()


def test_agos_check_agent_passes_the_example_served_from_elsewhere(tmp_path: Path) -> None:
    port = free_port(23000 + os.getpid() % 400)
    endpoint = f"tcp/127.0.0.1:{port}"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    procs = [subprocess.Popen([*AGOS, "router", "--listen", endpoint], cwd=tmp_path, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)]
    try:
        assert wait_listening("127.0.0.1", port, 15.0)
        for role in ("uav", "ugv"):  # cwd is not the repository: the example comes from PYTHONPATH
            log = (tmp_path / f"agent-{role}.log").open("wb")
            procs.append(subprocess.Popen([*AGOS, "agent", "--role", role, "--policy", EXAMPLE, "--connect", endpoint,
                                           "--run", "own"], cwd=tmp_path, env=env, stdout=log, stderr=subprocess.STDOUT))
        out = subprocess.run([*AGOS, "check", "agent", "--connect", endpoint, "--run", "own", "--policy", EXAMPLE,
                              "--budget", str(BUDGET)], cwd=tmp_path, env={**os.environ, **FLAT_AND_SHORT},
                             capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stdout + out.stderr
        assert "PASS: the agents conform" in out.stdout and f"{BUDGET} decisions, 0 fallbacks" in out.stdout
    finally:
        stop_all(procs)
