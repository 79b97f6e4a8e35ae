"""``agos dataset shard`` and ``agos dataset merge``: one split's dataset built as N independent builds
(a Slurm array job's tasks, or any hosts) whose outputs merge into the files a one-host build writes.

    agos dataset shard --split train.jsonl --shards 8 --out DIR      # DIR/shards.json, DIR/splits/<k>.jsonl
    agos dataset build --split DIR/splits/<k>.jsonl --out DIR/shards/<k>   # each shard, anywhere (one array task)
    agos dataset merge DIR --out DATASET                             # DATASET: what one build of train.jsonl writes

**Sharding** is round-robin: the split's i-th episode (from 0) goes to shard ``i mod N``, its line
copied byte for byte. Splits list their episodes by difficulty and town, so round-robin gives every
shard the same mix, and with it about the same work; contiguous blocks would give one shard all the
hard episodes of one town. ``DIR/shards.json`` records the split (its path as given, which the merged
manifest repeats, and its sha256), N and each shard's file, sha256 and episode ids.

**A shard's build** is ``agos dataset build`` unchanged; nothing in an episode's files depends on the
split around it, the run id or the worker that played it (``make slurm-test`` checks it), so an
episode's directory is the same bytes in a shard as in a one-host build.

**Merging** copies every shard's ``episodes/<episode>/`` into ``DATASET/episodes/`` (each file checked
against the episode's ``files.sha256`` on the way; ``--link`` hard-links them instead), makes the run
directory a one-host build would have (``dataset-<split sha256[:8]>``: ``run.json`` from the shards'
with the whole split as its source, ``episodes.jsonl``, and ``results.sqlite`` holding every shard's
records under the merged run id, so ``agos dataset build --split SPLIT --out DATASET`` finds nothing
left to play), then writes the top-level files with the build's own code
(:func:`agos.deploy.dataset.build.finish`): ``manifest.json``, ``export.jsonl`` (episodes in sorted
order, as a build writes it whatever order they finished in), ``dataset_info.json``, ``README.md``. An
expert failure of a shard goes to ``failed.jsonl`` in split order (a one-host build lists them in the
order they ended). What a one-host build writes that a merge does not: the run's logs.

A merge refuses, in one line naming the shard and the field: a shard built from another split than
its file in ``shards.json``; shards whose configuration (``config_hash``, look, views' spacing) or agos
(version, commit, uncommitted changes, lock, package versions) differ; an agos other than the shards'
doing the merge (it writes the top-level files); a shard not built, or with episodes neither
assembled nor failed (their ids are named: resubmit those array tasks, the builds resume).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
from rich.console import Console

from agos.agents.dataset.writer import EPISODES
from agos.deploy.dataset import build
from agos.deploy.run import plan as run_plan
from agos.runtime.episode_config import StoredConfigError, read_config
from agos.runtime.provenance import provenance
from agos.runtime.schemas import EpisodeSpec

PLAN = "shards.json"
SPLITS = "splits"
SHARDS = "shards"
PLAN_FORMAT = 1
ASSIGNMENT = "round-robin: the split's i-th episode (from 0) is in shard i mod N"
MERGING = ".merging"
"""Where an episode is copied before its one rename into ``episodes/`` (as a build assembles it)."""
SAME_IN_EVERY_SHARD = ("format", "config_hash", "look", "capture_every_m")
"""Manifest fields every shard must share (the configuration; the agos is compared from ``run.json``)."""
NAMED = 8
"""Episode ids a message names before it counts the rest."""


class ShardError(ValueError):
    """A shard plan that cannot be made, or shards that cannot be merged: one line naming what and why."""


@dataclass(frozen=True)
class Shard:
    """One shard of a plan: its index, its split file and the episodes in it, in split order."""

    index: int
    split: Path
    split_sha256: str
    episodes: list[str]

    def out(self, root: Path) -> Path:
        """Where its build writes (``DIR/shards/<k>``; the Slurm array task ``k`` does)."""
        return root / SHARDS / str(self.index)


# ----- shard -----------------------------------------------------------------------------------------
def shard(split: Path, shards: int, out_dir: Path) -> dict[str, Any]:
    """Write the plan and the N shard files of ``split`` into ``out_dir``; the plan. The same command
    again does nothing; another split or N into the same ``out_dir`` is refused."""
    from agos.world.episodes.files import EpisodeFileError, read_episodes

    try:
        specs = read_episodes(split)  # ids checked (unique); the towns are checked by each shard's build
    except EpisodeFileError as exc:
        raise ShardError(str(exc)) from None
    data = split.read_bytes()
    lines = [line for line in data.split(b"\n") if line.strip()]  # the lines read_episodes read, in order
    if not 1 <= shards <= len(specs):
        raise ShardError(f"--shards {shards}: give 1 to {len(specs)} (the episodes in {split}); every shard needs one")
    split_sha = hashlib.sha256(data).hexdigest()
    parts = [lines[k::shards] for k in range(shards)]
    ids = [[s.episode_id for s in specs[k::shards]] for k in range(shards)]
    plan = {
        "format": PLAN_FORMAT, "split": str(split), "split_sha256": split_sha, "episodes": len(specs),
        "shards": shards, "assignment": ASSIGNMENT,
        "parts": [{"shard": k, "split": f"{SPLITS}/{k}.jsonl",
                   "split_sha256": hashlib.sha256(b"".join(line + b"\n" for line in part)).hexdigest(),
                   "episodes": ids[k]} for k, part in enumerate(parts)],
    }
    existing = out_dir / PLAN
    if existing.exists():
        old = json.loads(existing.read_text())
        if (old.get("split_sha256"), old.get("shards")) != (split_sha, shards):
            raise ShardError(f"{out_dir} holds {old.get('shards')} shards of another split or count (split sha256 "
                             f"{str(old.get('split_sha256'))[:12]}; {split} is {split_sha[:12]}, --shards {shards}); "
                             "give another --out")
        return dict(old)
    (out_dir / SPLITS).mkdir(parents=True, exist_ok=True)
    for k, part in enumerate(parts):
        _write(out_dir / SPLITS / f"{k}.jsonl", b"".join(line + b"\n" for line in part))
    _write(existing, (json.dumps(plan, indent=1) + "\n").encode())  # last: a plan means its files are there
    return plan


def next_steps(plan: dict[str, Any], root: Path) -> str:
    """What ``agos dataset shard`` prints: the plan in a line, then how to build and merge the shards."""
    n, root = plan["shards"], root.resolve()
    sizes = sorted({len(p["episodes"]) for p in plan["parts"]})
    return "\n".join([
        f"{plan['episodes']} episodes of {plan['split']} in {n} shards of {'-'.join(map(str, sizes))} "
        f"({ASSIGNMENT}): {root / PLAN}, {root / SPLITS}/<k>.jsonl",
        "build each shard, on Slurm as one array job (the build flags in AGOS_DATASET_ARGS, the same for every task):",
        f"  AGOS_DATASET_SHARDS={root} sbatch --array=0-{n - 1} -N NODES deploy/slurm/agos-eval.sbatch",
        f"or anywhere: agos dataset build --split {root / SPLITS}/<k>.jsonl --out {root / SHARDS}/<k> [flags]",
        f"then: agos dataset merge {root} --out DATASET",
    ])


def read_plan(root: Path) -> tuple[dict[str, Any], list[Shard]]:
    """``root``'s plan and its shards (ShardError when there is none, or a shard file changed)."""
    path = root / PLAN
    if not path.is_file():
        raise ShardError(f"{root}: no {PLAN}; make the shards first: agos dataset shard --split SPLIT --shards N "
                         f"--out {root}")
    plan = json.loads(path.read_text())
    if plan.get("format") != PLAN_FORMAT:
        raise ShardError(f"{path}: format {plan.get('format')}, this agos reads {PLAN_FORMAT}; shard the split again")
    shards = [Shard(p["shard"], root / p["split"], p["split_sha256"], list(p["episodes"])) for p in plan["parts"]]
    for s in shards:
        if not s.split.is_file() or build._sha256(s.split) != s.split_sha256:
            raise ShardError(f"shard {s.index}: {s.split} is missing or changed since {path} was written; shard the "
                             "split again into a new directory")
    return plan, shards


