"""Typed settings: defaults, then a TOML file, then ``AGOS_<SECTION>__<KEY>`` environment
variables, then command-line flags (STYLE.md item 10).

A bad file or value stops the process with one line naming the file (or variable) and the
field, e.g. ``config error: demo.toml: world.ugv_speed_mps: Input should be a valid number``.
"""

from __future__ import annotations

import os
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

ENV_PREFIX = "AGOS_"


class ConfigError(ValueError):
    """One line naming the source (file or environment variable) and the field."""


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True)


class ZenohSettings(_Section):
    connect: str = "tcp/127.0.0.1:7447"
    """Router endpoint every process connects to."""
    listen: str = "tcp/127.0.0.1:7447"
    """Where ``agos router`` listens."""
    multicast_scouting: bool = False
    connect_timeout_s: float = Field(10.0, gt=0)


class RunSettings(_Section):
    run_id: str = "demo"
    runs_dir: Path = Path("runs")
    town: str = "grid-s7"
    """Town of generated episodes: a procedural id (grid-s7, curved-s13 ...) or an asset directory."""
    episode_seed: int = 1
    per_difficulty: int = Field(2, ge=1)
    episodes_file: Path | None = None
    """JSONL episode file; when set, it replaces the generated episodes."""
    policy_uav: str = "heuristic"
    policy_ugv: str = "heuristic"
    decision_timeout_s: float = Field(60.0, gt=0)
    """Wall-clock wait for an action before the world logs a WAIT fallback."""
    agent_wait_s: float = Field(30.0, gt=0)
    """How long a world worker waits for both agent services at an episode's first decision
    before it records the episode as failed, naming the missing role."""
    workers: int = Field(1, ge=1)


class WorldSettings(_Section):
    renderer: Literal["tiny", "egl"] = "tiny"
    nadir_px: int = Field(512, ge=64)
    ground_px: int = Field(256, ge=64)
    rgb_encoding: Literal["jpeg", "png"] = "jpeg"
    uav_speed_mps: float = Field(10.0, gt=0)
    ugv_speed_mps: float = Field(8.0, gt=0)
    wait_max_s: float = Field(20.0, gt=0)
    max_annotations: int = Field(5, ge=1)
    uav_visible_min_pixels: int = Field(30, ge=1)
    """Oracle: target pixels for "visible from the air", at 512 x 512 (scaled with nadir_px²)."""
    confirm_min_pixels: int = Field(50, ge=1)
    """CONFIRM checker: target pixels in one of the six views, at 256 x 256 (scaled with ground_px²)."""
    confirm_max_distance_m: float = Field(50.0, gt=0)
    require_fresh_stop: bool = True
    require_line_of_sight: bool = True

    def episode_settings(self) -> Any:
        """The world's :class:`~agos.world.sim.engine.EpisodeSettings` (imported here: PyBullet is
        loaded only by processes that simulate)."""
        from agos.world.sim.confirm import ConfirmSettings
        from agos.world.sim.engine import EpisodeSettings
        from agos.world.sim.sensors import CameraSettings

        return EpisodeSettings(
            uav_speed_mps=self.uav_speed_mps, ugv_speed_mps=self.ugv_speed_mps, wait_max_s=self.wait_max_s,
            max_annotations=self.max_annotations,
            uav_visible_min_px=max(1, round(self.uav_visible_min_pixels * (self.nadir_px / 512) ** 2)),
            confirm=ConfirmSettings(require_fresh_stop=self.require_fresh_stop,
                                    min_target_pixels=max(1, round(self.confirm_min_pixels * (self.ground_px / 256) ** 2)),
                                    max_distance_m=self.confirm_max_distance_m,
                                    require_line_of_sight=self.require_line_of_sight),
            cameras=CameraSettings(nadir_px=self.nadir_px, ground_px=self.ground_px, rgb_encoding=self.rgb_encoding))


class VlmOptions(_Section):
    """How VLM policies reach their model (``[vlm]`` section, ``AGOS_VLM__*``, ``--vlm-*`` flags)."""

    base_url: str | None = None
    """OpenAI-compatible endpoint, e.g. ``http://127.0.0.1:8000/v1`` (vLLM, SGLang, Ollama ...)."""
    model: str | None = None
    api_key_env: str = "OPENAI_API_KEY"
    """Environment variable holding the API key (the key itself is never logged or stored)."""
    timeout_s: float = Field(60.0, gt=0)
    """Per HTTP attempt."""
    max_retries: int = Field(4, ge=0)
    concurrency: int = Field(8, ge=1)
    """HTTP requests in flight at once, per agent service."""
    structured: bool = True
    """Send a JSON schema as ``response_format`` (turn off for servers that mishandle it)."""
    max_tokens: int = Field(512, ge=16)
    reasks: int = Field(2, ge=0)
    """Further requests after a reply that cannot be used, before the fallback action."""
    images: Literal["all", "view_only"] = "all"
    """``view_only`` sends only the role's camera view(s) and the top reference (small image limits)."""
    trace_file: Path | None = None
    """Also append every decision trace as a JSON line here (agent side)."""


class AgosConfig(_Section):
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    run: RunSettings = Field(default_factory=RunSettings)
    world: WorldSettings = Field(default_factory=WorldSettings)
    vlm: VlmOptions = Field(default_factory=VlmOptions)


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _validate(data: dict[str, Any], source: str) -> AgosConfig:
    try:
        return AgosConfig.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        field = ".".join(str(p) for p in err["loc"])
        raise ConfigError(f"config error: {source}: {field}: {err['msg']}") from None


def load_config(path: Path | None = None, *, overrides: dict[str, Any] | None = None,
                environ: dict[str, str] | None = None) -> AgosConfig:
    """Defaults < TOML file < environment < overrides (flags), each layer validated."""
    data: dict[str, Any] = {}
    if path is not None:
        try:
            data = tomllib.loads(path.read_text())
        except FileNotFoundError:
            raise ConfigError(f"config error: {path}: file not found") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"config error: {path}: not valid TOML ({exc})") from None
        _validate(data, str(path))
    env = os.environ if environ is None else environ
    env_layer: dict[str, Any] = {}
    for name, value in env.items():
        if not name.startswith(ENV_PREFIX) or "__" not in name:
            continue
        section, _, key = name[len(ENV_PREFIX):].lower().partition("__")
        env_layer.setdefault(section, {})[key] = value
        _validate(_merge(data, {section: {key: value}}), f"environment {name}")
    data = _merge(data, env_layer)
    if overrides:
        data = _merge(data, {s: {k: v for k, v in kv.items() if v is not None} for s, kv in overrides.items()})
    return _validate(data, "command line" if overrides else (str(path) if path else "defaults"))
