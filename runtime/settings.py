"""Typed settings: defaults, then a TOML file, then ``AGOS_<SECTION>__<KEY>`` environment
variables, then command-line flags (STYLE.md item 10).

A bad file or value stops the process with one line naming the file (or variable) and the
field, e.g. ``config error: demo.toml: world.ugv_speed_mps: Input should be a valid number``.
"""

from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, ValidationError, ValidationInfo, field_validator

from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.textfiles import TextFileError, one_line, read_toml

ENV_PREFIX = "AGOS_"
ENV_SEPARATOR = "__"
"""Between a setting's section and key in its variable: ``AGOS_ZENOH__CONNECT``, ``AGOS_WORLD__CAMERAS__NADIR_PX``."""


def is_setting_variable(name: str) -> bool:
    """Whether ``name`` is an environment variable :func:`load_config` reads as a setting."""
    return name.startswith(ENV_PREFIX) and ENV_SEPARATOR in name


class ConfigError(ValueError):
    """One line naming the source (file or environment variable) and the field."""


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True)


_ENDPOINT = re.compile(r"[a-z][a-z0-9-]*/[^\s,]+")


def endpoint_list(text: str) -> list[str]:
    """The endpoints of a comma-separated list (``"tcp/a:7447, tcp/b:7447"``), blanks dropped."""
    return [part.strip() for part in text.split(",") if part.strip()]


def _check_endpoints(endpoints: list[str], mixed: str) -> None:
    """A ValueError unless each endpoint is PROTOCOL/ADDRESS and all or none are TLS (``mixed`` says
    what mixes them)."""
    for endpoint in endpoints:
        if not _ENDPOINT.fullmatch(endpoint):
            raise ValueError(f"{endpoint!r} is not an endpoint: write PROTOCOL/HOST:PORT, e.g. tcp/10.0.0.2:7447")
    if len({e.startswith("tls/") for e in endpoints}) > 1:
        raise ValueError(f"{mixed} tls/ and plain endpoints: a secured bus is tls/ on every link")


class ZenohSettings(_Section):
    connect: str = "tcp/127.0.0.1:7447"
    """Router endpoint every process connects to. Several, separated by commas, for a router mesh: the
    nearest router first, the others in order of preference; a process whose router goes away
    reconnects to the first one that answers (docs/DEPLOY.md, "Router mesh")."""
    listen: str = "tcp/127.0.0.1:7447"
    """Where ``agos router`` listens."""
    peers: list[str] = Field(default_factory=list)
    """Other routers ``agos router`` connects to, making a mesh (``--peer``, repeated; in
    ``AGOS_ZENOH__PEERS`` comma-separated). Each keeps trying a peer that is not up yet or went away."""
    multicast_scouting: bool = False
    connect_timeout_s: float = Field(10.0, gt=0)
    # Mutual TLS (docs/DEPLOY.md, "A secured bus"): used when the endpoint is ``tls/HOST:PORT``.
    # Each credential comes from a file (``*_file``) or, in the environment, as PEM text (``*_pem``).
    ca_file: Path | None = None
    """CA certificate (PEM) that signed the router's and every process's certificate (``agos certs``)."""
    cert_file: Path | None = None
    """This process's certificate (PEM); its common name is the identity the router's access control knows."""
    key_file: Path | None = None
    """This process's private key (PEM)."""
    ca_pem: str | None = None
    cert_pem: str | None = None
    key_pem: SecretStr | None = None
    """The private key as PEM text (e.g. ``AGOS_ZENOH__KEY_PEM`` from a secret store); never logged."""
    verify_name: bool = True
    """Clients check that the router's certificate names the host they connect to."""

    @field_validator("connect")
    @classmethod
    def _connect_list(cls, value: str) -> str:
        if not endpoint_list(value):
            raise ValueError("no endpoint: name the router, e.g. tcp/127.0.0.1:7447")
        _check_endpoints(endpoint_list(value), "the list mixes")
        return value

    @field_validator("peers", mode="before")
    @classmethod
    def _peers_list(cls, value: object) -> object:
        return endpoint_list(value) if isinstance(value, str) else value

    @field_validator("peers")
    @classmethod
    def _peers_like_listen(cls, value: list[str], info: ValidationInfo) -> list[str]:
        listen = info.data.get("listen")  # absent when it failed its own check
        _check_endpoints([listen, *value] if listen else value, "the peers and the listen endpoint mix")
        return value

    @property
    def connect_endpoints(self) -> list[str]:
        """:attr:`connect` as a list, the nearest router first."""
        return endpoint_list(self.connect)


