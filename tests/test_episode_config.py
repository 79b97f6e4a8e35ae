"""One episode configuration: layered building, its hash, the grant and the record, and the refusal to
pool records made under different configurations (runtime/episode_config.py, deploy/run/configure.py,
evaluator/pooling.py)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from agos.deploy.run.configure import run_episode_config
from agos.evaluator.pooling import mixed_configurations
from agos.evaluator.store import ResultStore
from agos.evaluator.summary import read_run
from agos.runtime.episode_config import EpisodeConfig, differing_fields, read_config
from agos.runtime.failure_records import failure_record
from agos.runtime.schemas import JobGrant
from agos.runtime.settings import ConfigError, load_config

from support.episodes import minimal_spec

REPO = Path(__file__).resolve().parents[1]


def test_defaults_layered_file_env_flags(tmp_path: Path) -> None:
    toml = tmp_path / "c.toml"
    toml.write_text("[world]\nugv_speed_mps = 6.0\n[world.cameras]\nnadir_px = 256\n")
    cfg = load_config(toml, environ={"AGOS_WORLD__CAMERAS__GROUND_PX": "128", "AGOS_WORLD__UGV_SPEED_MPS": "5"})
    assert cfg.world.ugv_speed_mps == 5.0  # environment over file
    assert (cfg.world.cameras.nadir_px, cfg.world.cameras.ground_px) == (256, 128)
    assert cfg.world.uav_speed_mps == EpisodeConfig().uav_speed_mps  # untouched: the default
    with pytest.raises(ConfigError, match=r"AGOS_WORLD__CAMERAS__NADIR_PX.*world\.cameras\.nadir_px"):
        load_config(None, environ={"AGOS_WORLD__CAMERAS__NADIR_PX": "12"})


def test_builder_sets_comm_timing_tools_and_budget() -> None:
    cfg = load_config(None, environ={})
    config = run_episode_config(cfg, policies={"uav": "baseline", "ugv": "oracle"}, comm="lossy", timing_mode="realtime",
                                decision_budget=16)
    assert config.comm.name == "lossy" and config.timing_mode == "realtime" and config.decision_budget == 16
    assert config.tools.candidates is False and config.tools.oracle is True
    assert run_episode_config(cfg, policies={"uav": "heuristic", "ugv": "heuristic"}).tools.candidates is True


def test_hash_is_stable_and_tells_configurations_apart() -> None:
    a = EpisodeConfig()
    assert a.config_hash() == EpisodeConfig().config_hash() == EpisodeConfig.model_validate(
        json.loads(a.model_dump_json())).config_hash()
    b = EpisodeConfig.model_validate({"cameras": {"nadir_px": 256}})
    assert len(a.config_hash()) == 12 and a.config_hash() != b.config_hash()
    assert differing_fields(a.model_dump(mode="json"), b.model_dump(mode="json")) == ["cameras.nadir_px"]


def test_thresholds_scale_with_image_size() -> None:
    small = EpisodeConfig.model_validate({"cameras": {"nadir_px": 256, "ground_px": 128}})
    assert EpisodeConfig().uav_visible_min_px() == 30 and small.uav_visible_min_px() == 8  # 30 * (256/512)^2
    assert EpisodeConfig().confirm_at_view_size().min_target_pixels == 50
    assert small.confirm_at_view_size().min_target_pixels == 12  # 50 * (128/256)^2 = 12.5, rounded to even


def test_grant_and_record_carry_the_whole_configuration() -> None:
    from agos.runtime.codec import decode, encode
    config = EpisodeConfig.model_validate({"ugv_speed_mps": 6.0, "comm": {"name": "x"}})
    grant = decode(encode(JobGrant(episode=minimal_spec("e1"), config=config.model_dump(mode="json"))))
    assert read_config(grant.config, where="job grant") == config
    record = failure_record("r", minimal_spec("e1"), status="world_crashed", worker_id="w", error="x", config=config)
    assert record.config_hash == config.config_hash() and record.config["ugv_speed_mps"] == 6.0


def _store_mixed_run(run_dir: Path) -> None:
    """One run whose records were made under two configurations (e.g. workers of two builds)."""
    with ResultStore(run_dir / "results.sqlite") as store:
        for i, nadir_px in enumerate((512, 512, 256)):
            config = EpisodeConfig.model_validate({"cameras": {"nadir_px": nadir_px}})
            record = failure_record("mixed", minimal_spec(f"e{i}"), status="finished", worker_id="w", error="", config=config)
            record.success, record.final_distance_m = True, 3.0
            store.add(record)


def test_mixed_configurations_are_named(tmp_path: Path) -> None:
    _store_mixed_run(tmp_path)
    problem = mixed_configurations(read_run(tmp_path))
    assert problem is not None and "cameras.nadir_px" in problem and "2 under" in problem and "1 under" in problem


@pytest.mark.parametrize("command", [["metrics"], ["report", "--out", "REPORT"]])
def test_cli_refuses_to_pool_mixed_configurations(tmp_path: Path, command: list[str], agos) -> None:
    _store_mixed_run(tmp_path / "run")
    args = [str(tmp_path / "REPORT") if a == "REPORT" else a for a in command]
    refused = agos(args[0], tmp_path / "run", *args[1:], cwd=REPO)
    assert refused.returncode == 2, refused.stderr
    assert "different configurations" in refused.stderr and "cameras.nadir_px" in refused.stderr
    assert "--allow-mixed" in refused.stderr and refused.stdout == ""
    pooled = agos(args[0], tmp_path / "run", *args[1:], "--allow-mixed", cwd=REPO)
    assert pooled.returncode == 0, pooled.stderr


def test_compare_checks_each_run(tmp_path: Path, agos) -> None:
    _store_mixed_run(tmp_path / "a")
    out = agos("compare", tmp_path / "a", tmp_path / "a", cwd=REPO)
    assert out.returncode == 2 and "cameras.nadir_px" in out.stderr


def test_demo_toml_writes_out_the_defaults() -> None:
    cfg = load_config(REPO / "deploy" / "configs" / "demo.toml", environ={})
    assert cfg.world == EpisodeConfig()


def test_the_look_is_named_in_every_configuration_and_hashed_only_when_not_flat() -> None:
    from agos.runtime.episode_config import EpisodeConfig, config_hash

    assert EpisodeConfig().look == "rich"  # the default
    flat = EpisodeConfig(look="flat")
    stored = flat.model_dump(mode="json")
    assert stored["look"] == "flat"
    before_the_field = {k: v for k, v in stored.items() if k != "look"}
    assert flat.config_hash() == config_hash(before_the_field) == config_hash(stored)
    rich = EpisodeConfig(look="rich")
    assert rich.config_hash() != flat.config_hash()
    assert config_hash(rich.model_dump(mode="json")) == rich.config_hash()
