"""``agos demo``: an evaluation run on the embedded defaults (see :mod:`agos.deploy.run.evaluate`).

Six generated episodes on ``grid-s7`` (two per difficulty), heuristic agents, ideal link,
lockstep, one world worker; every process separate, on a router it starts (7447 or a free port).
"""

from __future__ import annotations

from pathlib import Path

from rich.console import Console

from agos.deploy.run import evaluate
from agos.deploy.run.local import Recording
from agos.deploy.run.plan import new_plan
from agos.runtime.settings import DEFAULTS, AgosConfig


def main(cfg: AgosConfig, *, config_path: Path | None = None, port: int | None = None, attach: bool = False,
         console: Console | None = None, comm: str = DEFAULTS.world.comm.name, timing_mode: str = DEFAULTS.world.timing_mode,
         secure: bool = False, recording: Recording | None = None) -> int:
    """``recording``: ``--record DIR``, a recorder writes each episode as a rerun file (deploy/recording/recorder.py)."""
    plan = new_plan(cfg, run_dir=None, comm=comm, timing_mode=timing_mode, stamp=not attach, check_vlm=not attach)
    return evaluate.run(cfg, plan, workers=cfg.run.workers, attach=attach, port=port, config_path=config_path,
                        console=console, secure=secure, recording=recording)
