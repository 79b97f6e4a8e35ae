"""No silent waits: `agos eval --connect` on a run that cannot progress names what is missing and
the command that starts it (router, evaluator and an agent on another run are real processes)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from agos.deploy.run.launcher import free_port, wait_listening

pytestmark = pytest.mark.e2e
AGOS = [sys.executable, "-m", "agos.deploy.cli"]
FAST_CHECKS = {"AGOS_RUN__PRESENCE_CHECK_S": "3"}
"""Presence checks 3 s apart rather than 15, for the tests that wait for three of them."""
FIRST_CHECK_SOONER = {"AGOS_RUN__PRESENCE_CHECK_S": "6"}
"""For the tests that read the first check's lines and then press Ctrl-C (before the third check stops the run)."""
HANG_BOUND_S = 120.0
"""A hang, not a speed: how long a test waits for a command's line or its exit before it fails. The
lines come at the first presence check, 3-6 s in here; bounds of 30 s failed at load 10 on 2 cores and
seven commands starting at once once took 46 s to exit."""


def test_eval_names_the_missing_processes_and_runs_with_agents(tmp_path, sample_mid_episodes, running_system) -> None:
    endpoint = running_system.endpoint
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    procs = [running_system.start("agent", "--role", "uav", "--connect", endpoint, "--run", "mine-typo")]
    try:
        split = sample_mid_episodes(1, 7)
        started = time.monotonic()
        ev = subprocess.Popen([*AGOS, "eval", "--connect", endpoint, "--run", "mine", "--split", str(split),
                               "--runs-dir", "runs"], cwd=tmp_path, env={**env, **FIRST_CHECK_SOONER}, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)
        procs.append(ev)
        seen = ""
        assert ev.stdout is not None
        while "other runs" not in seen:
            assert time.monotonic() - started < HANG_BOUND_S and ev.poll() is None, seen
            seen += ev.stdout.readline()
        text = " ".join(seen.split())
        assert f"no world worker serves run mine: start one with `agos world --connect {endpoint} --run mine`" in text
        assert "no UAV agent" in text and "no UGV agent serves run mine" in text
        assert "agos agent --role ugv --policy heuristic" in text
        assert "mine-typo (uav)" in text
        assert "no evaluator" not in text  # the evaluator serves every run
        ev.send_signal(signal.SIGINT)
        ev.wait(timeout=HANG_BOUND_S)
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
    from agos.deploy.run.presence import LossStreak

    class R:
        def __init__(self, status: str, error: str | None = None) -> None:
            self.status, self.error = status, error

    streak = LossStreak(3)
    seq = [R("agent_crashed", "x"), R("agent_crashed", "x"), R("finished"), R("agent_crashed", "x"),
           R("world_crashed", "y"), R("agent_crashed", "x"), R("agent_crashed", "x")]
    assert [streak.add(r) for r in seq] == [None] * 7  # type: ignore[arg-type]
    assert streak.add(R("agent_crashed", "x")) == "agent_crashed: x"  # type: ignore[arg-type]


