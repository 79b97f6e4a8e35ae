"""Dataset splits like the paper's: train and val over a set of towns, test on a held-out town.

The sizes default to the paper's: 5,500 train and 2,200 val episodes spread as evenly as the
numbers allow over the train/val towns and the three difficulties, and 210 test episodes (70 per
difficulty) on the held-out town. Towns are procedural ids, asset directories or OpenDRIVE files
(imported here with seed 0, as ``agos map import`` does, and put in the local asset cache so that
``agos eval`` finds them). The ``paper`` preset names the layout: five CARLA towns for train/val,
the test town given by the caller (the paper's own test town, Town03, is not among the maps we
have).

Episodes are sampled in parallel worker processes (spawned, one PyBullet client each) in chunks
of a fixed size; a chunk's episodes depend only on (town, difficulty, split, index, seed, look),
and the files are written in plan order, so the same arguments give the same files byte for byte
whatever the number of workers. Finished chunks are kept under ``OUT/.chunks`` until the split is
written, so an interrupted build resumes. ``OUT/manifest.json`` records the towns with their asset
sha256, the seed, the look, the counts and the sha256 of every file written; it holds no path or
time, so it is reproducible too.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from agos.runtime.codec import from_json, to_json
from agos.runtime.episode_config import DEFAULT_LOOK
from agos.runtime.process import interruptible_imap
from agos.runtime.schemas import DIFFICULTIES, Difficulty, EpisodeSpec
from agos.world.episodes.sampling import write_episodes

if TYPE_CHECKING:
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import Town

SPLIT_STREAMS = {"train": 0, "val": 100, "test": 200}
"""Disjoint random streams, so train and val never share an episode."""
SPLITS = ("train", "val", "test")
PAPER_COUNTS = {"train": 5500, "val": 2200, "test": 210}
PAPER_TRAINVAL_MAPS = ("Town01", "Town02", "Town04", "Town06", "Town07")
"""The ``paper`` preset's train/val towns: five CARLA maps, ``<maps dir>/<name>.xodr``."""
IMPORT_SEED = 0
"""Seed for the furnishing of an imported map (``agos map import``'s default), so a split over
``.xodr`` files names the same assets as one over directories made by ``agos map import``."""
CHUNK = 10
MANIFEST_FORMAT = 2
"""2: towns with their asset hashes, the look, per-difficulty counts and file hashes (1 had ids only)."""


@dataclass(frozen=True)
class SplitTown:
    """A town of a split: what the manifest records and what a worker opens (``source``, a
    procedural id or an asset directory in the local cache)."""

    town_id: str
    generator: str
    seed: int
    sha256: str
    source: str

    def record(self) -> dict[str, str | int]:
        """The manifest's entry: no path, so it is the same on every machine."""
        return {"town_id": self.town_id, "generator": self.generator, "seed": self.seed, "sha256": self.sha256}


def resolve_town(name: str) -> SplitTown:
    """A town by procedural id (``grid-s7``), asset directory or ``.xodr`` file. Imported towns go
    to the local asset cache. Raises ``ValueError`` with one line naming the town and what to do."""
    from agos.world.towns.asset import cache_dir, freeze, open_town, save_town
    from agos.world.towns.procedural import TOWNS

    path = Path(name)
    if path.suffix.lower() == ".xodr":
        if not path.is_file():
            raise ValueError(f"town {name}: no such OpenDRIVE file (the CARLA maps: README, \"Towns and maps\")")
        from agos.world.towns.imported import imported_layout

        town = freeze(imported_layout(path, seed=IMPORT_SEED))
        cached = cache_dir() / town.sha256
        if not (cached / "asset.msgpack").exists():
            save_town(town, cached)
        return _split_town(town, str(cached))
    try:
        town = open_town(name)  # an asset directory is also put in the cache
    except ValueError:
        if path.exists():
            raise  # an asset directory that is damaged: its own message says why
        raise ValueError(f"unknown town {name!r}: give a procedural town ({', '.join(TOWNS)} or "
                         f"<generator>-s<seed>), an asset directory (agos map import FILE.xodr --out DIR) "
                         f"or an .xodr file") from None
    is_asset = (path / "asset.msgpack").exists() or path.suffix == ".msgpack"  # as open_town tells them apart
    return _split_town(town, str(cache_dir() / town.sha256) if is_asset else name)


def _split_town(town: Town, source: str) -> SplitTown:
    return SplitTown(town.town_id, town.layout.generator, town.layout.seed, town.sha256, source)


def paper_towns(maps_dir: Path) -> list[str]:
    """The ``paper`` preset's train/val towns as ``.xodr`` paths; ``ValueError`` (one line) names
    the first one missing."""
    paths = [maps_dir / f"{name}.xodr" for name in PAPER_TRAINVAL_MAPS]
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise ValueError(f"--preset paper needs the CARLA maps {', '.join(PAPER_TRAINVAL_MAPS)} as .xodr files; "
                         f"{missing[0]} is missing: put them in {maps_dir} (README, \"Towns and maps\") "
                         f"or give --maps DIR")
    return [str(p) for p in paths]


def check_disjoint(trainval: Sequence[SplitTown], test: Sequence[SplitTown]) -> None:
    """``ValueError`` (one line) unless the train/val towns are distinct and the test towns are none
    of them, by id (episode ids must be unique) and by asset (the same map under two names)."""
    for i, town in enumerate(trainval):
        for other in trainval[:i]:
            if town.town_id == other.town_id or town.sha256 == other.sha256:
                raise ValueError(f"train/val town {town.town_id} is given twice: name each town once in --towns")
    for town in test:
        for other in trainval:
            if town.town_id == other.town_id or town.sha256 == other.sha256:
                raise ValueError(f"test town {town.town_id} is also a train/val town; the test town is held out: "
                                 f"give a --test-town that is not among the train/val towns")


