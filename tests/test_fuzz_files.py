"""The readers of agos's input files, fuzzed with Hypothesis (issue 30): episode files (``agos episodes
check``, as every command that reads a split), comm profiles (``--comm FILE``) and settings files
(``--config FILE``). Every mutation of a valid file (tests/support/mutations.py) ends in one line on
stderr and exit 2 through the in-process CLI, or is accepted; none raises a traceback.

``agos eval --split MISSING`` fails at the split only after it has read the profile and the settings,
so it exits 2 for every mutation: on the mutated file's own line when that file is refused, else on the
missing split's. Nothing starts: these are unit tests (tests/process_guard.py)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import msgspec
import pytest
from hypothesis import HealthCheck, given, settings

from agos.runtime.codec import to_json
from agos.runtime.links import PROFILE_DIR, CommProfile, ProfileError, load_profile
from agos.runtime.settings import ConfigError, load_config

from support.episodes import grid_episodes
from support.mutations import jsonl_mutation, toml_mutation

EPISODE_CASES, PROFILE_CASES, CONFIG_CASES = 1000, 600, 600
"""2,200 generated cases in all, in about 20 s on one loaded core: what they cost is the suite's time
(``make check``), not a promise of these tests; a hang is pytest-timeout's (``timeout = 300`` in
pyproject.toml, 15 times that)."""
ROOT = Path(__file__).resolve().parents[1]


def fuzz(cases: int) -> settings:
    """Hypothesis's settings here: ``cases`` examples, no deadline per example (pytest-timeout catches a
    hang), no example database written to the working tree."""
    return settings(max_examples=cases, deadline=None, database=None, print_blob=True,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much])


@pytest.fixture
def quick_cli(agos, monkeypatch: pytest.MonkeyPatch):
    """The ``agos`` fixture with its argument parser built once: building it (all commands) is most of
    an in-process command's time, and parsing does not change it."""
    from agos.deploy import cli

    parser = cli.build_parser()
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    return agos


@pytest.fixture(scope="module")
def valid_episodes() -> list[dict[str, Any]]:
    """Three episodes that pass ``agos episodes check`` on grid-s7, as JSON objects."""
    return [msgspec.json.decode(to_json(s)) for s in grid_episodes()]


def _one_line(text: str) -> str:
    lines = text.strip().splitlines()
    assert len(lines) == 1 and lines[0].strip(), f"not one line: {text!r}"
    return lines[0]


def test_the_seeds_are_valid(quick_cli, valid_episodes, tmp_path: Path) -> None:
    """What is mutated is accepted before it is."""
    path = tmp_path / "eps.jsonl"
    path.write_bytes(b"".join(msgspec.json.encode(e) + b"\n" for e in valid_episodes))
    out = quick_cli("episodes", "check", path)
    assert out.returncode == 0 and "3 valid episodes on grid-s7" in out.stdout, out.stderr
    assert len(sorted(PROFILE_DIR.glob("*.toml"))) >= 5
    load_config(ROOT / "deploy" / "configs" / "demo.toml")


def test_fuzzed_episode_files_end_in_one_line_or_are_accepted(quick_cli, valid_episodes, tmp_path: Path) -> None:
    path = tmp_path / "eps.jsonl"
    seen: Counter[int] = Counter()

    @fuzz(EPISODE_CASES)
    @given(jsonl_mutation(valid_episodes))
    def case(data: bytes) -> None:
        path.write_bytes(data)
        out = quick_cli("episodes", "check", path)
        seen[out.returncode] += 1
        if out.returncode == 0:
            assert "valid episodes" in _one_line(out.stdout), out
        else:
            assert out.returncode == 2, out
            assert _one_line(out.stderr).startswith(f"episodes error: {path}"), out

    case()
    assert sum(seen.values()) >= EPISODE_CASES and seen[0] and seen[2], seen


def _eval_reading(quick_cli, tmp_path: Path, *flags: str | Path):
    """``agos eval FLAGS --split MISSING``: reads the settings and the profile, then fails on the split."""
    return quick_cli("eval", *flags, "--split", tmp_path / "missing.jsonl", "--runs-dir", tmp_path / "runs")


def test_fuzzed_comm_profiles_end_in_one_line_or_are_accepted(quick_cli, tmp_path: Path) -> None:
    path = tmp_path / "fuzzed.toml"
    seeds = [p.read_text() for p in sorted(PROFILE_DIR.glob("*.toml"))]
    seen: Counter[str] = Counter()

    for text in seeds:
        @fuzz(PROFILE_CASES // len(seeds) + 1)
        @given(toml_mutation(text))
        def case(data: bytes) -> None:
            path.write_bytes(data)
            try:
                accepted = isinstance(load_profile(path), CommProfile)
            except ProfileError as exc:
                accepted = False
                _one_line(str(exc))
            seen["accepted" if accepted else "refused"] += 1
            out = _eval_reading(quick_cli, tmp_path, "--comm", path)
            line = _one_line(out.stderr)
            assert out.returncode == 2, out
            assert ("missing.jsonl" in line) == accepted and (accepted or str(path) in line), out

        case()
    assert sum(seen.values()) >= PROFILE_CASES and seen["accepted"] and seen["refused"], seen


CONFIG_WITH_A_LINK = """[run]
policy_uav = "heuristic"
presence_check_s = 5.0
[world]
look = "flat"
decision_budget = 40
[world.comm]
name = "mine"
beacon_s = 2.0
[world.comm.loss]
model = "bernoulli"
p = 0.25
[[world.comm.blackouts]]
start_s = 10.0
end_s = 20.0
[vlm]
timeout_s = 5.0
"""


def test_fuzzed_settings_files_end_in_one_line_or_are_accepted(quick_cli, tmp_path: Path) -> None:
    path = tmp_path / "fuzzed.toml"
    seeds = [(ROOT / "deploy" / "configs" / "demo.toml").read_text(), CONFIG_WITH_A_LINK]
    seen: Counter[str] = Counter()

    for text in seeds:
        @fuzz(CONFIG_CASES // len(seeds))
        @given(toml_mutation(text))
        def case(data: bytes) -> None:
            path.write_bytes(data)
            try:
                load_config(path, environ={})
                accepted = True
            except ConfigError as exc:
                accepted = False
                _one_line(str(exc))
            seen["accepted" if accepted else "refused"] += 1
            out = _eval_reading(quick_cli, tmp_path, "--config", path)
            line = _one_line(out.stderr)
            assert out.returncode == 2, out
            assert accepted or str(path) in line, out

        case()
    assert sum(seen.values()) >= CONFIG_CASES and seen["accepted"] and seen["refused"], seen
