"""The runtime benchmark and the evaluation-at-model-speed one still run end to end (their goals are
checked by reading their output, not here: wall-clock figures do not belong in tests). Catches a
bench that no longer fits the runtime, e.g. an agent protocol change that leaves a hand-made world
unanswered."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.e2e
BENCH = Path(__file__).resolve().parents[1] / "bench" / "bench_runtime.py"


def test_round_trip_and_concurrency_parts_run() -> None:
    out = subprocess.run([sys.executable, str(BENCH), "--only", "roundtrip", "--only", "concurrency"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    ratio = re.search(r"decision round trip .*: ([0-9.]+)x \(median", out.stdout)
    rate = re.search(r"32 episodes, 200 ms agent\s+([0-9.]+) decisions/s", out.stdout)
    assert ratio and float(ratio.group(1)) > 0, out.stdout
    assert rate and float(rate.group(1)) > 0, out.stdout  # the bench fails if any episode went unanswered


def test_eval_bench_runs_a_real_eval_and_counts_every_round(sample_mid_episodes, tmp_path: Path) -> None:
    bench = Path(__file__).resolve().parents[1] / "bench" / "bench_eval.py"
    split = sample_mid_episodes(2, 5)
    out = subprocess.run([sys.executable, str(bench), "--split", str(split), "--episodes", "2", "--latency-ms", "50",
                          "--work", str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    assert "world workers: 2 (auto" in out.stdout, out.stdout[-3000:]
    ratio = re.search(r"ratio wall / max\(floors\)\s*│\s*([0-9.]+)x", out.stdout)
    assert ratio and float(ratio.group(1)) > 0, out.stdout[-3000:]
    assert "missed events" not in out.stdout  # every episode's rounds came from its step events
