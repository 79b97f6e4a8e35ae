"""The control-plane benchmark still runs end to end: the real router, evaluator and ``agos eval
--connect`` against a simulated world worker (the real lease loop), every episode stored. Its figures
are read by people, not asserted (wall-clock numbers on a shared machine); its key census is
asserted: the key space the router holds and the keys samples are put on are the same after 50
episodes as after 5, and none names an episode (docs/ARCHITECTURE.md §2, "Why no key names an
episode"; before the slot key space the census grew by 7 keys an episode)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.e2e
BENCH = Path(__file__).resolve().parents[1] / "bench" / "bench_control_plane.py"


def test_control_plane_stores_every_episode_and_its_key_space_stays_put(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, str(BENCH), "--quick", "--workers", "1", "--episodes-per-worker", "55",
                          "--episode-s", "0.05", "--decision-s", "0.02", "--census", "5,50", "--work", str(tmp_path)],
                         capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    line = re.search(r"^control plane N=1: lease p50 (\d+) ms p99 (\d+) ms, ([0-9.]+) records/s, lost 0$", out.stdout, re.M)
    assert line, out.stdout[-3000:]
    assert int(line.group(1)) <= int(line.group(2))
    assert float(line.group(3)) > 0
    assert re.search(r"│\s+55 / 0\s+│", out.stdout), out.stdout[-3000:]  # 55 records stored, each a valid finished one
    census = re.search(r"^key census: (\d+) after 5 records, (\d+) after 50 records; 0 new; 0 naming an episode$",
                       out.stdout, re.M)
    assert census, out.stdout[-3000:]
    assert int(census.group(1)) == int(census.group(2)) > 20  # the router's declarations are in it, not only puts
