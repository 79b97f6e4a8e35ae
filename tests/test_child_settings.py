"""A run's children get their settings through one path: the environment built from a settings
object (deploy/run/children.py) loads that object again, whatever the parent's environment said."""

from __future__ import annotations

from pathlib import Path

from pydantic import SecretStr

from agos.deploy.run.children import child_environ, settings_env, with_settings
from agos.runtime.settings import AgosConfig, load_config


def _loaded_by_child(cfg: AgosConfig, inherited: dict[str, str]) -> AgosConfig:
    return load_config(None, environ=child_environ(cfg, inherited))


def test_the_environment_carries_every_setting_that_differs_from_the_defaults() -> None:
    cfg = with_settings(AgosConfig(), zenoh={"connect": "tls/127.0.0.1:7999", "ca_file": Path("/c/ca.pem"),
                                             "key_pem": SecretStr("KEY"), "multicast_scouting": True},
                        run={"run_id": "r1", "runs_dir": Path("/runs"), "agent_wait_s": 12.5},
                        vlm={"base_url": "http://127.0.0.1:8000/v1", "model": "m", "timeout_s": 2.0, "max_retries": 10,
                             "structured": False, "images": "view_only"})
    cfg = with_settings(cfg, world={"decision_timeout_s": 7200.0, "look": "flat",
                                    "cameras": cfg.world.cameras.model_copy(update={"nadir_px": 256})})
    env = settings_env(cfg)
    assert env["AGOS_ZENOH__CONNECT"] == "tls/127.0.0.1:7999" and env["AGOS_ZENOH__KEY_PEM"] == "KEY"
    assert env["AGOS_WORLD__CAMERAS__NADIR_PX"] == "256" and env["AGOS_VLM__STRUCTURED"] == "false"
    assert "AGOS_RUN__TOWN" not in env  # a default is not repeated
    child = _loaded_by_child(cfg, {})
    assert child.model_dump() == cfg.model_dump()
    assert child.zenoh.key_pem is not None and child.zenoh.key_pem.get_secret_value() == "KEY"


def test_the_parents_setting_variables_do_not_reach_the_child() -> None:
    """The settings object already holds what they said; a setting it puts back to its default wins."""
    inherited = {"AGOS_ZENOH__CONNECT": "tcp/elsewhere:7447", "AGOS_RUN__TOWN": "parks-s23", "PATH": "/bin",
                 "AGOS_HEALTH_DIR": "/tmp/h"}
    cfg = with_settings(AgosConfig(), zenoh={"connect": AgosConfig().zenoh.connect})
    env = child_environ(cfg, inherited)
    assert env["PATH"] == "/bin" and env["AGOS_HEALTH_DIR"] == "/tmp/h"  # not settings: inherited
    child = _loaded_by_child(cfg, inherited)
    assert child.zenoh.connect == "tcp/127.0.0.1:7447" and child.run.town == "grid-s7"


def test_settings_loaded_from_a_file_and_the_environment_travel_whole(tmp_path: Path) -> None:
    path = tmp_path / "agos.toml"
    path.write_text('[run]\ntown = "tee-s17"\nper_difficulty = 3\n[world]\nrenderer = "tiny"\nuav_speed_mps = 12.0\n'
                    '[world.comm]\nname = "lossy"\nbeacon_s = 2.0\n[world.comm.loss]\nmodel = "bernoulli"\np = 0.25\n')
    cfg = load_config(path, environ={"AGOS_VLM__REASKS": "0"})
    child = _loaded_by_child(cfg, {}).model_dump()
    assert child["world"].pop("comm") == AgosConfig().world.comm.model_dump()  # the job grant carries the run's
    assert child == cfg.model_dump(exclude={"world": {"comm"}})
