"""No silent waits: `agos eval --connect` on a run that cannot progress names what is missing and
the command that starts it (router, evaluator and an agent on another run are real processes)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from agos.deploy.launcher import free_port, wait_listening

pytestmark = pytest.mark.e2e
AGOS = [sys.executable, "-m", "agos.deploy.cli"]


def test_eval_names_the_missing_processes_and_runs_with_agents(tmp_path, sample_mid_episodes) -> None:
    port = free_port(17700)
    endpoint = f"tcp/127.0.0.1:{port}"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "cwd": tmp_path}
    procs = [subprocess.Popen([*AGOS, "router", "--listen", endpoint], **quiet)]
    try:
        assert wait_listening("127.0.0.1", port, 15)
        procs.append(subprocess.Popen([*AGOS, "evaluator", "--connect", endpoint, "--runs-dir", "runs"], **quiet))
        procs.append(subprocess.Popen([*AGOS, "agent", "--role", "uav", "--connect", endpoint, "--run", "mine-typo"],
                                      **quiet))
        split = sample_mid_episodes(1, 7)
        started = time.monotonic()
        ev = subprocess.Popen([*AGOS, "eval", "--connect", endpoint, "--run", "mine", "--split", str(split),
                               "--runs-dir", "runs"], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)
        procs.append(ev)
        seen = ""
        assert ev.stdout is not None
        while "other runs" not in seen:
            assert time.monotonic() - started < 60 and ev.poll() is None, seen
            seen += ev.stdout.readline()
        text = " ".join(seen.split())
        assert f"no world worker serves run mine: start one with `agos world --connect {endpoint} --run mine`" in text
        assert "no UAV agent" in text and "no UGV agent serves run mine" in text
        assert "agos agent --role ugv --policy heuristic" in text
        assert "mine-typo (uav)" in text
        assert "no evaluator" not in text  # the evaluator serves every run
        ev.send_signal(signal.SIGINT)
        ev.wait(timeout=30)
        assert ev.returncode == 130
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                p.wait(timeout=10)


def test_eval_stops_after_three_episodes_lost_to_one_cause(tmp_path, sample_mid_episodes) -> None:
    """No agent services at all: each episode is lost after the world's agent wait; after three in a row
    lost the same way, eval stops with the cause and exit 3 instead of spending every episode's wait."""
    port = free_port(17800)
    endpoint = f"tcp/127.0.0.1:{port}"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "cwd": tmp_path}
    procs = [subprocess.Popen([*AGOS, "router", "--listen", endpoint], **quiet)]
    try:
        assert wait_listening("127.0.0.1", port, 15)
        procs.append(subprocess.Popen([*AGOS, "evaluator", "--connect", endpoint, "--runs-dir", "runs"], **quiet))
        procs.append(subprocess.Popen([*AGOS, "world", "--connect", endpoint, "--run", "lost", "--agent-wait", "1"],
                                      **quiet))
        out = subprocess.run([*AGOS, "eval", "--connect", endpoint, "--run", "lost", "--split",
                              str(sample_mid_episodes(5, 9)), "--runs-dir", "runs"], cwd=tmp_path,
                             capture_output=True, text=True, timeout=240)
        text = " ".join(out.stdout.split())
        assert out.returncode == 3, text
        assert "3 episodes in a row lost to the same cause (agent_crashed)" in text
        assert "no UAV and UGV agent service subscribed to run 'lost'" in text
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                p.wait(timeout=10)


def test_a_loss_streak_counts_one_cause_in_a_row() -> None:
    from agos.deploy.presence import LossStreak

    class R:
        def __init__(self, status: str, error: str | None = None) -> None:
            self.status, self.error = status, error

    streak = LossStreak(3)
    seq = [R("agent_crashed", "x"), R("agent_crashed", "x"), R("finished"), R("agent_crashed", "x"),
           R("world_crashed", "y"), R("agent_crashed", "x"), R("agent_crashed", "x")]
    assert [streak.add(r) for r in seq] == [None] * 7  # type: ignore[arg-type]
    assert streak.add(R("agent_crashed", "x")) == "agent_crashed: x"  # type: ignore[arg-type]
