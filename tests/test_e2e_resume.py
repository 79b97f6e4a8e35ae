"""`agos eval` interrupted with Ctrl-C, then `--resume`: every episode stored exactly once. On the way,
one of its two world workers crashes (SIGSEGV, sent by the test): the console names it and its signal
once, the run goes on with the other, and the worker's log holds the fault handler's traceback."""

from __future__ import annotations

import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from agos.deploy.run.launcher import free_port

pytestmark = pytest.mark.e2e
AGOS = [sys.executable, "-m", "agos.deploy.cli"]


def _rows(db: Path) -> list[tuple[str, str]]:
    if not db.exists():
        return []
    try:
        with sqlite3.connect(db) as conn:
            return list(conn.execute("SELECT episode_id, status FROM episodes"))
    except sqlite3.OperationalError:  # the evaluator made the file and has not created the table yet
        return []


def test_interrupted_eval_resumes_and_stores_each_episode_once(tmp_path, sample_mid_episodes) -> None:
    episodes = sample_mid_episodes(3, seed=5)
    run_dir = tmp_path / "run"
    db = run_dir / "results.sqlite"
    port = str(free_port(23000 + os.getpid() % 400))
    first = subprocess.Popen([*AGOS, "eval", "--split", str(episodes), "--run-dir", str(run_dir), "--port", port,
                              "--workers", "2"],
                             cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + 180
    while len(_rows(db)) < 1 and time.monotonic() < deadline and first.poll() is None:
        time.sleep(0.2)
    world_1 = run_dir / "logs" / "world-1.log"
    pid = int(re.findall(r" world\[(\d+)\] ", world_1.read_text())[-1])
    os.kill(pid, signal.SIGSEGV)  # as a crash in native code (the EGL renderer's, issue 39) ends it
    while Path(f"/proc/{pid}").exists() and time.monotonic() < deadline:  # until agos eval has reaped it
        time.sleep(0.05)
    time.sleep(0.6)  # its next look (every 0.25 s) names it
    first.send_signal(signal.SIGINT)
    out, _ = first.communicate(timeout=60)
    done_first = len(_rows(db))
    assert out.count("world-1 died: killed by SIGSEGV (Segmentation fault); the last lines of ") == 1, out
    said = out[out.index("world-1 died"):]
    assert "    Fatal Python error: Segmentation fault" in said and "    Current thread 0x" in said, said[:3000]
    assert "Fatal Python error: Segmentation fault" in world_1.read_text()
    assert "world-0 died" not in out, out  # stopped by agos itself at the end: not a death to report
    assert first.returncode == (0 if done_first == 3 else 130), out  # interrupted: 130, like a shell
    if done_first < 3:  # Ctrl-C landed before the end: the run says how to resume
        assert f"agos eval --resume {run_dir}" in " ".join(out.split())
    second = subprocess.run([*AGOS, "eval", "--resume", str(run_dir), "--port", port], cwd=tmp_path,
                            capture_output=True, text=True, timeout=300)
    assert second.returncode == 0, second.stdout + second.stderr
    assert f"{done_first} of 3 episodes already finished" in " ".join(second.stdout.split())
    rows = _rows(db)
    assert sorted(eid for eid, _ in rows) == sorted(json.loads(line)["episode_id"] for line in episodes.read_text().splitlines())
    assert all(status == "finished" for _, status in rows)
    if done_first < 3:  # the resume started two workers again, and appended to the first attempt's logs
        world_1 = (run_dir / "logs" / "world-1.log").read_text()
        assert world_1.count("===== agos world started") == 2, world_1[:2000]
