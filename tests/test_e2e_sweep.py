"""`agos sweep`: Ctrl-C keeps every finished episode, and the next run of the same sweep plays only the
rest and writes what an uninterrupted sweep writes; a finished sweep given another value plays only
it. One worker process (the same pool as with several) plays the two points in order, so Ctrl-C after
the first episode is stored interrupts the second.
The pool of a sweep's workers names one that dies (issue 39, item 2): its signal and its log's last lines."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from agos.runtime.deaths import ChildDied
from agos.runtime.process import interruptible_imap

from support.crash import fail_on, segfault_on
from support.interrupt import HANG_BOUND_S

pytestmark = pytest.mark.e2e
AGOS = [sys.executable, "-m", "agos.deploy.cli"]


def _sweep(split: Path, out: Path, values: str = "0,0.5") -> list[str]:
    return [*AGOS, "sweep", "--split", str(split), "--param", "loss.p", "--values", values, "--seeds", "0",
            "--workers", "1", "--out", str(out)]


def test_interrupted_sweep_resumes_to_the_same_table(tmp_path, sample_mid_episodes) -> None:
    split = sample_mid_episodes(1, 11)  # 2 points x 1 episode, in order on one worker process
    # The clean table comes from a finished one-value sweep given a second value: it plays only that one.
    first = subprocess.run(_sweep(split, tmp_path / "clean", "0"), capture_output=True, text=True, timeout=300)
    assert first.returncode == 0, first.stderr
    (played,) = (tmp_path / "clean" / ".episodes").glob("*.jsonl")
    stamp = played.stat().st_mtime_ns
    clean = subprocess.run(_sweep(split, tmp_path / "clean"), capture_output=True, text=True, timeout=300)
    assert clean.returncode == 0, clean.stderr
    assert played.stat().st_mtime_ns == stamp  # the point already played was not played again
    assert len(list((tmp_path / "clean" / ".episodes").glob("*.jsonl"))) == 2

    out = tmp_path / "cut"
    proc = subprocess.Popen(_sweep(split, out), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not any(f.stat().st_size for f in (out / ".episodes").glob("*.jsonl")) if (out / ".episodes").exists() else True:
        assert time.monotonic() < deadline and proc.poll() is None
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=HANG_BOUND_S)  # it stops (a hang, not a speed: tests/support/interrupt.py)
    assert proc.returncode == 130
    assert "Traceback" not in proc.stderr.read()
    kept = sum(len(f.read_text().splitlines()) for f in (out / ".episodes").glob("*.jsonl"))
    assert kept == 1  # the first point's episode; the second was in play

    again = subprocess.run(_sweep(split, out), capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert (out / "sweep.csv").read_text() == (tmp_path / "clean" / "sweep.csv").read_text()


def test_a_pool_worker_that_dies_is_named_with_its_signal_and_its_log(tmp_path) -> None:
    """What ``agos sweep`` (and ``agos episodes split``) run their episodes on: a worker killed by SIGSEGV
    stops the pool at once (multiprocessing's pool waited for it forever), named with its signal and the
    fault handler's traceback its log holds; an exception in a worker is raised as it was."""
    got = []
    with pytest.raises(ChildDied) as died:
        for item in interruptible_imap(segfault_on, [0, 1, 2], 1, name="sweep", log_dir=tmp_path):
            got.append(item)
    assert got == [0] and (died.value.name, died.value.returncode) == ("sweep-0", -signal.SIGSEGV)
    said = str(died.value).splitlines()
    assert said[0] == f"sweep-0 died: killed by SIGSEGV (Segmentation fault); the last lines of {tmp_path / 'sweep-0.log'}:"
    assert said[1] == "    Fatal Python error: Segmentation fault" and "in segfault_on" in said[3], said
    with pytest.raises(ValueError, match="item 1 is refused"):
        list(interruptible_imap(fail_on, [0, 1], 1))