class _Procs:
    """A router on a free port and whatever the test starts beside it, all stopped at the end."""

    def __init__(self, tmp_path, base: int) -> None:
        self.port = free_port(base)
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.cwd = tmp_path
        self.procs: list[subprocess.Popen] = []
        self.start("router", "--listen", self.endpoint)
        assert wait_listening("127.0.0.1", self.port, 15)

    def start(self, *argv: str) -> subprocess.Popen:
        proc = subprocess.Popen([*AGOS, *argv], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=self.cwd)
        self.procs.append(proc)
        return proc

    def close(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.terminate()
                p.wait(timeout=10)


def test_eval_without_an_evaluator_says_so_and_stops(tmp_path, sample_mid_episodes) -> None:
    """World and agents but no evaluator: the console names the missing evaluator and its start command
    at a presence check, and once records have waited unstored for three checks the run stops with exit 3
    (checks 3 s apart here: ``[run] presence_check_s``)."""
    procs = _Procs(tmp_path, 17900)
    try:
        procs.start("world", "--connect", procs.endpoint, "--run", "unstored")
        for role in ("uav", "ugv"):
            procs.start("agent", "--role", role, "--connect", procs.endpoint, "--run", "unstored")
        started = time.monotonic()
        ev = subprocess.Popen([*AGOS, "eval", "--connect", procs.endpoint, "--run", "unstored", "--split",
                               str(sample_mid_episodes(1, 7)), "--runs-dir", "runs"], cwd=tmp_path,
                              env={**os.environ, "PYTHONUNBUFFERED": "1", **FAST_CHECKS}, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)
        procs.procs.append(ev)
        assert ev.stdout is not None
        seen = ""
        while "no evaluator stores run unstored" not in " ".join(seen.split()):
            assert time.monotonic() - started < HANG_BOUND_S and ev.poll() is None, seen
            seen += ev.stdout.readline()
        out, _ = ev.communicate(timeout=HANG_BOUND_S)
        text = " ".join((seen + out).split())
        assert f"start one with `agos evaluator --connect {procs.endpoint} --run unstored`" in text
        assert ev.returncode == 3, text
        assert "stopping: no evaluator stored the records of" in text
    finally:
        procs.close()


def test_demo_connect_names_what_is_missing(tmp_path) -> None:
    """``agos demo --connect`` on a router with nothing else: the same lines as ``agos eval``, at its first
    presence check."""
    procs = _Procs(tmp_path, 18000)
    try:
        started = time.monotonic()
        demo = subprocess.Popen([*AGOS, "demo", "--connect", procs.endpoint, "--run", "handmade", "--runs-dir", "runs"],
                                cwd=tmp_path, env={**os.environ, "PYTHONUNBUFFERED": "1", **FIRST_CHECK_SOONER},
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        procs.procs.append(demo)
        assert demo.stdout is not None
        seen = ""
        while "no UGV agent" not in seen:
            assert time.monotonic() - started < HANG_BOUND_S and demo.poll() is None, seen
            seen += demo.stdout.readline()
        text = " ".join(seen.split())
        assert f"start one with `agos world --connect {procs.endpoint} --run handmade`" in text
        assert "no evaluator stores run handmade" in text
        demo.send_signal(signal.SIGINT)
        demo.wait(timeout=HANG_BOUND_S)
        assert demo.returncode == 130
    finally:
        procs.close()


def test_check_agent_names_the_start_command_and_other_runs(tmp_path, running_system) -> None:
    """``agos check agent`` with the UAV agent started under another run id: one failed check that
    names the start command, a line naming the other run, exit 1, all within the agent wait."""
    running_system.start("agent", "--role", "uav", "--connect", running_system.endpoint, "--run", "checked-typo")
    time.sleep(2.0)  # its token is up
    out = subprocess.run([*AGOS, "check", "agent", "--connect", running_system.endpoint, "--run", "checked",
                          "--agent-wait", "3"], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    text = " ".join(out.stdout.split())
    assert out.returncode == 1, text
    assert "agos agent --role uav --run checked --connect" in text
    assert "checked-typo (uav)" in text


def test_a_wrong_port_is_one_line_and_exit_2_in_every_command(tmp_path, sample_mid_episodes) -> None:
    """Nothing listens on the port: each command says so in one line naming the endpoint and what to
    check, and exits 2."""
    endpoint = f"tcp/127.0.0.1:{free_port(18200)}"
    split = str(sample_mid_episodes(1, 3))
    commands = {
        "eval": ["eval", "--connect", endpoint, "--run", "x", "--split", split, "--runs-dir", "runs"],
        "demo": ["demo", "--connect", endpoint, "--run", "x", "--runs-dir", "runs"],
        "world": ["world", "--connect", endpoint, "--run", "x"],
        "agent": ["agent", "--role", "uav", "--connect", endpoint, "--run", "x"],
        "evaluator": ["evaluator", "--connect", endpoint],
        "watch": ["watch", "--connect", endpoint],
        "check": ["check", "agent", "--connect", endpoint],
    }
    procs = {name: subprocess.Popen([*AGOS, *argv], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                    text=True) for name, argv in commands.items()}
    for name, proc in procs.items():
        out, err = proc.communicate(timeout=HANG_BOUND_S)
        assert proc.returncode == 2, (name, out, err)
        errors = [line for line in err.splitlines() if line.strip() and " INFO " not in line]  # one line, no more
        assert len(errors) == 1 and f"agos {name}: cannot reach the zenoh router at {endpoint}" in errors[0], err
        assert "Traceback" not in out + err


def test_eval_without_a_world_worker_stops_after_three_checks(tmp_path, sample_mid_episodes, running_system) -> None:
    """Evaluator and agents but no world worker (the shared system): the start command at a presence
    check, exit 3 after three presence checks (3 s apart here), with the resume command."""
    endpoint, run = running_system.endpoint, running_system.run
    out = subprocess.run([*AGOS, "eval", "--connect", endpoint, "--run", run, "--split",
                          str(sample_mid_episodes(1, 7)), "--runs-dir", "runs"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=120, env={**os.environ, **FAST_CHECKS})
    text = " ".join(out.stdout.split())
    assert out.returncode == 3, text
    assert f"no world worker serves run {run}: start one with `agos world --connect {endpoint}" in text
    assert f"stopping: no world worker joined run {run}" in text and "agos eval --resume" in text