DEFAULT_TOWN = "grid-s7"
"""The town a run, the library's generated episodes and ``agos episodes sample`` use unless told another."""
DEFAULT_POLICY = "heuristic"
"""The policy of each role unless told another (``[run] policy_uav``, ``policy_ugv``, ``--policy``)."""


class RunSettings(_Section):
    run_id: str = "demo"
    runs_dir: Path = Path("runs")
    town: str = DEFAULT_TOWN
    """Town of generated episodes: a procedural id (grid-s7, curved-s13 ...) or an asset directory."""
    episode_seed: int = 1
    per_difficulty: int = Field(2, ge=1)
    episodes_file: Path | None = None
    """JSONL episode file; when set, it replaces the generated episodes."""
    policy_uav: str = DEFAULT_POLICY
    policy_ugv: str = DEFAULT_POLICY
    agent_wait_s: float = Field(30.0, gt=0)
    """How long a world worker waits for both agent services at an episode's first decision
    before it records the episode as failed, naming the missing role."""
    presence_check_s: float = Field(15.0, gt=0)
    """While a run makes no progress, how often ``agos eval`` checks which processes are missing and
    says so; after three such checks in a row with no world worker, or with records no evaluator
    stored, it stops (exit 3)."""
    workers: int = Field(1, ge=1)
    max_infra_attempts: int = Field(3, ge=1)
    """Attempts an episode may lose to its model endpoint giving no answer (after the client's retries)
    before ``agos eval`` stores it as ``infra_error`` (not scored; ``--resume`` plays it again)."""
    infra_wait_s: float = Field(60.0, ge=0)
    """After such an outage, how long ``agos eval`` leases nothing before the paused episodes go again."""
    reconnect_grace_s: float = Field(10.0, ge=0)
    """How long the orchestrator keeps the leases of a world worker whose liveliness token vanished,
    waiting for it to come back (a router restarted, a session that reconnected) before it leases them
    again: a worker back within it keeps its episode, which stays attempt 1."""


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
    image_max_px: int | None = Field(None, ge=16)
    """Shrink every image sent to the model to at most this many pixels on its longest side (its
    camera numbers scaled with it: agents/vlm/images.py). None: as rendered."""
    jpeg_quality: int | None = Field(None, ge=1, le=100)
    """Re-encode every image sent to the model as JPEG at this quality, but those with transparency
    (the target's references stay PNG). None: as rendered (camera views JPEG 90, references PNG, the
    map JPEG 85). With ``image_max_px``, what a request weighs on the link
    to the model (``--model-link``, docs/COMMS.md)."""
    trace_file: Path | None = None
    """Also append every decision trace as a JSON line here (agent side)."""
    cache_dir: Path | None = None
    """Record and replay model calls in this directory (``--vlm-cache``; agents/vlm/cache.py)."""
    cache_mode: Literal["record", "replay", "off"] = "record"
    """With ``cache_dir``: ``record`` (serve recorded replies, ask the endpoint for the rest and store
    them), ``replay`` (no network: a request not recorded stops the run) or ``off``."""

    @property
    def replaying(self) -> bool:
        """Replies come from the cache alone: no endpoint is needed or asked."""
        return self.cache_dir is not None and self.cache_mode == "replay"


class RenderSettings(_Section):
    """This process's renderer hardware (``[render]``, ``AGOS_RENDER__*``): never part of a run's
    configuration, which ``[world] renderer`` is (the orchestrator's, sent with every episode)."""

    egl_device: int | None = Field(None, ge=0)
    """A world worker's EGL device (the index PyBullet's EGL plugin reads from ``EGL_VISIBLE_DEVICES``).
    None: ``EGL_VISIBLE_DEVICES`` if set, else the worker's index modulo the GPUs it sees
    (world/sim/egl_device.py)."""


