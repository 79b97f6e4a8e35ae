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
