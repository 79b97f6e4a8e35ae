"""Synthetic episode summaries with known rates, for benchmarks and statistical tests (not shipped)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import numpy as np

from agos.evaluator.metrics import DIFFICULTY_ORDER
from agos.evaluator.summary import EpisodeSummary


def summary(episode_id: str, difficulty: str = "easy", *, won: bool = False, errors: tuple[float, ...] = (),
            **kw: Any) -> EpisodeSummary:
    """One hand-made summary: a finished, failed, unobserved episode with no candidates, unless told
    ``won`` (success, ground-observed, one CONFIRM) or given candidates' centre ``errors`` (each at
    polygon distance 0); other keyword arguments override the fields."""
    base: dict[str, Any] = dict(
        episode_id=episode_id, difficulty=difficulty, success=won, ground_observed=won, n_confirm=int(won),
        ugv_path_length_m=0.0, shortest_path_length_m=None, final_distance_m=None, uav_budget=80,
        uav_first_visible_step=None, decisions_uav=0, decisions_ugv=0,
        candidates=[{"distance_to_polygon_m": 0.0, "center_error_m": e} for e in errors])
    base.update(kw)
    return EpisodeSummary.model_validate(base)


def synthetic_summaries(n: int, *, seed: int, success_rate: float = 0.5, run_id: str = "synthetic",
                        uniforms: np.ndarray | None = None) -> Iterator[dict]:
    """``n`` summaries cycling through the difficulties. ``uniforms`` (one per episode) makes two
    runs share their randomness, so a paired comparison sees exactly the planted difference."""
    rng = np.random.default_rng(seed)
    u = uniforms if uniforms is not None else rng.random(n)
    for i in range(n):
        ok = bool(u[i] < success_rate)
        tau = int(rng.integers(1, 60)) if rng.random() < 0.8 else None
        candidates = [{"distance_to_polygon_m": float(rng.choice([0.0, rng.uniform(0, 120)])),
                       "center_error_m": float(rng.uniform(0, 40))} for _ in range(int(rng.integers(0, 3)))]
        path = float(rng.uniform(50, 600))
        yield {
            "episode_id": f"syn-{i:06d}", "difficulty": DIFFICULTY_ORDER[i % 3], "success": ok,
            "ground_observed": ok or bool(rng.random() < 0.2), "n_confirm": int(ok or rng.random() < 0.1),
            "ugv_path_length_m": path, "shortest_path_length_m": float(path * rng.uniform(0.4, 1.0)),
            "final_distance_m": float(rng.uniform(0, 30) if ok else rng.uniform(20, 300)), "uav_budget": 80,
            "uav_first_visible_step": tau, "candidates": candidates, "decisions_uav": int(rng.integers(1, 60)),
            "decisions_ugv": int(rng.integers(1, 20)), "run_id": run_id, "town_id": f"town-{i % 2}",
        }


def write_jsonl(path, rows) -> None:
    with open(path, "w") as fh:
        for row in rows:
            fh.write(json.dumps(row) + "\n")
