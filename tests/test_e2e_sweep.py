"""`agos sweep`: Ctrl-C keeps every finished episode, and the next run of the same sweep plays only the
rest and writes what an uninterrupted sweep writes. One worker process (the same pool as with several)
plays the two points in order, so Ctrl-C after the first episode is stored interrupts the second."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.e2e
AGOS = [sys.executable, "-m", "agos.deploy.cli"]


def _sweep(split: Path, out: Path) -> list[str]:
    return [*AGOS, "sweep", "--split", str(split), "--param", "loss.p", "--values", "0,0.5", "--seeds", "0",
            "--workers", "1", "--out", str(out)]


def test_interrupted_sweep_resumes_to_the_same_table(tmp_path, sample_mid_episodes) -> None:
    split = sample_mid_episodes(1, 11)  # 2 points x 1 episode, in order on one worker process
    clean = subprocess.run(_sweep(split, tmp_path / "clean"), capture_output=True, text=True, timeout=300)
    assert clean.returncode == 0, clean.stderr

    out = tmp_path / "cut"
    proc = subprocess.Popen(_sweep(split, out), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not any(f.stat().st_size for f in (out / ".episodes").glob("*.jsonl")) if (out / ".episodes").exists() else True:
        assert time.monotonic() < deadline and proc.poll() is None
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    stopped = time.monotonic()
    proc.wait(timeout=10)
    assert proc.returncode == 130 and time.monotonic() - stopped < 10
    assert "Traceback" not in proc.stderr.read()
    kept = sum(len(f.read_text().splitlines()) for f in (out / ".episodes").glob("*.jsonl"))
    assert kept == 1  # the first point's episode; the second was in play

    again = subprocess.run(_sweep(split, out), capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert (out / "sweep.csv").read_text() == (tmp_path / "clean" / "sweep.csv").read_text()
    assert not (out / ".episodes").exists()
