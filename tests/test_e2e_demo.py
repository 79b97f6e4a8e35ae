"""End to end: `agos demo` launches router, evaluator, both agents and a world worker as
separate OS processes over a real zenoh router on loopback; an independent zenoh client
watches the bus; results land once each in a real SQLite file."""

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

from agos.deploy.run.launcher import free_port
from agos.runtime.bus import zenoh_config

pytestmark = pytest.mark.e2e
AGOS = [sys.executable, "-m", "agos.deploy.cli"]


def _start_demo(tmp_path: Path, port: int, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([*AGOS, "demo", "--port", str(port), "--runs-dir", str(tmp_path / "runs"), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path,
                            env={**os.environ, "COLUMNS": "120"})


def _read_until(proc: subprocess.Popen, marker: str, lines: list[str], timeout_s: float = 60.0) -> str | None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            return None
        lines.append(line)
        if marker in line:
            return line
    return None


def _processes_mentioning(text: str) -> list[int]:
    """Processes whose command line or environment names ``text`` (a run's children get the router's
    endpoint as AGOS_ZENOH__CONNECT or AGOS_ZENOH__LISTEN in their environment)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
                environ = (entry / "environ").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                continue
            if (text in cmdline or text in environ) and "pytest" not in cmdline:
                pids.append(int(entry.name))
    return pids


def test_demo_runs_episodes_end_to_end_and_the_bus_is_observable(tmp_path: Path) -> None:
    port = free_port(17447)
    proc = _start_demo(tmp_path, port, "--per-difficulty", "1")  # 3 episodes: each difficulty once
    lines: list[str] = []
    endpoint_line = _read_until(proc, "zenoh endpoint:", lines)
    assert endpoint_line is not None, "".join(lines)
    assert endpoint_line.strip() == f"zenoh endpoint: tcp/127.0.0.1:{port}"

    seen: dict[str, set[str]] = {}
    keys_heard: set[str] = set()
    episodes_heard: set[str] = set()
    bad: list[str] = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        data = msgpack.unpackb(sample.payload.to_bytes(), raw=False)
        with lock:
            if not isinstance(data, dict) or "v" not in data or "type" not in data:
                bad.append(key)
                return
            kind = key.split("/")[4] if key.split("/")[2] == "slot" else key.split("/")[2]
            seen.setdefault(kind + ("/" + key.split("/")[5] if kind in ("obs", "act") else ""), set()).add(data["type"])
            keys_heard.add(key)
            if isinstance(data.get("episode_id"), str):
                episodes_heard.add(data["episode_id"])

    observer = zenoh.open(zenoh_config(connect=[f"tcp/127.0.0.1:{port}"]))
    sub = observer.declare_subscriber("agos/**", on_sample)
    try:
        out, _ = proc.communicate(timeout=300)
    finally:
        sub.undeclare()
        observer.close()
    output = "".join(lines) + out
    assert proc.returncode == 0, output

    assert not bad, f"payloads without v/type on {bad[:5]}"
    assert seen.get("obs/uav") == {"observation"} and seen.get("obs/ugv") == {"observation"}, seen
    assert seen.get("act/uav") == {"action"} and seen.get("act/ugv") == {"action"}, seen
    assert {"episode_started", "step"} <= seen.get("events", set()), seen
    assert seen.get("result") == {"episode_record"}, seen
    assert "run_manifest" in seen.get("ctl", set()), seen
    # The key space is bounded (docs/ARCHITECTURE.md §2): episodes travel in payloads, no key names one.
    assert len(episodes_heard) == 3, episodes_heard
    assert not [k for k in keys_heard if set(k.split("/")) & episodes_heard], sorted(keys_heard)

    results = [line for line in output.splitlines() if line.startswith("results: ")]
    assert results, output
    db_path = Path(results[0].removeprefix("results: ").strip())
    db = sqlite3.connect(db_path)
    rows = db.execute("SELECT episode_id, difficulty, status, success, record_json FROM episodes").fetchall()
    assert len(rows) == 3 and len({r[0] for r in rows}) == 3
    assert sorted(r[1] for r in rows) == ["easy", "hard", "mid"]
    assert all(r[2] == "finished" for r in rows), [json.loads(r[4])["error"] for r in rows]
    easy_confirmed = [r for r in rows if r[1] == "easy" and r[3] == 1]
    assert easy_confirmed, "the heuristic confirmed no easy target"
    for row in easy_confirmed:
        record = json.loads(row[4])
        assert record["termination"] == "confirmed" and record["n_confirm"] == 1
        assert record["candidates"][-1]["status"] == "confirmed"
    made_by = json.loads(rows[0][4])["provenance"]  # the world worker's, beside config (runtime/provenance.py)
    assert made_by["packages"]["pybullet"] and made_by["lock_sha256"]
    assert json.loads(db_path.with_name("run.json").read_text())["provenance"]["commit"] == made_by["commit"]
    for level in ("easy", "mid", "hard", "overall"):
        assert any(line.lstrip("│ ").startswith(level) for line in output.splitlines()), output
    assert not _processes_mentioning(f"tcp/127.0.0.1:{port}"), "processes left behind"


def test_ctrl_c_stops_every_process_and_exits_130(tmp_path: Path) -> None:
    port = free_port(17547)
    proc = _start_demo(tmp_path, port)
    lines: list[str] = []
    assert _read_until(proc, "zenoh endpoint:", lines) is not None, "".join(lines)
    time.sleep(4.0)  # let the workers start an episode
    assert _processes_mentioning(f"tcp/127.0.0.1:{port}"), "children were not started"
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 130, out  # like a shell's Ctrl-C: a script must not take it for a finished run
    assert "interrupted" in out
    time.sleep(0.5)
    assert not _processes_mentioning(f"tcp/127.0.0.1:{port}"), "processes left behind"


@pytest.mark.parametrize(("content", "expected"), [
    ('[world]\nugv_speed_mps = "fast"\n', "world.ugv_speed_mps"),
    ('[run]\nworkers = 0\n', "run.workers"),
    ('[world\n', "not valid TOML"),
    ('[wrold]\nx = 1\n', "wrold"),
])
def test_bad_config_is_one_clear_line(tmp_path: Path, content: str, expected: str) -> None:
    config = tmp_path / "bad.toml"
    config.write_text(content)
    proc = subprocess.run([*AGOS, "demo", "--config", str(config)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and str(config) in lines[0] and expected in lines[0], proc.stderr


def test_bad_episode_file_names_file_line_and_field(tmp_path: Path) -> None:
    good = tmp_path / "eps.jsonl"
    subprocess.run([*AGOS, "episodes", "sample", "--town", "grid-s7", "--out", str(good), "--per-difficulty", "1"], check=True,
                   capture_output=True, timeout=60)
    lines = good.read_text().splitlines()
    broken = json.loads(lines[1])
    del broken["target"]["colour"]
    bad = tmp_path / "bad.jsonl"
    bad.write_text("\n".join([lines[0], json.dumps(broken), lines[2]]) + "\n")
    proc = subprocess.run([*AGOS, "demo", "--episodes", str(bad), "--runs-dir", str(tmp_path / "runs")],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    err = proc.stderr.strip().splitlines()
    assert len(err) == 1 and f"{bad}:2" in err[0] and "target.colour" in err[0], proc.stderr
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())
