"""End to end on a real CARLA town: import the OpenDRIVE file, sample solvable episodes, start
every process by hand over a real router, and give the world worker an empty asset cache so it
must fetch the town from the orchestrator over zenoh by its hash."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from agos.deploy.run.launcher import free_port, wait_listening

pytestmark = pytest.mark.e2e
AGOS = [sys.executable, "-m", "agos.deploy.cli"]
TOWN02 = Path(__file__).resolve().parents[2] / "shared" / "maps" / "carla" / "Town02.xodr"


@pytest.mark.skipif(not TOWN02.exists(), reason="CARLA maps not present")
def test_imported_town_runs_with_the_asset_fetched_over_zenoh(tmp_path: Path) -> None:
    orchestrator_cache, worker_cache = tmp_path / "cache-orchestrator", tmp_path / "cache-worker"
    env = {**os.environ, "AGOS_ASSET_CACHE": str(orchestrator_cache)}
    run = lambda *args: subprocess.run([*AGOS, *args], env=env, capture_output=True, text=True, timeout=120, cwd=tmp_path)  # noqa: E731
    imported = run("map", "import", str(TOWN02), "--out", str(tmp_path / "town02"))
    assert imported.returncode == 0, imported.stderr
    sampled = run("episodes", "sample", "--town", str(tmp_path / "town02"), "--difficulty", "easy", "-n", "2",
                  "--out", str(tmp_path / "eps.jsonl"))
    assert sampled.returncode == 0, sampled.stderr
    sha = next(p.name for p in orchestrator_cache.iterdir() if (p / "asset.msgpack").exists())  # not build/ or textures/

    port = free_port(18700)
    endpoint = f"tcp/127.0.0.1:{port}"
    common = ["--connect", endpoint, "--run", "imported"]
    procs = [subprocess.Popen([*AGOS, "router", "--listen", endpoint], cwd=tmp_path, env=env)]
    try:
        assert wait_listening("127.0.0.1", port, 15.0)
        procs += [
            subprocess.Popen([*AGOS, "evaluator", "--connect", endpoint, "--runs-dir", "runs"], cwd=tmp_path, env=env),
            subprocess.Popen([*AGOS, "agent", "--role", "uav", *common], cwd=tmp_path, env=env),
            subprocess.Popen([*AGOS, "agent", "--role", "ugv", *common], cwd=tmp_path, env=env),
            subprocess.Popen([*AGOS, "world", *common], cwd=tmp_path, env={**env, "AGOS_ASSET_CACHE": str(worker_cache)}),
        ]
        demo = subprocess.run([*AGOS, "demo", *common, "--runs-dir", "runs", "--episodes", "eps.jsonl"], cwd=tmp_path,
                              env=env, capture_output=True, text=True, timeout=240)
        assert demo.returncode == 0, demo.stdout + demo.stderr
    finally:
        for proc in reversed(procs):
            proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + 10
        for proc in procs:
            proc.wait(timeout=max(0.1, deadline - time.monotonic()))

    assert (worker_cache / sha / "asset.msgpack").exists(), "the worker did not fetch the asset"
    rows = sqlite3.connect(tmp_path / "runs" / "imported" / "results.sqlite").execute(
        "SELECT status, success FROM episodes").fetchall()
    assert len(rows) == 2 and all(status == "finished" for status, _ in rows)
    assert any(success for _, success in rows), "the heuristic confirmed no target on Town02"
