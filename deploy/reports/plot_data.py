"""What a trajectory figure is drawn from: one episode of one run, read from the run directory.

Contract: :func:`load_episode` reads the episode's record from the run's ``results.sqlite``, its
spec from the run's ``episodes.jsonl`` and the policies from ``run.json``, and turns the record's
step log into the two trajectories and the UGV's CONFIRM and REJECT points. Nothing is simulated
again. Why the step log: records are the one thing every run keeps, whatever host ran it and
whether anyone watched; a recording (``--record``) is optional and lossy, so a figure made from it
could silently miss steps.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from agos.evaluator.store import ResultStore
from agos.runtime.codec import from_json
from agos.runtime.schemas import EpisodeRecord, EpisodeSpec

Point = tuple[float, float]


class PlotError(ValueError):
    """A run or episode that cannot be drawn; the message says which and why."""


@dataclass
class Event:
    """A point of the figure: where a role did something."""

    xy_world_m: Point
    action: str
    candidate_id: str | None = None


@dataclass
class EpisodeView:
    """Everything one panel shows."""

    run_dir: Path
    spec: EpisodeSpec
    record: EpisodeRecord
    policies: dict[str, str]
    uav_path_world_m: list[Point] = field(default_factory=list)
    ugv_path_world_m: list[Point] = field(default_factory=list)
    """Both start after the first decision; the starts come from the town (deploy/reports/episode_map.py)."""
    candidates: dict[str, list[Point]] = field(default_factory=dict)
    """Candidate id -> its ground polygon."""
    ugv_events: list[Event] = field(default_factory=list)
    """The UGV's CONFIRMs and REJECTs, where they happened."""

    @property
    def label(self) -> str:
        uav, ugv = self.policies.get("uav", "?"), self.policies.get("ugv", "?")
        return uav if uav == ugv else f"{uav} / {ugv}"

    def bounds_world_m(self) -> tuple[float, float, float, float]:
        """The region and everything drawn in it: (x_min, y_min, x_max, y_max)."""
        xs = [self.spec.region_world_m[0], self.spec.region_world_m[2], self.spec.target.position_world_m[0]]
        ys = [self.spec.region_world_m[1], self.spec.region_world_m[3], self.spec.target.position_world_m[1]]
        for x, y in [*self.uav_path_world_m, *self.ugv_path_world_m, *(p for poly in self.candidates.values() for p in poly)]:
            xs.append(x)
            ys.append(y)
        return (min(xs), min(ys), max(xs), max(ys))


def run_dir_of(path: Path) -> Path:
    """A run directory from itself or its ``results.sqlite``."""
    run_dir = path.parent if path.name == "results.sqlite" else path
    if not (run_dir / "results.sqlite").is_file():
        raise PlotError(f"{path}: no results.sqlite there; give a run directory (runs/<run>)")
    return run_dir


def load_episode(path: Path, episode_id: str) -> EpisodeView:
    run_dir = run_dir_of(path)
    record = _record(run_dir, episode_id)
    spec = _spec(run_dir, episode_id)
    try:
        policies = json.loads((run_dir / "run.json").read_text()).get("policies", {})
    except (OSError, ValueError):
        policies = {}
    if not record.step_log:
        why = (f"its status is {record.status}" if record.status != "finished"
               else "it was stored by an agos that kept no step log; run the episode again")
        raise PlotError(f"{run_dir.name}/{episode_id}: the record has no trajectory ({why})")
    view = EpisodeView(run_dir, spec, record, policies)
    for step in record.step_log:
        if step.candidate_polygon_world_m and step.candidate_id:  # an ANNOTATE_CANDIDATE
            view.candidates[step.candidate_id] = step.candidate_polygon_world_m
        if step.role == "uav":
            view.uav_path_world_m.append(step.position_world_m)
            continue
        view.ugv_path_world_m += step.road_path_world_m or [step.position_world_m]
        if step.applied in ("CONFIRM", "REJECT"):
            view.ugv_events.append(Event(step.position_world_m, step.applied, step.candidate_id))
    return view


def first_finished(runs: list[Path]) -> str:
    """The first episode id (in order) with a finished record in every one of ``runs``."""
    shared: set[str] | None = None
    for path in runs:
        with ResultStore(run_dir_of(path) / "results.sqlite", create=False) as store:
            ids = store.finished_ids()
        shared = ids if shared is None else shared & ids
    if not shared:
        raise PlotError(f"no episode finished in {' and '.join(str(r) for r in runs)}")
    return sorted(shared)[0]


def _record(run_dir: Path, episode_id: str) -> EpisodeRecord:
    with ResultStore(run_dir / "results.sqlite", create=False) as store:
        stored = dict(store.raw_records())  # episode id -> JSON: only the one drawn is decoded
    if episode_id not in stored:
        known = ", ".join(sorted(stored)[:5]) + (" ..." if len(stored) > 5 else "")
        raise PlotError(f"{run_dir.name}: no record of episode {episode_id!r} (stored: {known or 'none'})")
    return from_json(stored[episode_id], EpisodeRecord)


def _spec(run_dir: Path, episode_id: str) -> EpisodeSpec:
    from agos.world.episodes.files import EpisodeFileError, read_episodes

    try:
        specs = {s.episode_id: s for s in read_episodes(run_dir / "episodes.jsonl")}
    except EpisodeFileError as exc:
        raise PlotError(str(exc)) from None
    if episode_id not in specs:
        raise PlotError(f"{run_dir / 'episodes.jsonl'}: no episode {episode_id!r}")
    return specs[episode_id]
