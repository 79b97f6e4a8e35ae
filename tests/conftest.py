"""Helpers shared by the test modules."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from support.processes import stop_all

# Fails a test that starts a process or opens a socket unless it is marked e2e or loopback (process_guard.py).
pytest_plugins = ["process_guard"]

AGOS = [sys.executable, "-m", "agos.deploy.cli"]


@pytest.fixture(scope="session")
def sample_mid_episodes(tmp_path_factory) -> Callable[[int, int], Path]:
    """``sample(n, seed)``: a JSONL file of ``n`` mid-difficulty grid-s7 episodes, as ``agos episodes sample``
    writes it (the command run in this process, once per ``(n, seed)``; the file is shared, never write it)."""
    from agos.deploy.cli import main

    made: dict[tuple[int, int], Path] = {}  # one file per (n, seed) in a test process: tests only read it

    def sample(n: int, seed: int) -> Path:
        if (n, seed) not in made:
            path = tmp_path_factory.mktemp("episodes") / "eps.jsonl"
            code = main(["episodes", "sample", "--town", "grid-s7", "--difficulty", "mid", "-n", str(n),
                         "--seed", str(seed), "--out", str(path)])
            assert code == 0, f"agos episodes sample exited {code}"
            made[n, seed] = path
        return made[n, seed]

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
    from agos import Env
    from agos.agents.registry import make_policy
    from agos.runtime.episode_config import EpisodeConfig
    from agos.world.episodes.sampling import generate_episodes
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import open_town

    town = open_town("grid-s7")
    seen: list = []
    policies = {r: make_policy("heuristic", r) for r in ("uav", "ugv")}
    with Scene(town.layout, look="flat") as scene:
        spec = generate_episodes(town, scene, per_difficulty=1, seed=1)[0]
        with Env(spec, EpisodeConfig(look="flat"), run_id="t", scene=scene, town=town) as env:
            env.play(policies, seen=seen)
    return seen


class RunningSystem:
    """A router on a free loopback port, an evaluator serving every run, and a UAV and a UGV agent
    (heuristic) on run ``run``: the processes of ``agos eval --connect`` minus the world, started once
    and shared by the e2e tests that need only them. Start other processes beside it with
    :meth:`start`; the ``running_system`` fixture stops those after each test."""

    def __init__(self, cwd: Path, run: str = "shared") -> None:
        from agos.deploy.run.launcher import free_port, wait_listening

        self.cwd, self.run = cwd, run
        self.port = free_port(19700)
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self._base: list[subprocess.Popen] = []
        self._extra: list[subprocess.Popen] = []
        self._base.append(self._popen("router", "--listen", self.endpoint))
        assert wait_listening("127.0.0.1", self.port, 30), "the shared router never listened"
        self._base.append(self._popen("evaluator", "--connect", self.endpoint, "--runs-dir", "runs"))
        for role in ("uav", "ugv"):
            self._base.append(self._popen("agent", "--role", role, "--connect", self.endpoint, "--run", run))

    def _popen(self, *argv: str) -> subprocess.Popen:
        return subprocess.Popen([*AGOS, *argv], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=self.cwd)

    def start(self, *argv: str) -> subprocess.Popen:
        """``agos ARGV`` beside the system (output discarded), stopped at the end of the test."""
        proc = self._popen(*argv)
        self._extra.append(proc)
        return proc

    def stop_extra(self) -> None:
        stop_all(self._extra)
        self._extra.clear()

    def close(self) -> None:
        self.stop_extra()
        stop_all(self._base)

    def check_alive(self) -> None:
        exited = [p.args for p in self._base if p.poll() is not None]
        assert not exited, f"shared system processes exited: {exited}"


@pytest.fixture(scope="session")
def _running_system(tmp_path_factory) -> Iterator[RunningSystem]:
    system = RunningSystem(tmp_path_factory.mktemp("system"))
    try:
        yield system
    finally:
        system.close()


@pytest.fixture
def running_system(_running_system: RunningSystem) -> Iterator[RunningSystem]:
    """The shared :class:`RunningSystem` (e2e tests only); what a test starts beside it stops with the test."""
    _running_system.check_alive()
    try:
        yield _running_system
    finally:
        _running_system.stop_extra()
