"""Localisation error (runtime/sensing.py, world/sim/localisation.py): the profiles, the error model,
and an episode whose roles are shown, send and project from their believed poses."""

from __future__ import annotations

import math
from pathlib import Path

import msgspec
import numpy as np
import pytest

from agos.agents.registry import make_policy
from agos.env import Env
from agos.runtime.episode_config import CameraConfig, EpisodeConfig
from agos.runtime.sensing import EXACT, PROFILE_DIR, PoseErrorProfileError, PoseErrors, load_pose_error
from agos.world.episodes.sampling import sample_episode
from agos.world.sim.localisation import in_degraded_zone, sky_blocked_share
from agos.world.sim.scene import Scene
from agos.world.towns.asset import open_town

SMALL = CameraConfig(nadir_px=128, ground_px=96, reference_px=64, map_px=0)
VOLATILE = {"wall_time_s", "provenance"}


def test_every_shipped_profile_loads_and_exact_is_the_default() -> None:
    names = sorted(p.stem for p in PROFILE_DIR.glob("*.toml"))
    assert {"exact", "gnss-2m", "gnss-5m", "gnss-10m", "urban-gnss"} <= set(names)
    for name in names:
        assert load_pose_error(name).name == name
    assert load_pose_error("exact") == EXACT and EXACT.exact
    assert EpisodeConfig(pose_error=load_pose_error("exact")).config_hash() == EpisodeConfig().config_hash()
    assert EpisodeConfig(pose_error=load_pose_error("gnss-5m")).config_hash() != EpisodeConfig().config_hash()


