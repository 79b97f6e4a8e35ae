"""Helpers shared by the test modules."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

AGOS = [sys.executable, "-m", "agos.runtime.cli"]


@pytest.fixture(scope="session")
def sample_mid_episodes(tmp_path_factory) -> Callable[[int, int], Path]:
    """``sample(n, seed)``: a JSONL file of ``n`` mid-difficulty grid-s7 episodes, sampled by the CLI."""

    def sample(n: int, seed: int) -> Path:
        path = tmp_path_factory.mktemp("episodes") / "eps.jsonl"
        subprocess.run([*AGOS, "episodes", "sample", "--town", "grid-s7", "--difficulty", "mid", "-n", str(n),
                        "--seed", str(seed), "--out", str(path)], check=True, capture_output=True, timeout=120)
        return path

    return sample
