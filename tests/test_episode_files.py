"""Episode files are checked as a whole before anything runs (issue 30, item 1; world/episodes/files.py):
a duplicate episode id (both lines named), an episode whose town is not what this agos builds, one
whose waypoints its town lacks, one the run's look cannot draw. Every command that reads a split says
so in one line and exits 2, run here in-process: nothing may start (tests/process_guard.py)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import msgspec
import pytest

from agos.runtime.codec import to_json
from agos.runtime.schemas import EpisodeSpec
from agos.world.episodes.files import EpisodeFileError, read_episodes, read_split, write_episodes

from support.episodes import grid_episodes


@pytest.fixture(scope="module")
def specs() -> list[EpisodeSpec]:
    return grid_episodes()


def _lines(specs: list[EpisodeSpec]) -> list[dict[str, Any]]:
    return [json.loads(to_json(s)) for s in specs]


def _write(path: Path, lines: list[dict[str, Any]]) -> Path:
    path.write_text("".join(json.dumps(line) + "\n" for line in lines))
    return path


def _one_line(text: str) -> str:
    lines = text.strip().splitlines()
    assert len(lines) == 1, text
    return lines[0]


def test_the_episodes_pass(tmp_path: Path, specs: list[EpisodeSpec]) -> None:
    path = tmp_path / "eps.jsonl"
    write_episodes(path, specs)
    assert read_split(path, look="rich") == specs == read_episodes(path)


def test_a_duplicate_episode_id_is_refused_by_every_command_that_reads_a_split(tmp_path: Path, specs, agos) -> None:
    lines = _lines(specs)
    again = {**lines[0], "seed": 99}  # the same id, another episode
    path = _write(tmp_path / "dup.jsonl", [*lines, {}, again][:3] + [again])
    path.write_text(path.read_text().replace("\n", "\n\n", 1))  # a blank line still counts as a line
    says = f"{path}:5: episode id {specs[0].episode_id} again (first at line 1)"
    with pytest.raises(EpisodeFileError, match=r"dup\.jsonl:5: episode id .* again \(first at line 1\)"):
        read_episodes(path)
    runs, out = tmp_path / "runs", tmp_path / "out"
    for argv in (("episodes", "check", path), ("eval", "--split", path, "--runs-dir", runs),
                 ("demo", "--episodes", path, "--runs-dir", runs), ("dataset", "build", "--split", path, "--out", out),
                 ("sweep", "--split", path, "--out", out)):
        done = agos(*argv, cwd=tmp_path)
        assert done.returncode == 2 and says in _one_line(done.stderr), (argv, done)
    assert not runs.exists() and not out.exists()


@pytest.mark.parametrize(("change", "says"), [
    ({"asset_sha256": "ab" * 32}, "episode expects asset sha256 abababababab"),
    ({"town": {"generator": "grid", "seed": 7, "town_id": "grid-s8"}}, "'town.town_id': 'grid-s8', but generator grid "
                                                                        "with seed 7 builds grid-s7"),
    ({"town": {"generator": "grid", "seed": 8, "town_id": "grid-s8"}}, "town grid-s8: episode expects asset sha256"),
    ({"town": {"generator": "maze", "seed": 7, "town_id": "maze-s7"}}, "unknown town generator 'maze'"),
    ({"town": {"generator": "opendrive", "seed": 0, "town_id": "Town01"}}, "agos map import"),
    ({"uav_start_waypoint": "U99_99"}, "'uav_start_waypoint': 'U99_99' is not a UAV node of grid-s7"),
    ({"active_uav_waypoints": ["U1_1", "nowhere"]}, "'active_uav_waypoints': 'nowhere' is not a UAV node"),
    ({"ugv_start_waypoint": "R99999999"}, "'ugv_start_waypoint': 'R99999999' is not a road waypoint of grid-s7"),
    ({"ugv_start_waypoint": "U1_1"}, "is not a road waypoint id"),
])
def test_an_episode_its_town_does_not_match_is_refused(tmp_path: Path, specs, change: dict, says: str) -> None:
    lines = _lines(specs)
    path = _write(tmp_path / "eps.jsonl", [lines[0], {**lines[1], **change}, lines[2]])
    read_episodes(path)  # the file alone is fine
    with pytest.raises(EpisodeFileError) as caught:
        read_split(path)
    assert str(caught.value).startswith(f"{path}:2: episode {specs[1].episode_id}: ") and says in str(caught.value)


def test_eval_refuses_a_town_mismatch_before_starting_anything(tmp_path: Path, specs, agos) -> None:
    lines = _lines(specs)
    path = _write(tmp_path / "eps.jsonl", [lines[0], {**lines[1], "ugv_start_waypoint": "R99999999"}])
    done = agos("eval", "--split", path, "--runs-dir", tmp_path / "runs")
    assert done.returncode == 2 and f"{path}:2: episode {specs[1].episode_id}: field 'ugv_start_waypoint'" in done.stderr
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize(("change", "says"), [
    ({"episode_id": "a/b"}, "field 'episode_id': episode id 'a/b' is not a valid name"),
    ({"episode_id": "-rf"}, "field 'episode_id'"),
    ({"asset_sha256": "afdc"}, "field 'asset_sha256': 'afdc' is not a sha256"),
    ({"seed": -1}, "field 'seed': -1 is negative"),
    ({"region_world_m": [10.0, 0.0, 0.0, 10.0]}, "field 'region_world_m'"),
    ({"target": {"model": "sedan", "colour": "red", "position_world_m": [1e6, 0.0, 0.0], "yaw_rad": 0.0}},
     "field 'target.position_world_m': (1e+06, 0) lies outside the region"),
    ({"decision_budget": 0}, "field 'decision_budget': 0: give at least 1"),
    ({"active_uav_waypoints": []}, "field 'active_uav_waypoints': empty"),
    ({"distractors": [{"model": "tank", "colour": "red", "position_world_m": [0.0, 0.0, 0.0], "yaw_rad": 0.0}]},
     "field 'distractors.0.model': 'tank' is not a body type"),
    ({"difficulty": "nightmare"}, "field 'difficulty'"),
    ({"episode_id": "two\nlines"}, "'two\\nlines'"),  # one line, whatever the file holds
])
def test_an_episode_is_checked_on_its_own_line(tmp_path: Path, specs, change: dict, says: str) -> None:
    lines = _lines(specs)
    path = _write(tmp_path / "eps.jsonl", [lines[0], {**lines[1], **change}])
    with pytest.raises(EpisodeFileError) as caught:
        read_episodes(path)
    assert str(caught.value).startswith(f"{path}:2: ") and says in str(caught.value)
    assert "\n" not in str(caught.value)


def test_a_run_whose_look_cannot_draw_an_episode_is_refused_before_it_starts(tmp_path: Path, specs, agos) -> None:
    """The one setting an episode file implies: the hard episode's two-tone look-alike needs the rich look.
    A flat run used to start and store it as invalid; now it does not start."""
    path = tmp_path / "eps.jsonl"
    write_episodes(path, specs)
    flat = {"AGOS_WORLD__LOOK": "flat"}
    done = agos("eval", "--split", path, "--runs-dir", tmp_path / "runs", env=flat)
    line = _one_line(done.stderr)
    assert done.returncode == 2 and f"{path}:3: episode {specs[2].episode_id}: its look-alike needs look = \"rich\"" in line
    assert not (tmp_path / "runs").exists()
    done = agos("episodes", "check", path, "--look", "flat")
    assert done.returncode == 2 and f"{path}:3:" in _one_line(done.stderr)
    assert agos("episodes", "check", path, "--look", "rich").returncode == 0


def test_a_resumed_run_checks_its_episodes_again(tmp_path: Path, specs, agos) -> None:
    """Another agos may build the towns otherwise: the resume says so before anything starts."""
    from agos.deploy.run.plan import new_plan, resume_plan
    from agos.runtime.settings import load_config

    split = tmp_path / "eps.jsonl"
    write_episodes(split, specs)
    cfg = load_config(overrides={"run": {"episodes_file": str(split), "runs_dir": str(tmp_path / "runs")}})
    plan = new_plan(cfg, run_dir=tmp_path / "runs" / "r", comm="ideal", timing_mode="lockstep", stamp=False)
    assert resume_plan(plan.run_dir).episodes == specs
    stored = plan.run_dir / "episodes.jsonl"
    moved = msgspec.structs.replace(specs[0], asset_sha256="cd" * 32)
    stored.write_text(stored.read_text().replace(to_json(specs[0]).decode(), to_json(moved).decode()))
    done = agos("eval", "--resume", plan.run_dir)
    assert done.returncode == 2 and f"{stored}:1: episode {specs[0].episode_id}: town grid-s7" in _one_line(done.stderr)
