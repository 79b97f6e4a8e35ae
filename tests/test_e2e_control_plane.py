"""The control-plane benchmark still runs end to end in its quick form: the real router, evaluator and
``agos eval --connect`` against simulated world workers (the real lease loop), every episode stored.
Its figures are read by people, not asserted (wall-clock numbers on a shared machine)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.e2e
BENCH = Path(__file__).resolve().parents[1] / "bench" / "bench_control_plane.py"


def test_quick_control_plane_stores_every_episode(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, str(BENCH), "--quick", "--work", str(tmp_path)], capture_output=True, text=True,
                         timeout=180)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    line = re.search(r"^control plane N=5: lease p50 (\d+) ms p99 (\d+) ms, ([0-9.]+) records/s, lost 0$", out.stdout, re.M)
    assert line, out.stdout[-3000:]
    assert int(line.group(1)) <= int(line.group(2))
    assert float(line.group(3)) > 0
    assert re.search(r"│\s+10 / 0\s+│", out.stdout), out.stdout[-3000:]  # 10 records stored, each a valid finished one
