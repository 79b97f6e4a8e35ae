"""What the ``agos`` command groups share: the :class:`Command` a group registers, the settings a
command reads (``--config`` and the flags that override it), and the flags several commands take."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agos.runtime.settings import DEFAULTS, AgosConfig, load_config

Handler = Callable[[argparse.Namespace], int]
"""Runs a parsed command; returns its exit status."""


@dataclass(frozen=True)
class Command:
    """``agos`` commands: ``add`` adds their parsers to the ``agos`` subparsers (one call for all of
    ``names``), ``run`` calls what the parsed command names."""

    names: tuple[str, ...]
    add: Callable[[Any], object]
    run: Handler


def with_settings(handler: Callable[[argparse.Namespace, AgosConfig], int]) -> Handler:
    """A handler that gets the command's settings: defaults < ``--config`` file < ``AGOS_*`` environment < flags."""

    def run(args: argparse.Namespace) -> int:
        return handler(args, settings_of(args))

    return run


def by_subcommand(dest: str, handlers: dict[str, Handler]) -> Handler:
    """A handler that runs the handler of the subcommand named in ``args.<dest>``."""

    def run(args: argparse.Namespace) -> int:
        return handlers[getattr(args, dest)](args)

    return run


def connection_flags(p: argparse.ArgumentParser) -> None:
    """``--config``, ``--connect`` and ``--run`` of the processes that join a run."""
    p.add_argument("--config", type=Path, help="TOML settings file (see deploy/configs/demo.toml)")
    p.add_argument("--connect", help="zenoh router endpoint, e.g. tcp/127.0.0.1:7447; several, comma-separated: "
                                     "the nearest router first, the others as fallbacks")
    p.add_argument("--run", dest="run_id", help="run id (the <run> in agos/<run>/...)")


def vlm_flags(p: argparse.ArgumentParser) -> None:
    """The ``[vlm]`` settings as flags, for the commands whose VLM policies ask a model."""
    p.add_argument("--vlm-base-url", help="OpenAI-compatible endpoint of VLM policies, e.g. http://HOST:8000/v1")
    p.add_argument("--model", help="model name at that endpoint")
    p.add_argument("--vlm-api-key-env", help=f"environment variable holding the API key (default {DEFAULTS.vlm.api_key_env})")
    p.add_argument("--vlm-timeout", type=float, help=f"seconds per HTTP attempt (default {DEFAULTS.vlm.timeout_s:g})")
    p.add_argument("--vlm-max-retries", type=int, help=f"HTTP retries per request (default {DEFAULTS.vlm.max_retries})")
    p.add_argument("--vlm-no-structured", action="store_true", help="do not send a JSON schema (servers that mishandle it)")
    p.add_argument("--vlm-image-max-px", type=int, metavar="PX",
                   help="shrink every image sent to the model to at most PX on its longest side (default: as rendered)")
    p.add_argument("--vlm-jpeg-quality", type=int, metavar="Q",
                   help="re-encode every image sent to the model as JPEG at quality Q, 1-100 (default: as rendered)")
    p.add_argument("--vlm-trace", type=Path, help="also append every decision trace to this JSONL file")
    p.add_argument("--vlm-cache", type=Path, metavar="DIR",
                   help="record every model call in DIR and serve recorded ones from it (docs/AGENTS.md)")
    p.add_argument("--vlm-cache-mode", choices=["record", "replay", "off"],
                   help="with --vlm-cache: record (default), replay (no endpoint: a call not recorded stops the run) or off")


def price_flags(p: argparse.ArgumentParser) -> None:
    """What a run's model calls cost (evaluator/cost.py): one price for every model, or a TOML table."""
    p.add_argument("--price-in", type=float, metavar="USD", help="USD per million prompt (input) tokens, every model")
    p.add_argument("--price-out", type=float, metavar="USD",
                   help="USD per million completion (output) tokens, every model")
    p.add_argument("--prices", type=Path, metavar="FILE.toml",
                   help='prices per model: ["MODEL"] in_usd_per_mtok = 2.5, out_usd_per_mtok = 10 (docs/METRICS.md)')


def _int_or_none(value: object) -> int | None:
    return value if isinstance(value, int) else None


def settings_of(args: argparse.Namespace) -> AgosConfig:
    """The settings of a parsed command: its ``--config`` file, the environment, then the flags it has."""
    overrides = {
        "vlm": {"base_url": getattr(args, "vlm_base_url", None), "model": getattr(args, "model", None),
                "api_key_env": getattr(args, "vlm_api_key_env", None), "timeout_s": getattr(args, "vlm_timeout", None),
                "max_retries": getattr(args, "vlm_max_retries", None),
                "structured": False if getattr(args, "vlm_no_structured", False) else None,
                "image_max_px": getattr(args, "vlm_image_max_px", None),
                "jpeg_quality": getattr(args, "vlm_jpeg_quality", None),
                "trace_file": getattr(args, "vlm_trace", None), "cache_dir": getattr(args, "vlm_cache", None),
                "cache_mode": getattr(args, "vlm_cache_mode", None)},
        "zenoh": {"connect": getattr(args, "connect", None), "listen": getattr(args, "listen", None),
                  "peers": getattr(args, "peers", None)},
        "world": {"decision_timeout_s": getattr(args, "decision_timeout", None),
                  "uav_during_verification": getattr(args, "uav_verification", None)},
        "run": {"run_id": getattr(args, "run_id", None), "runs_dir": getattr(args, "runs_dir", None),
                "workers": _int_or_none(getattr(args, "workers", None)), "agent_wait_s": getattr(args, "agent_wait", None),
                "episodes_file": getattr(args, "episodes", None) or getattr(args, "split", None),
                "per_difficulty": getattr(args, "per_difficulty", None),
                "policy_uav": getattr(args, "policy_uav", None) or getattr(args, "policy", None),
                "policy_ugv": getattr(args, "policy_ugv", None) or getattr(args, "policy", None)},
    }
    return load_config(getattr(args, "config", None), overrides=overrides)
