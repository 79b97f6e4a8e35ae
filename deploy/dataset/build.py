"""``agos dataset build``: AGOS-Dataset from an episode split, built by leased world workers.

    agos dataset build --split val.jsonl --out data/val [--workers N] [--look rich] [--capture-every 10]

A build is an evaluation run of the ``expert`` policy (comm ideal, lockstep, the rich look unless
``--look flat``) in
``DIR/dataset-<split hash>``, with the same leases, re-leases and resume as ``agos eval``; its two
agents write every decision under
``DIR/.partial`` (agents/dataset/writer.py) and its world workers render each role's camera every
``--capture-every`` metres between decisions too. Each stored record is *assembled* here, on the
build's thread: a successful episode whose two roles wrote every decision the record counts gets
``episode.json`` (spec, outcome, the expert's trajectories), ``export.parquet`` (its examples with their
images embedded, deploy/dataset/loading.py) and ``files.sha256``, and its directory
is moved into ``DIR/episodes/<episode>`` in one rename, so an episode is either whole there or absent.
An episode the expert failed (a bug in the dataset or the checker: the expert must succeed) is listed
in ``failed.jsonl`` and left in ``.partial`` for a look. At the end (also after Ctrl-C) ``export.jsonl``
(every decision's fine-tuning example, paths relative to ``DIR``) and ``manifest.json`` (counts, the
split's sha256, the configuration hash, the agos commit, each episode's ``files.sha256`` hash) are
written again from what is assembled, and with them what trainers' loaders read: LLaMA-Factory's
``dataset_info.json`` and the dataset card ``README.md``, whose ``configs`` point ``datasets`` at the
Parquet files (deploy/dataset/loading.py).

Run the same command again to resume: stored episodes are skipped, and a stored episode whose files
were not assembled yet (the build stopped in between) is assembled from ``.partial``. On many hosts,
start the agents where ``DIR`` is (``agos agent --role R --policy expert --dataset-out DIR``), world
workers anywhere, and this command with ``--connect EP --run RUN`` on the agents' host
(docs/DATASET.md).
"""

from __future__ import annotations

import hashlib
import json
import os
import shlex
import shutil
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Console

from agos.agents.dataset.writer import EPISODES, PARTIAL
from agos.deploy.dataset import loading
from agos.deploy.run import evaluate
from agos.deploy.run import plan as run_plan
from agos.runtime.episode_config import DEFAULT_LOOK
from agos.runtime.keys import ROLES
from agos.runtime.schemas import EpisodeRecord, EpisodeSpec
from agos.runtime.settings import AgosConfig

MANIFEST = "manifest.json"
EXPORT = "export.jsonl"
FAILED = "failed.jsonl"
EPISODE_FILE = "episode.json"
HASHES = "files.sha256"


class DatasetError(ValueError):
    """A build that cannot start or go on; the message names the file and what to do."""