@pytest.mark.parametrize(("text", "field"), [
    ("[uav]\nbias_m = -1.0\n", "uav.bias_m"),
    ("[ugv]\nsigma_m = 2.0\n", "ugv.sigma_m"),
    ("[satellite]\nnoise_m = 1.0\n", "satellite"),
    ("[uav]\nurban_factor = 0.5\n", "uav.urban_factor"),
])
def test_a_bad_profile_is_one_line_naming_the_file_and_the_field(tmp_path: Path, text: str, field: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(PoseErrorProfileError) as caught:
        load_pose_error(path)
    assert str(caught.value).startswith(f"{path}: {field}:") and "\n" not in str(caught.value)
    with pytest.raises(PoseErrorProfileError, match=r"no such file.*known profiles: exact"):
        load_pose_error("gnss-1km")


def test_the_levels_are_what_their_names_say_and_the_same_seed_draws_the_same_fixes() -> None:
    """Over many episodes (a bias each), the horizontal RMS error of gnss-Xm is X m within 10 %."""
    for level in (2, 5, 10):
        profile = load_pose_error(f"gnss-{level}m")
        errors = [PoseErrors(profile, seed).fix("uav", 5.0 * k).horizontal_m for seed in range(200) for k in range(20)]
        assert math.sqrt(np.mean(np.square(errors))) == pytest.approx(level, rel=0.1)
    a, b = PoseErrors(load_pose_error("urban-gnss"), 7), PoseErrors(load_pose_error("urban-gnss"), 7)
    times = [0.0, 0.0, 3.5, 10.0, 10.0, 61.0]
    assert [a.fix("ugv", t) for t in times] == [b.fix("ugv", t) for t in times]
    assert a.fix("ugv", 61.0) is a.fix("ugv", 61.0)  # one fix per instant: observation and sync agree
    assert PoseErrors(EXACT, 7).fix("uav", 3.0).horizontal_m == 0.0


def test_the_degraded_zone_multiplies_drift_and_noise() -> None:
    profile = load_pose_error("urban-gnss")
    open_sky = [PoseErrors(profile, s).fix("ugv", 1.0, lambda: False) for s in range(300)]
    canyon = [PoseErrors(profile, s).fix("ugv", 1.0, lambda: True) for s in range(300)]
    assert not any(f.degraded for f in open_sky) and all(f.degraded for f in canyon)
    rms = [math.sqrt(np.mean([f.horizontal_m ** 2 for f in fixes])) for fixes in (open_sky, canyon)]
    assert 2.0 < rms[1] / rms[0] < 4.0  # drift and noise x4, the bias not


@pytest.fixture(scope="module")
def world():
    town = open_town("grid-s7")
    with Scene(town.layout, look="flat") as scene:
        yield town, scene, sample_episode(town, scene, "mid", 0, seed=2, stream=1)


def _play(world, pose_error: str) -> tuple[dict, list]:
    town, scene, spec = world
    config = EpisodeConfig(look="flat", cameras=SMALL, pose_error=load_pose_error(pose_error), decision_budget=40)
    shown = []
    with Env(spec, config, scene=scene, town=town) as env:
        observations = env.reset()
        policies = {r: make_policy("heuristic", r) for r in ("uav", "ugv")}
        while observations:
            assert env._runner is not None
            state = env._runner.state  # the truth beside what each role is shown
            for role, obs in observations.items():
                true = state.pose(role).position_world_m
                shown.append((role, math.dist(obs.pose.position_world_m[:2], true[:2]),
                              obs.coordination.poses[role] == obs.pose))
            observations = env.step({r: policies[r].act(o) for r, o in observations.items()}).observations
        record = env.record
    return {k: v for k, v in msgspec.to_builtins(record).items() if k not in VOLATILE}, shown


def test_an_episode_shows_each_role_its_believed_pose_and_records_the_error(world) -> None:
    exact, shown_exact = _play(world, "exact")
    assert exact["pose_error"] == {} and exact["pose_error_profile"] == "exact"
    assert all(error == 0.0 and same for _, error, same in shown_exact)
    noisy, shown = _play(world, "gnss-10m")
    assert noisy == _play(world, "gnss-10m")[0]  # the same seed, the same record
    assert all(same for *_, same in shown)  # the observation and its coordination state agree
    for role in ("uav", "ugv"):
        errors = [e for r, e, _ in shown if r == role]
        stats = noisy["pose_error"][role]
        assert stats["mean_m"] == pytest.approx(np.mean(errors), abs=2e-3)
        assert stats["max_m"] == pytest.approx(max(errors), abs=2e-3)
        assert 1.0 < stats["mean_m"] < 40.0
    steps = [s for s in noisy["step_log"] if "pose_error_m" in s]
    assert len(steps) == len(noisy["step_log"]) and all(s["pose_error_m"] >= 0 for s in steps)
    assert exact["config_hash"] != noisy["config_hash"]


def test_the_sky_is_open_above_the_roofs_and_crowded_between_tall_blocks(world) -> None:
    town, scene, _ = world
    assert sky_blocked_share(scene, (0.0, 0.0, 400.0)) == 0.0 and not in_degraded_zone(scene, (0.0, 0.0, 400.0))
    anchors = town.roads.positions_world_m
    shares = [sky_blocked_share(scene, (float(p[0]), float(p[1]), 1.7)) for p in anchors[:: max(1, len(anchors) // 60)]]
    assert min(shares) >= 0.0 and max(shares) <= 1.0 and max(shares) > 0.0  # grid-s7's blocks block some sky


@pytest.mark.parametrize("command", ["eval", "sweep"])
@pytest.mark.parametrize(("flag", "text", "says"), [
    ("--pose-error", "[ugv]\nnoise_m = -2.0\n", "ugv.noise_m: Input should be greater than or equal to 0"),
    ("--comm", "[echo]\np = 0.1\n", "echo: Extra inputs are not permitted"),
])
def test_the_commands_refuse_a_bad_profile_in_one_line(tmp_path: Path, agos, command: str, flag: str, text: str,
                                                       says: str) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    where = ["--run-dir", tmp_path / "run"] if command == "eval" else ["--split", tmp_path / "none.jsonl", "--out", tmp_path / "o"]
    out = agos(command, flag, bad, *where)
    assert (out.returncode, out.stderr.strip()) == (2, f"{command} error: {bad}: {says}")
    assert not (tmp_path / "run").exists() and not (tmp_path / "o").exists()


def test_a_settings_file_names_the_profile(tmp_path: Path) -> None:
    from agos.runtime.settings import ConfigError, load_config

    good, bad = tmp_path / "good.toml", tmp_path / "bad.toml"
    good.write_text('[world]\npose_error = "urban-gnss"\n')
    bad.write_text('[world]\npose_error = "gnss-1km"\n')
    assert load_config(good, environ={}).world.pose_error == load_pose_error("urban-gnss")
    with pytest.raises(ConfigError) as caught:
        load_config(bad, environ={})
    assert "world.pose_error" in str(caught.value) and "gnss-1km" in str(caught.value) and "\n" not in str(caught.value)
