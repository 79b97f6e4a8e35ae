"""Helpers shared by the test modules."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

AGOS = [sys.executable, "-m", "agos.deploy.cli"]


@pytest.fixture(scope="session")
def sample_mid_episodes(tmp_path_factory) -> Callable[[int, int], Path]:
    """``sample(n, seed)``: a JSONL file of ``n`` mid-difficulty grid-s7 episodes, sampled by the CLI."""

    def sample(n: int, seed: int) -> Path:
        path = tmp_path_factory.mktemp("episodes") / "eps.jsonl"
        subprocess.run([*AGOS, "episodes", "sample", "--town", "grid-s7", "--difficulty", "mid", "-n", str(n),
                        "--seed", str(seed), "--out", str(path)], check=True, capture_output=True, timeout=120)
        return path

    return sample


@pytest.fixture(scope="session")
def observations() -> list:
    """Every observation of one heuristic episode on grid-s7 (search, handoff, six views)."""
    from agos.agents.inprocess import InProcessAgents
    from agos.agents.registry import make_policy
    from agos.world.episodes.sampling import generate_episodes
    from agos.world.sim.engine import EpisodeRunner
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import open_town

    town = open_town("grid-s7")
    scene = Scene(town.layout, look="flat")
    spec = generate_episodes(town, scene, per_difficulty=1, seed=1)[0]
    seen: list = []
    inner = InProcessAgents({r: make_policy("heuristic", r) for r in ("uav", "ugv")})

    class Spy:
        def decide(self, obs):
            seen.extend(obs.values())
            return inner.decide(obs)

    EpisodeRunner(scene, town, spec, run_id="t", worker_id="w").run(Spy())
    scene.close()
    return seen