@dataclass
class Assembler:
    """Moves finished episodes from ``.partial`` into ``episodes/`` (module docstring)."""

    out_dir: Path
    specs: dict[str, EpisodeSpec]
    console: Console = field(default_factory=Console)

    def __call__(self, record: EpisodeRecord) -> None:
        problem = self.assemble(record)
        if problem is not None:
            self.console.print(f"[red]dataset: {record.episode_id} not added: {problem}", highlight=False)
            if record.episode_id in _failed_ids(self.out_dir):
                return  # listed by the build this one resumes (its stored records come back on resume)
            with (self.out_dir / FAILED).open("a") as f:
                f.write(json.dumps({"episode_id": record.episode_id, "difficulty": record.difficulty,
                                    "termination": record.termination, "problem": problem}) + "\n")

    def assemble(self, record: EpisodeRecord) -> str | None:
        """Add ``record``'s episode to the dataset; the reason when it cannot be."""
        final = self.out_dir / EPISODES / record.episode_id
        if (final / EPISODE_FILE).exists():
            return None  # assembled by an earlier build
        if not record.success:
            return f"the expert did not succeed ({record.status}, {record.termination}); its files stay in " \
                   f"{self.out_dir / PARTIAL / record.episode_id}"
        attempt = _latest_attempt(self.out_dir / PARTIAL / record.episode_id)
        if attempt is None:
            return f"no decisions were written under {self.out_dir / PARTIAL / record.episode_id} (were the agents " \
                   "started with --dataset-out on this directory?)"
        counts = {"uav": record.decisions_uav, "ugv": record.decisions_ugv}
        for role in ROLES:
            written = _lines(attempt / role / "decisions.jsonl")
            if written != counts[role]:
                return f"{role}: {written} decisions written, the record has {counts[role]} (an agent restarted " \
                       "mid-episode?); rebuild it"
        expert: dict[str, Any] = {role: json.loads((attempt / role / "expert.json").read_text()) for role in ROLES}
        spec = self.specs[record.episode_id]
        (attempt / EPISODE_FILE).write_text(json.dumps(_episode_doc(spec, record, expert), indent=1) + "\n")
        _write_parquet(attempt, record.episode_id)
        (attempt / HASHES).write_text("".join(f"{digest}  {rel}\n" for rel, digest in _hashes(attempt)))
        if final.exists():
            shutil.rmtree(final)
        final.parent.mkdir(parents=True, exist_ok=True)
        os.rename(attempt, final)  # the whole episode appears at once
        shutil.rmtree(self.out_dir / PARTIAL / record.episode_id, ignore_errors=True)
        return None


def build(cfg: AgosConfig, split: Path, out_dir: Path, *, workers: int, capture_every_m: float, look: str = DEFAULT_LOOK,
          attach: bool = False, port: int | None = None, config_path: Path | None = None,
          console: Console | None = None) -> int:
    """Build (or resume) the dataset of ``split`` in ``out_dir`` drawn with ``look``; the exit code. A
    resumed build keeps the configuration it was started with (``run.json``)."""
    console = console or Console(soft_wrap=True)  # paths and commands it prints are never cut at the width
    out_dir = out_dir.resolve()
    try:
        loading.check_pyarrow()
    except loading.LoadingFilesError as exc:
        raise DatasetError(str(exc)) from None
    split_sha = _sha256(split)
    run_dir = out_dir / (cfg.run.run_id if attach else f"dataset-{split_sha[:8]}")
    made_from = json.loads((out_dir / MANIFEST).read_text()).get("split_sha256") if (out_dir / MANIFEST).exists() else None
    if made_from is not None and made_from != split_sha:
        raise DatasetError(f"{out_dir} holds a build of another split (sha256 {made_from[:12]}; {split} is "
                           f"{split_sha[:12]}); give another --out")
    if (run_dir / run_plan.RUN_FILE).exists():
        plan = run_plan.resume_plan(run_dir)
        console.print(f"resuming the build in {out_dir}", highlight=False)
    else:
        run = cfg.run.model_copy(update={"episodes_file": split, "policy_uav": "expert", "policy_ugv": "expert"})
        world = cfg.world.model_copy(update={"capture_every_m": capture_every_m, "look": look})
        cfg = cfg.model_copy(update={"run": run, "world": world})
        plan = run_plan.new_plan(cfg, run_dir=run_dir, comm="ideal", timing_mode="lockstep", stamp=False,
                                 workers=workers, dataset_out=out_dir)
    assembler = Assembler(out_dir, {s.episode_id: s for s in plan.episodes}, console)
    _write_manifest(out_dir, plan, split, split_sha)  # the split's hash first: a resume checks it
    for record in _stored_records(run_dir):  # stored before an interruption, not yet assembled
        assembler(record)
    try:
        code = evaluate.run(cfg, plan, workers=workers, attach=attach, port=port, config_path=config_path,
                            console=console, on_record=assembler,
                            resume=resume_command(split, out_dir, workers=workers, attach=attach, cfg=cfg,
                                                  config_path=config_path))
    finally:
        manifest = finish(out_dir, plan, split, split_sha)
    c = manifest["counts"]
    console.print(f"dataset {out_dir}: {c['episodes']} of {len(plan.episodes)} episodes, {c['decisions']} decisions, "
                  f"{c['images']} images ({c['bytes'] / 1e6:.1f} MB); {c['failed']} failed; export: {out_dir / EXPORT}",
                  highlight=False)
    return code if code else (1 if c["failed"] else 0)