class AgosConfig(_Section):
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    run: RunSettings = Field(default_factory=RunSettings)
    world: EpisodeConfig = Field(default_factory=EpisodeConfig)
    """Everything that shapes an episode (runtime/episode_config.py); the orchestrator's copy, with
    the run's comm profile, timing and tools set, is what every world worker runs with."""
    vlm: VlmOptions = Field(default_factory=VlmOptions)
    render: RenderSettings = Field(default_factory=RenderSettings)


DEFAULTS = AgosConfig()
"""Every setting at its default, to be read, never changed: a function below the settings whose keyword
stands for a setting takes its default from here (``DEFAULTS.run.reconnect_grace_s``), so each default
is written once, in the models above."""


class LocalDirs(BaseModel):
    """Folders of this host, not settings of a run: each from its own environment variable (the field's
    alias; empty counts as unset), else its default. Read when asked (:func:`local_dirs`), so a variable
    set after start counts."""

    model_config = ConfigDict(extra="ignore", frozen=True)

    asset_cache: Path = Field(default_factory=lambda: Path.home() / ".cache" / "agos" / "assets",
                              validation_alias="AGOS_ASSET_CACHE")
    """Town assets, meshes and textures built or fetched before (world/towns/asset.py)."""
    health_dir: Path = Field(default_factory=lambda: Path(tempfile.gettempdir()) / "agos-health",
                             validation_alias="AGOS_HEALTH_DIR")
    """The files ``agos health`` reads (runtime/health.py)."""


def local_dirs(environ: Mapping[str, str] | None = None) -> LocalDirs:
    """:class:`LocalDirs` from ``environ`` (default: this process's environment)."""
    env = os.environ if environ is None else environ
    names = [str(field.validation_alias) for field in LocalDirs.model_fields.values()]
    return LocalDirs.model_validate({name: env[name] for name in names if env.get(name)})


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def config_error(exc: ValidationError, source: str, *, section: str = "") -> ConfigError:
    """The one line for a settings value pydantic refused: the source, the dotted field, the reason."""
    err = exc.errors()[0]
    field = section + ".".join(str(p) for p in err["loc"])
    return ConfigError(one_line(f"config error: {source}: {field}: {err['msg']}"))


def _validate(data: dict[str, Any], source: str) -> AgosConfig:
    try:
        return AgosConfig.model_validate(data)
    except ValidationError as exc:
        raise config_error(exc, source) from None


def load_config(path: Path | None = None, *, overrides: dict[str, Any] | None = None,
                environ: dict[str, str] | None = None) -> AgosConfig:
    """Defaults < TOML file < environment < overrides (flags), each layer validated."""
    data: dict[str, Any] = {}
    if path is not None:
        try:
            data = read_toml(path)
        except FileNotFoundError:
            raise ConfigError(one_line(f"config error: {path}: file not found")) from None
        except TextFileError as exc:
            raise ConfigError(one_line(f"config error: {path}: {exc}")) from None
        _validate(data, str(path))
    env = os.environ if environ is None else environ
    env_layer: dict[str, Any] = {}
    for name, value in env.items():
        if not is_setting_variable(name):
            continue
        dotted = name[len(ENV_PREFIX):].lower().split(ENV_SEPARATOR)  # AGOS_WORLD__CAMERAS__NADIR_PX
        nested: dict[str, Any] = {dotted[-1]: value}
        for part in reversed(dotted[:-1]):
            nested = {part: nested}
        env_layer = _merge(env_layer, nested)
        _validate(_merge(data, nested), f"environment {name}")
    data = _merge(data, env_layer)
    if overrides:
        data = _merge(data, {s: {k: v for k, v in kv.items() if v is not None} for s, kv in overrides.items()})
    return _validate(data, "command line" if overrides else (str(path) if path else "defaults"))