# ----- merge -----------------------------------------------------------------------------------------
def merge(root: Path, out_dir: Path, *, link: bool = False, console: Console | None = None) -> int:
    """Merge the shards of ``root`` into ``out_dir`` (module docstring); the exit code: 0, or 1 when an
    episode's expert failed (as a build's). ShardError (one line) when the shards cannot be merged."""
    console = console or Console(soft_wrap=True)
    out_dir = out_dir.resolve()
    plan, shards = read_plan(root)
    split, split_sha = Path(plan["split"]), plan["split_sha256"]
    found = [_read_shard(s, root) for s in shards]
    _check_missing(shards, found, root)
    built = [f for f in found if f is not None]
    _check_same(built)
    made_from = json.loads((out_dir / build.MANIFEST).read_text()).get("split_sha256") \
        if (out_dir / build.MANIFEST).exists() else None
    if made_from is not None and made_from != split_sha:
        raise ShardError(f"{out_dir} holds a dataset of another split (sha256 {made_from[:12]}; the shards' split "
                         f"{split} is {split_sha[:12]}); give another --out")
    specs = _specs_in_split_order(plan, shards)
    run_dir = out_dir / f"dataset-{split_sha[:8]}"
    merged_plan = _write_run(run_dir, out_dir, split, specs, built)
    copied = 0
    for found_shard in built:
        for episode in found_shard.assembled:
            copied += _copy_episode(found_shard.out / EPISODES / episode, out_dir / EPISODES / episode,
                                    out_dir / MERGING / episode, link=link)
    shutil.rmtree(out_dir / MERGING, ignore_errors=True)
    failed = [line for f in built for line in f.failed_lines]
    order = {spec.episode_id: i for i, spec in enumerate(specs)}
    failed.sort(key=lambda line: order.get(json.loads(line)["episode_id"], len(order)))
    if failed:
        _write(out_dir / build.FAILED, "".join(failed).encode())
    else:
        (out_dir / build.FAILED).unlink(missing_ok=True)
    manifest = build.finish(out_dir, merged_plan, split, split_sha)
    c = manifest["counts"]
    console.print(f"dataset {out_dir}: {len(shards)} shards merged ({copied} episodes copied, the rest already "
                  f"there): {c['episodes']} of {len(specs)} episodes, {c['decisions']} decisions, {c['images']} images "
                  f"({c['bytes'] / 1e6:.1f} MB); {c['failed']} failed; export: {out_dir / build.EXPORT}",
                  highlight=False)
    return 1 if c["failed"] else 0


