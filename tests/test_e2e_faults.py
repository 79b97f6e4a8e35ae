"""Fault tolerance and determinism with real processes over a real router on loopback.

Each process is started by hand (as a user would on several hosts) and ``agos eval --connect``
orchestrates. The tests kill processes with SIGKILL mid-episode and check that every episode
ends up stored exactly once.
"""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import pytest
import zenoh

from agos.runtime.bus import zenoh_config
from agos.runtime.launcher import free_port, wait_listening

pytestmark = pytest.mark.e2e
AGOS = [sys.executable, "-m", "agos.runtime.cli"]


@pytest.fixture(scope="module")
def episodes(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("episodes") / "eps.jsonl"
    subprocess.run([*AGOS, "episodes", "sample", "--town", "grid-s7", "--difficulty", "mid", "-n", "4", "--seed", "2",
                    "--out", str(path)], check=True, capture_output=True, timeout=120)
    return path


class Cluster:
    """Router, evaluator, two agents and world workers, each a separate process."""

    def __init__(self, tmp: Path, run: str, workers: int = 2) -> None:
        self.tmp, self.run = tmp, run
        self.port = free_port(19000 + (os.getpid() % 500))
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.procs: dict[str, subprocess.Popen] = {}
        self.start("router", "router", "--listen", self.endpoint)
        assert wait_listening("127.0.0.1", self.port, 15.0)
        self.start("evaluator", "evaluator", "--connect", self.endpoint, "--runs-dir", "runs")
        for role in ("uav", "ugv"):
            self.start_agent(role)
        for k in range(workers):
            self.start(f"w{k}", "world", "--connect", self.endpoint, "--run", run, "--worker-id", f"w{k}")

    def start(self, name: str, *args: str) -> None:
        log = (self.tmp / f"{name}.log").open("ab")
        self.procs[name] = subprocess.Popen([*AGOS, *args], cwd=self.tmp, stdout=log, stderr=subprocess.STDOUT)

    def start_agent(self, role: str) -> None:
        self.start(f"agent-{role}", "agent", "--role", role, "--connect", self.endpoint, "--run", self.run)

    def kill(self, name: str) -> None:
        self.procs[name].send_signal(signal.SIGKILL)
        self.procs[name].wait(timeout=10)

    def eval(self, episodes: Path, *extra: str) -> subprocess.Popen:
        return subprocess.Popen([*AGOS, "eval", "--connect", self.endpoint, "--run", self.run, "--split", str(episodes),
                                 "--runs-dir", "runs", *extra], cwd=self.tmp, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True)

    def close(self) -> None:
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in self.procs.values():
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()

    def records(self) -> list[dict]:
        db = sqlite3.connect(self.tmp / "runs" / self.run / "results.sqlite")
        rows = db.execute("SELECT episode_id, record_json FROM episodes").fetchall()
        return [json.loads(r) for _, r in rows]


class Watcher:
    """A zenoh client that records which worker started which episode, and step events."""

    def __init__(self, endpoint: str, *, delay_s: float = 0.0) -> None:
        self.started: dict[str, str] = {}
        self.steps = 0
        self.delay_s = delay_s
        self.lock = threading.Lock()
        self.session = zenoh.open(zenoh_config(connect=[endpoint]))
        self.sub = self.session.declare_subscriber("agos/**", self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        if self.delay_s:
            time.sleep(self.delay_s)  # a slow observer: its work happens in the callback on purpose
        data = msgpack.unpackb(sample.payload.to_bytes(), raw=False)
        with self.lock:
            if data.get("type") == "episode_started":
                self.started[data["episode_id"]] = data["worker_id"]
            elif data.get("type") == "step":
                self.steps += 1

    def wait(self, predicate, timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self.lock:
                if predicate(self):
                    return
            time.sleep(0.05)
        raise AssertionError("timed out waiting for the cluster")

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def _finish(proc: subprocess.Popen, timeout_s: float = 240.0) -> str:
    out, _ = proc.communicate(timeout=timeout_s)
    assert proc.returncode == 0, out
    return out


def _one_finished_record_each(records: list[dict], n: int) -> None:
    assert len(records) == n and len({r["episode_id"] for r in records}) == n
    assert all(r["status"] == "finished" for r in records), [r.get("error") for r in records]


def test_killed_world_worker_episode_completes_on_another(tmp_path: Path, episodes: Path) -> None:
    cluster = Cluster(tmp_path, "kill-worker")
    watcher = Watcher(cluster.endpoint)
    try:
        proc = cluster.eval(episodes)
        watcher.wait(lambda w: "w0" in w.started.values())
        victim = next(e for e, w in watcher.started.items() if w == "w0")
        cluster.kill("w0")
        out = _finish(proc)
        records = cluster.records()
        _one_finished_record_each(records, 4)
        assert next(r for r in records if r["episode_id"] == victim)["worker_id"] == "w1"
        assert "re-leased episodes: 1" in out
    finally:
        watcher.close()
        cluster.close()


def test_killed_and_restarted_agent_service_run_completes(tmp_path: Path, episodes: Path) -> None:
    cluster = Cluster(tmp_path, "kill-agent", workers=1)
    watcher = Watcher(cluster.endpoint)
    try:
        proc = cluster.eval(episodes)
        watcher.wait(lambda w: w.steps >= 3)
        cluster.kill("agent-ugv")
        time.sleep(1.0)
        cluster.start_agent("ugv")
        _finish(proc)
        records = cluster.records()
        _one_finished_record_each(records, 4)
        # a re-requested decision is one decision: no episode counts more decisions than steps allow
        assert all(r["decisions_uav"] + r["decisions_ugv"] <= 80 for r in records)
    finally:
        watcher.close()
        cluster.close()


def test_router_restart_clients_reconnect_and_run_completes(tmp_path: Path, episodes: Path) -> None:
    cluster = Cluster(tmp_path, "router-restart")
    watcher = Watcher(cluster.endpoint)
    try:
        proc = cluster.eval(episodes)
        watcher.wait(lambda w: w.steps >= 3)
        cluster.kill("router")
        time.sleep(2.0)
        cluster.start("router", "router", "--listen", cluster.endpoint)
        _finish(proc)
        _one_finished_record_each(cluster.records(), 4)
    finally:
        watcher.close()
        cluster.close()


def _summaries(records: list[dict]) -> dict[str, dict]:
    volatile = {"wall_time_s", "worker_id", "run_id"}
    return {r["episode_id"]: {k: v for k, v in r.items() if k not in volatile} for r in records}


def test_same_results_with_one_or_two_workers_and_with_a_slow_observer(tmp_path: Path, episodes: Path) -> None:
    results = {}
    for name, workers, slow_observer in (("one", 1, False), ("two", 2, False), ("observed", 1, True)):
        run_dir = tmp_path / name
        run_dir.mkdir()
        cluster = Cluster(run_dir, f"det-{name}", workers=workers)
        watcher = Watcher(cluster.endpoint, delay_s=0.02) if slow_observer else None
        try:
            _finish(cluster.eval(episodes, "--comm", "lossy"))
            results[name] = _summaries(cluster.records())
        finally:
            if watcher:
                watcher.close()
            cluster.close()
    assert len(results["one"]) == 4
    assert results["one"] == results["two"] == results["observed"]