def finish(out_dir: Path, plan: run_plan.RunPlan, split: Path, split_sha: str) -> dict[str, Any]:
    """The top-level files, written again from what ``episodes/`` holds: ``manifest.json`` (returned),
    ``export.jsonl`` and the loaders' files. ``agos dataset merge`` (shards.py) ends with this too, so a
    merged build's files are a one-host build's: add a top-level file here, not in :func:`build`."""
    _add_missing_parquet(out_dir)
    manifest = _write_manifest(out_dir, plan, split, split_sha)
    _write_export(out_dir, sorted(manifest["episodes"]))
    loading.write_loading_files(out_dir, manifest, out_dir / EXPORT)
    return manifest


def resume_command(split: Path, out_dir: Path, *, workers: int, attach: bool, cfg: AgosConfig,
                   config_path: Path | None) -> str:
    """The command that resumes a build: this one again (``agos eval --resume`` would play the missing
    episodes but leave the export and the manifest incomplete). The build's configuration is its run's
    (``run.json``); the flags here say only where and with how many workers."""
    words = ["agos", "dataset", "build", "--split", str(split), "--out", str(out_dir)]
    if config_path is not None:
        words += ["--config", str(config_path)]
    if workers != 1:
        words += ["--workers", str(workers)]
    if attach:
        words += ["--connect", cfg.zenoh.connect, "--run", cfg.run.run_id]
    return shlex.join(words)


# ----- the files ------------------------------------------------------------------------------
def _episode_doc(spec: EpisodeSpec, record: EpisodeRecord, expert: dict[str, dict[str, Any]]) -> dict[str, Any]:
    uav, ugv = expert["uav"], expert["ugv"]
    return {
        "episode_id": spec.episode_id, "town_id": record.town_id, "asset_sha256": record.asset_sha256,
        "difficulty": spec.difficulty, "seed": spec.seed, "decision_budget": spec.decision_budget,
        "target": {"model": spec.target.model, "colour": spec.target.colour,
                   "position_world_m": list(spec.target.position_world_m)},
        "outcome": {"success": record.success, "termination": record.termination, "sim_time_s": record.sim_time_s,
                    "decisions_uav": record.decisions_uav, "decisions_ugv": record.decisions_ugv,
                    "ugv_path_length_m": record.ugv_path_length_m,
                    "shortest_path_length_m": record.shortest_path_length_m, "config_hash": record.config_hash},
        "expert": {"t_f_s": uav["t_f_s"], "t_arr_s": uav["t_arr_s"], "finder": uav["finder"],
                   "wrong_candidates": uav["wrong_candidates"],
                   "raw_trajectory": {"uav": uav["raw_trajectory"], "ugv": ugv["raw_trajectory"]},
                   "trajectory": {"uav": uav["trajectory"], "ugv": ugv["trajectory"]},
                   "steps": {"uav": uav["steps"], "ugv": ugv["steps"]}},
    }


def _failed_ids(out_dir: Path) -> set[str]:
    path = out_dir / FAILED
    return {json.loads(line)["episode_id"] for line in path.read_text().splitlines() if line} if path.exists() else set()