@dataclass
class _Built:
    shard: Shard
    out: Path
    manifest: dict[str, Any]
    run: dict[str, Any]
    assembled: list[str]
    failed_lines: list[str]


def _read_shard(s: Shard, root: Path) -> _Built | None:
    out = s.out(root)
    if not (out / build.MANIFEST).is_file():
        return None
    manifest = json.loads((out / build.MANIFEST).read_text())
    where = f"shard {s.index} ({out})"
    if manifest.get("split_sha256") != s.split_sha256:
        raise ShardError(f"{where}: split_sha256 {str(manifest.get('split_sha256'))[:12]} is not that of its file "
                         f"{s.split} ({s.split_sha256[:12]}): it was built from another split; build it again from "
                         f"{s.split} into an empty directory")
    run_file = out / str(manifest.get("run_dir")) / run_plan.RUN_FILE
    if not run_file.is_file():
        raise ShardError(f"{where}: no {run_file.relative_to(out)}; not a dataset build's directory")
    run = json.loads(run_file.read_text())
    failed_lines = (out / build.FAILED).read_text().splitlines(keepends=True) if (out / build.FAILED).exists() else []
    assembled = sorted(manifest.get("episodes", {}))
    strangers = sorted(set(assembled) - set(s.episodes))
    if strangers:
        raise ShardError(f"{where}: episodes {_named(strangers)} are not in its split {s.split}")
    for episode in assembled:
        hashes = out / EPISODES / episode / build.HASHES
        if not hashes.is_file() or build._sha256(hashes) != manifest["episodes"][episode]["files_sha256"]:
            raise ShardError(f"{where}: episode {episode}: {hashes.relative_to(out)} is missing or not the one its "
                             f"manifest.json names (files_sha256); run its build command again")
    return _Built(s, out, manifest, run, assembled, failed_lines)


def _check_missing(shards: list[Shard], found: list[_Built | None], root: Path) -> None:
    problems = []
    for s, f in zip(shards, found, strict=True):
        if f is None:
            problems.append(f"shard {s.index} ({s.out(root)}) is not built (no manifest.json): its episodes "
                            f"({len(s.episodes)}) {_named(s.episodes)}")
            continue
        failed = {json.loads(line)["episode_id"] for line in f.failed_lines}
        missing = [e for e in s.episodes if e not in f.manifest["episodes"] and e not in failed]
        if missing:
            problems.append(f"shard {s.index} ({f.out}) misses {len(missing)} of its {len(s.episodes)} episodes: "
                            f"{_named(missing)}")
    if problems:
        tasks = ",".join(str(s.index) for s, f in zip(shards, found, strict=True)
                         if f is None or any(p.startswith(f"shard {s.index} ") for p in problems))
        raise ShardError(f"episodes missing: {'; '.join(problems)}. Build them (the Slurm array tasks --array={tasks} "
                         f"again, or agos dataset build of each shard: it resumes), then merge again")


