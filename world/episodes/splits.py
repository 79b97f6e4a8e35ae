"""Dataset splits like the paper's: train and val over five towns, test on a held-out town.

Defaults are the paper's proportions: 5,500 train and 2,200 val episodes spread evenly over the
five train/val towns and the three difficulties, and 210 test episodes (70 per difficulty) on
the held-out town. Episodes are sampled in parallel worker processes (spawned, one PyBullet
client each); the result does not depend on the number of workers.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from agos.runtime.codec import from_json, to_json
from agos.runtime.process import interruptible_imap
from agos.runtime.schemas import Difficulty, EpisodeSpec
from agos.world.episodes.sampling import DIFFICULTIES, write_episodes

if TYPE_CHECKING:
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import Town

SPLIT_STREAMS = {"train": 0, "val": 100, "test": 200}
"""Disjoint random streams, so train and val never share an episode."""


@dataclass(frozen=True)
class Job:
    split: str
    town: str
    difficulty: Difficulty
    start: int
    count: int
    seed: int


def plan_jobs(*, train: int, val: int, test: int, trainval_towns: list[str], test_towns: list[str], seed: int,
              chunk: int = 10) -> list[Job]:
    jobs: list[Job] = []
    for split, total, towns in (("train", train, trainval_towns), ("val", val, trainval_towns),
                                ("test", test, test_towns)):
        cells = [(t, d) for t in towns for d in DIFFICULTIES]
        for k, (town, difficulty) in enumerate(cells):
            n = total // len(cells) + (1 if k < total % len(cells) else 0)
            for start in range(0, n, chunk):
                jobs.append(Job(split, town, difficulty, start, min(chunk, n - start), seed))
    return jobs


_WORKER_TOWNS: dict[str, tuple[Town, Scene]] = {}


def _run_keyed(job: Job) -> tuple[Job, list[str]]:
    return job, run_job(job)


def run_job(job: Job) -> list[str]:
    """Sample one chunk in a worker process; returns the episodes as JSON lines."""
    from agos.world.episodes.sampling import sample_episode
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import open_town

    if job.town not in _WORKER_TOWNS:
        town = open_town(job.town)
        _WORKER_TOWNS[job.town] = (town, Scene(town.layout))
    town, scene = _WORKER_TOWNS[job.town]
    stream = SPLIT_STREAMS[job.split] + DIFFICULTIES.index(job.difficulty)
    return [to_json(sample_episode(town, scene, job.difficulty, i, seed=job.seed, stream=stream, split=job.split)).decode()
            for i in range(job.start, job.start + job.count)]


def _chunk_path(out_dir: Path, job: Job) -> Path:
    """Where a finished chunk is kept until the split is written, so an interrupted build resumes."""
    return out_dir / ".chunks" / f"{job.split}-{job.town}-{job.difficulty}-{job.start}-{job.count}-s{job.seed}.jsonl"


def build_split(out_dir: Path, jobs: list[Job], *, workers: int, progress: Callable[[int], None] | None = None) -> dict:
    """Sample every job (chunks already finished by an interrupted build are reused) and write the
    split. Ctrl-C stops the workers at once and keeps the finished chunks; it then raises
    KeyboardInterrupt."""
    results: dict[Job, list[str]] = {}
    (out_dir / ".chunks").mkdir(parents=True, exist_ok=True)
    for job in jobs:
        path = _chunk_path(out_dir, job)
        if path.exists():
            results[job] = path.read_text().splitlines()
            if progress:
                progress(job.count)
    todo = [job for job in jobs if job not in results]

    def keep(job: Job, lines: list[str]) -> None:
        tmp = _chunk_path(out_dir, job).with_suffix(".tmp")
        tmp.write_text("".join(line + "\n" for line in lines))
        tmp.replace(_chunk_path(out_dir, job))
        results[job] = lines
        if progress:
            progress(job.count)

    if workers <= 1:
        for job in todo:
            keep(job, run_job(job))
    else:  # Ctrl-C: pending chunks are dropped, finished ones are already kept
        for job, lines in interruptible_imap(_run_keyed, todo, workers):
            keep(job, lines)
    counts = {}
    for split in ("train", "val", "test"):
        lines = [line for job in jobs if job.split == split for line in results[job]]
        if lines:
            write_episodes(out_dir / f"{split}.jsonl", [from_json(x, EpisodeSpec) for x in lines])
        counts[split] = len(lines)
    manifest = {"counts": counts, "towns": sorted({j.town for j in jobs}), "seed": jobs[0].seed if jobs else None}
    (out_dir / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    shutil.rmtree(out_dir / ".chunks", ignore_errors=True)
    return manifest