@dataclass(frozen=True)
class SplitPlan:
    """Everything that decides a split's files."""

    trainval: tuple[SplitTown, ...]
    test_towns: tuple[SplitTown, ...]
    train: int = PAPER_COUNTS["train"]
    val: int = PAPER_COUNTS["val"]
    test: int = PAPER_COUNTS["test"]
    seed: int = 1
    look: str = DEFAULT_LOOK
    preset: str | None = None

    def jobs(self, chunk: int = CHUNK) -> list[Job]:
        return plan_jobs(train=self.train, val=self.val, test=self.test, trainval_towns=list(self.trainval),
                         test_towns=list(self.test_towns), seed=self.seed, look=self.look, chunk=chunk)


@dataclass(frozen=True)
class Job:
    split: str
    town: SplitTown
    difficulty: Difficulty
    start: int
    count: int
    seed: int
    look: str


def plan_jobs(*, train: int, val: int, test: int, trainval_towns: list[SplitTown], test_towns: list[SplitTown],
              seed: int, look: str, chunk: int = CHUNK) -> list[Job]:
    """Each split's total spread over its (town, difficulty) cells, the first cells taking one
    more where it does not divide; each cell cut into chunks of ``chunk`` episodes."""
    jobs: list[Job] = []
    for split, total, towns in (("train", train, trainval_towns), ("val", val, trainval_towns),
                                ("test", test, test_towns)):
        cells = [(t, d) for t in towns for d in DIFFICULTIES]
        if total and not cells:
            raise ValueError(f"{total} {split} episodes but no town to sample them on")
        for k, (town, difficulty) in enumerate(cells):
            n = total // len(cells) + (1 if k < total % len(cells) else 0)
            for start in range(0, n, chunk):
                jobs.append(Job(split, town, difficulty, start, min(chunk, n - start), seed, look))
    return jobs


_WORKER_TOWNS: dict[tuple[str, str], tuple[Town, Scene]] = {}


def _run_keyed(job: Job) -> tuple[Job, list[str]]:
    return job, run_job(job)


def run_job(job: Job) -> list[str]:
    """Sample one chunk in a worker process; returns the episodes as JSON lines."""
    from agos.world.episodes.sampling import sample_episode
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import open_town

    key = (job.town.source, job.look)
    if key not in _WORKER_TOWNS:
        town = open_town(job.town.source)
        if town.sha256 != job.town.sha256:  # a cache entry or generator that changed under the build
            raise ValueError(f"town {job.town.town_id}: {job.town.source} now hashes to {town.sha256[:12]}, "
                             f"the split planned {job.town.sha256[:12]}")
        _WORKER_TOWNS[key] = (town, Scene(town.layout, look=job.look))
    town, scene = _WORKER_TOWNS[key]
    stream = SPLIT_STREAMS[job.split] + DIFFICULTIES.index(job.difficulty)
    return [to_json(sample_episode(town, scene, job.difficulty, i, seed=job.seed, stream=stream, split=job.split)).decode()
            for i in range(job.start, job.start + job.count)]


def _chunk_path(out_dir: Path, job: Job) -> Path:
    """Where a finished chunk is kept until the split is written, so an interrupted build resumes;
    the name holds everything the chunk depends on, so a build with other arguments never reuses it."""
    return out_dir / ".chunks" / (f"{job.split}-{job.town.town_id}-{job.town.sha256[:12]}-{job.difficulty}-"
                                  f"{job.start}-{job.count}-s{job.seed}-{job.look}.jsonl")


def build_split(out_dir: Path, plan: SplitPlan, *, workers: int, progress: Callable[[int], None] | None = None) -> dict:
    """Sample every job of ``plan`` (chunks already finished by an interrupted build are reused),
    write ``train/val/test.jsonl`` (a split of no episodes writes no file) and ``manifest.json``,
    and return the manifest. Ctrl-C stops the workers at once and keeps the finished chunks; it
    then raises KeyboardInterrupt."""
    jobs = plan.jobs()
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
    counts: dict[str, int] = {}
    per_difficulty: dict[str, dict[str, int]] = {}
    files: dict[str, str] = {}
    for split in SPLITS:
        split_jobs = [job for job in jobs if job.split == split]
        lines = [line for job in split_jobs for line in results[job]]
        if lines:
            path = out_dir / f"{split}.jsonl"
            write_episodes(path, [from_json(x, EpisodeSpec) for x in lines])
            files[path.name] = hashlib.sha256(path.read_bytes()).hexdigest()
        counts[split] = len(lines)
        per_difficulty[split] = {d: sum(j.count for j in split_jobs if j.difficulty == d) for d in DIFFICULTIES}
    manifest = {
        "format": MANIFEST_FORMAT, "preset": plan.preset, "seed": plan.seed, "look": plan.look,
        "counts": counts, "per_difficulty": per_difficulty,
        "towns": {"trainval": [t.record() for t in plan.trainval], "test": [t.record() for t in plan.test_towns]},
        "files": files,
    }
    (out_dir / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    shutil.rmtree(out_dir / ".chunks", ignore_errors=True)
    return manifest


def file_hashes(out_dir: Path) -> dict[str, str]:
    """sha256 of a written split's files, the manifest included (what the repository pins)."""
    names = [f"{s}.jsonl" for s in SPLITS] + ["manifest.json"]
    return {n: hashlib.sha256((out_dir / n).read_bytes()).hexdigest() for n in names if (out_dir / n).exists()}