def _check_same(built: list[_Built]) -> None:
    """Every shard's configuration and agos are the first's, and this agos is theirs."""
    first = built[0]

    def fields(b: _Built) -> dict[str, Any]:
        made_by = b.run.get("provenance") or {}
        return {**{k: b.manifest.get(k) for k in SAME_IN_EVERY_SHARD},
                **{f"provenance.{k}": made_by.get(k) for k in ("agos", "commit", "dirty", "lock_sha256", "python")},
                **{f"provenance.packages.{k}": v for k, v in (made_by.get("packages") or {}).items()},
                "policies": b.run.get("policies")}

    want = fields(first)
    for b in built[1:]:
        got = fields(b)
        for key in sorted(want.keys() | got.keys()):
            if want.get(key) != got.get(key):
                raise ShardError(f"shard {b.shard.index} ({b.out}): {key} is {got.get(key)!r}, shard "
                                 f"{first.shard.index}'s is {want.get(key)!r}: merge only shards built with the same "
                                 "configuration and agos; build this one again into an empty directory")
    here = provenance()
    for key in ("agos", "commit"):
        if here.get(key) != want.get(f"provenance.{key}"):
            raise ShardError(f"this agos's {key} is {here.get(key)!r}, the shards' (shard {first.shard.index}, "
                             f"{first.out}) is {want.get(f'provenance.{key}')!r}: merge with the agos that built them "
                             "(it writes manifest.json and the card)")


def _specs_in_split_order(plan: dict[str, Any], shards: list[Shard]) -> list[EpisodeSpec]:
    """The split's episodes, in its order, from the shard files (round-robin undone)."""
    from agos.world.episodes.files import read_episodes

    per_shard = [read_episodes(s.split) for s in shards]
    n = len(shards)
    return [per_shard[i % n][i // n] for i in range(plan["episodes"])]


def _write_run(run_dir: Path, out_dir: Path, split: Path, specs: list[EpisodeSpec],
               built: list[_Built]) -> run_plan.RunPlan:
    """The merged run directory (module docstring) and its plan."""
    from agos.evaluator.store import ResultStore
    from agos.world.episodes.files import write_episodes

    first = built[0]
    try:
        config = read_config(first.run["episode_config"], where=str(first.out / first.manifest["run_dir"]))
    except (KeyError, StoredConfigError) as exc:
        raise ShardError(f"shard {first.shard.index} ({first.out}): run.json: {exc}") from None
    run = {**first.run, "run_id": run_dir.name, "episodes": len(specs), "dataset_out": str(out_dir),
           "episode_source": str(split),
           "merged_from": [{"shard": b.shard.index, "dir": str(b.out), "run_id": b.manifest["run_dir"],
                            "created_utc": b.run.get("created_utc")} for b in built]}
    run_dir.mkdir(parents=True, exist_ok=True)
    write_episodes(run_dir / "episodes.jsonl", specs)
    with ResultStore(run_dir / "results.sqlite") as store:
        for b in built:
            for record in build._stored_records(b.out / str(b.manifest["run_dir"])):  # re-stored under this run's id
                store.add(msgspec.structs.replace(record, run_id=run_dir.name))
    _write(run_dir / run_plan.RUN_FILE, (json.dumps(run, indent=2) + "\n").encode())
    return run_plan.RunPlan(run_dir, specs, dict(first.run.get("policies") or {}), config, resumed=True,
                            dataset_out=out_dir)


def _copy_episode(src: Path, dst: Path, tmp: Path, *, link: bool) -> int:
    """``src`` (an assembled episode) as ``dst``, every file checked against ``files.sha256``; 1 when
    copied, 0 when ``dst`` already holds it."""
    hashes = (src / build.HASHES).read_bytes()
    if (dst / build.HASHES).is_file() and (dst / build.HASHES).read_bytes() == hashes:
        return 0
    if tmp.exists():
        shutil.rmtree(tmp)
    for line in hashes.decode().splitlines():
        digest, rel = line.split("  ", 1)
        source, target = src / rel, tmp / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        if link:
            os.link(source, target)
            data = target.read_bytes()
        else:
            data = source.read_bytes()
            target.write_bytes(data)
        if hashlib.sha256(data).hexdigest() != digest:
            raise ShardError(f"{source}: sha256 differs from its line in {src / build.HASHES}: the file changed after "
                             "the build; build that shard again")
    (tmp / build.HASHES).write_bytes(hashes)
    if dst.exists():
        shutil.rmtree(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    os.rename(tmp, dst)
    return 1


def _named(ids: list[str]) -> str:
    return ", ".join(ids[:NAMED]) + (f" and {len(ids) - NAMED} more" if len(ids) > NAMED else "")


def _write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data)
    tmp.replace(path)