def _write_manifest(out_dir: Path, plan: run_plan.RunPlan, split: Path, split_sha: str) -> dict[str, Any]:
    episodes: dict[str, Any] = {}
    decisions = images = size = 0
    for ep_dir in sorted((out_dir / EPISODES).glob("*/")):
        hashes = ep_dir / HASHES
        if not (ep_dir / EPISODE_FILE).exists() or not hashes.exists():
            continue
        doc = json.loads((ep_dir / EPISODE_FILE).read_text())
        lines = hashes.read_text().splitlines()
        n_images = sum(1 for line in lines if line.endswith((".jpg", ".png")))
        n_bytes = sum((ep_dir / line.split("  ", 1)[1]).stat().st_size for line in lines)
        n_decisions = doc["outcome"]["decisions_uav"] + doc["outcome"]["decisions_ugv"]
        episodes[ep_dir.name] = {"difficulty": doc["difficulty"], "town_id": doc["town_id"], "decisions": n_decisions,
                                 "images": n_images, "bytes": n_bytes, "files_sha256": _sha256(hashes)}
        decisions, images, size = decisions + n_decisions, images + n_images, size + n_bytes
    failed = _lines(out_dir / FAILED)
    run_file = plan.run_dir / run_plan.RUN_FILE
    made_by = json.loads(run_file.read_text()).get("provenance", {}) if run_file.exists() else {}
    manifest = {
        "format": 1, "split": str(split), "split_sha256": split_sha, "run_dir": plan.run_dir.name,
        "config_hash": plan.config.config_hash(), "look": plan.config.look, "capture_every_m": plan.config.capture_every_m,
        "provenance": {key: made_by.get(key) for key in ("agos", "commit", "dirty")},  # of the process that began it
        "counts": {"episodes": len(episodes), "decisions": decisions, "images": images, "bytes": size,
                   "failed": failed, "split": len(plan.episodes)},
        "episodes": episodes,
    }
    tmp = out_dir / f".{MANIFEST}.tmp"
    out_dir.mkdir(parents=True, exist_ok=True)
    tmp.write_text(json.dumps(manifest, indent=1) + "\n")
    tmp.replace(out_dir / MANIFEST)
    return manifest


def _write_export(out_dir: Path, episodes: list[str]) -> None:
    """``export.jsonl``: every assembled episode's examples, episode by episode, UAV then UGV."""
    tmp = out_dir / f".{EXPORT}.tmp"
    with tmp.open("w") as out:
        for episode in episodes:
            for role in ROLES:
                path = out_dir / EPISODES / episode / role / EXPORT
                out.write(path.read_text())
    tmp.replace(out_dir / EXPORT)


def _write_parquet(episode_dir: Path, episode_id: str) -> None:
    """``export.parquet`` of an episode's directory (deploy/dataset/loading.py): both roles' examples, UAV
    then UGV, as ``export.jsonl`` lists them, with their images."""
    lines = [json.loads(line) for role in ROLES for line in (episode_dir / role / EXPORT).read_text().splitlines()]
    loading.write_episode_parquet(lines, episode_dir, f"{EPISODES}/{episode_id}/", episode_dir / loading.PARQUET)


def _add_missing_parquet(out_dir: Path) -> None:
    """Episodes assembled before builds wrote ``export.parquet`` get it, and its line in ``files.sha256``."""
    for ep_dir in sorted((out_dir / EPISODES).glob("*/")):
        if (ep_dir / EPISODE_FILE).exists() and (ep_dir / HASHES).exists() and not (ep_dir / loading.PARQUET).exists():
            _write_parquet(ep_dir, ep_dir.name)
            (ep_dir / HASHES).write_text("".join(f"{digest}  {rel}\n" for rel, digest in _hashes(ep_dir)))


def _stored_records(run_dir: Path) -> Iterator[EpisodeRecord]:
    from agos.evaluator.store import ResultStore

    path = run_dir / "results.sqlite"
    if not path.exists():
        return
    with ResultStore(path, create=False) as store:
        yield from store.records()


def _latest_attempt(episode_partial: Path) -> Path | None:
    attempts = sorted((p for p in episode_partial.glob("a*") if p.name[1:].isdigit()), key=lambda p: int(p.name[1:]))
    return attempts[-1] if attempts else None


def _hashes(root: Path) -> list[tuple[str, str]]:
    return [(p.relative_to(root).as_posix(), _sha256(p)) for p in sorted(root.rglob("*")) if p.is_file()
            and p.name != HASHES]


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _lines(path: Path) -> int:
    return sum(1 for _ in path.open()) if path.exists() else 0
