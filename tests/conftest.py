"""Helpers shared by the test modules."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

# Fails a test that starts a process or opens a socket unless it is marked e2e or loopback (process_guard.py).
pytest_plugins = ["process_guard"]

@pytest.fixture(scope="session")
def sample_mid_episodes(tmp_path_factory) -> Callable[[int, int], Path]:
    """``sample(n, seed)``: a JSONL file of ``n`` mid-difficulty grid-s7 episodes, as ``agos episodes sample``
    writes it (the command run in this process)."""
    from agos.deploy.cli import main

    def sample(n: int, seed: int) -> Path:
        path = tmp_path_factory.mktemp("episodes") / "eps.jsonl"
        code = main(["episodes", "sample", "--town", "grid-s7", "--difficulty", "mid", "-n", str(n),
                     "--seed", str(seed), "--out", str(path)])
        assert code == 0, f"agos episodes sample exited {code}"
        return path

    return sample


@pytest.fixture
def agos(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> Callable[..., CliResult]:
    """``agos(*args, env={...}, cwd=PATH)``: the ``agos`` command run in this process (``agos.deploy.cli.main``),
    its exit status and what it printed. For tests about what a command decides and says; a test about the
    command as a process (signals, pipes, the services it starts) runs it as a subprocess, marked e2e."""
    from agos.deploy.cli import main

    def run(*args: str | Path, env: dict[str, str] | None = None, cwd: Path | None = None) -> CliResult:
        with monkeypatch.context() as patch:
            for name, value in (env or {}).items():
                patch.setenv(name, value)
            if cwd is not None:
                patch.chdir(cwd)
            capsys.readouterr()
            try:
                code = main([str(a) for a in args])
            except SystemExit as exit_:  # argparse refusing the arguments
                code = exit_.code if isinstance(exit_.code, int) else 2
            out, err = capsys.readouterr()
        return CliResult(code, out, err)

    return run


@dataclass(frozen=True)
class CliResult:
    """What one in-process ``agos`` command did; the names match ``subprocess.CompletedProcess``'s."""

    returncode: int
    stdout: str
    stderr: str


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
