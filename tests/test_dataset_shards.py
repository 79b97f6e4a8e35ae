"""``agos dataset shard`` and ``agos dataset merge`` in-process (deploy/dataset/shards.py), on builds made
of synthetic episodes: each "build" is episode directories as the assembler leaves them, finished by
the build's own :func:`agos.deploy.dataset.build.finish`, the code that writes a real build's top-level
files. A merge of the shards' builds equals the whole split's build, file for file (sha256); mismatched
or missing shards are refused in one line naming the shard and the field or the episodes. The real
thing, rendered episodes built by Slurm array tasks: ``make slurm-test`` (tests/deploy/slurm_e2e.py).
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Any

import pytest

from agos.deploy.dataset import build, shards
from agos.deploy.run.plan import RUN_FILE, RunPlan
from agos.runtime.codec import to_json
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.provenance import provenance
from agos.runtime.schemas import EpisodeSpec

from support.episodes import minimal_spec

IDS = [f"grid-s7-easy-{i:03d}-v1" for i in range(5)]
EXPERT = {"uav": "expert", "ugv": "expert"}


def write_split(path: Path, ids: list[str]) -> list[EpisodeSpec]:
    specs = [minimal_spec(i) for i in ids]
    path.write_bytes(b"".join(to_json(s) + b"\n" for s in specs))
    return specs


def fake_build(out: Path, split: Path, *, assembled: list[str] | None = None, failed: tuple[str, ...] = (),
               config: EpisodeConfig | None = None, made_by: dict[str, Any] | None = None) -> None:
    """What ``agos dataset build --split SPLIT --out OUT`` leaves, its episodes synthetic: the run's
    run.json, each assembled episode's directory (two decisions, their images, export lines, Parquet,
    files.sha256) and the top-level files from :func:`build.finish`."""
    from agos.world.episodes.files import read_episodes

    specs = read_episodes(split)
    config = config or EpisodeConfig(look="flat", capture_every_m=50.0)
    sha = hashlib.sha256(split.read_bytes()).hexdigest()
    run_dir = out / f"dataset-{sha[:8]}"
    run_dir.mkdir(parents=True)
    (run_dir / RUN_FILE).write_text(json.dumps({
        "run_id": run_dir.name, "created_utc": "2026-01-01T00:00:00+00:00", "policies": EXPERT,
        "episode_config": config.model_dump(mode="json"), "provenance": made_by or provenance()}) + "\n")
    for spec in specs:
        episode = spec.episode_id
        if episode in failed:
            with (out / build.FAILED).open("a") as f:
                f.write(json.dumps({"episode_id": episode, "problem": "synthetic"}) + "\n")
            continue
        if assembled is not None and episode not in assembled:
            continue
        ep = out / "episodes" / episode
        (ep / "episode.json").parent.mkdir(parents=True)
        (ep / "episode.json").write_text(json.dumps({"episode_id": episode, "town_id": "grid-s7", "difficulty": "easy",
                                                     "outcome": {"decisions_uav": 1, "decisions_ugv": 1}}) + "\n")
        for role in build.ROLES:
            image = f"{role}/d001/view.jpg"
            (ep / image).parent.mkdir(parents=True)
            (ep / image).write_bytes(hashlib.sha256(f"{episode}/{role}".encode()).digest() * 50)
            line = {"id": f"{episode}/{role}/1", "episode_id": episode, "role": role, "decision_index": 1,
                    "stage": "search", "legal_actions": ["WAIT"],
                    "messages": [{"role": "user", "content": "<image>"}, {"role": "assistant", "content": "{}"}],
                    "images": [f"episodes/{episode}/{image}"]}
            (ep / role / "export.jsonl").write_text(json.dumps(line, separators=(",", ":")) + "\n")
        build._write_parquet(ep, episode)
        (ep / build.HASHES).write_text("".join(f"{digest}  {rel}\n" for rel, digest in build._hashes(ep)))
    build.finish(out.resolve(), RunPlan(run_dir, specs, EXPERT, config), split, sha)


def tree(root: Path) -> dict[str, str]:
    """sha256 of every file under ``root``, the run's folder (its logs, results.sqlite) left out."""
    run = json.loads((root / "manifest.json").read_text())["run_dir"]
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and p.relative_to(root).parts[0] != run}


@pytest.fixture
def sharded(tmp_path: Path) -> tuple[Path, Path, dict[str, str]]:
    """A 5-episode split in 2 shards, each shard built; the whole split's build in ``whole/``; the merge
    goes to ``ds/`` (nothing in a dataset names its directory: the card says ``--out DIR``)."""
    split = tmp_path / "split.jsonl"
    write_split(split, IDS)
    fake_build(tmp_path / "whole", split)
    root = tmp_path / "sh"
    shards.shard(split, 2, root)
    for k in (0, 1):
        fake_build(root / "shards" / str(k), root / "splits" / f"{k}.jsonl")
    return root, tmp_path / "ds", tree(tmp_path / "whole")


def test_a_split_is_dealt_round_robin_line_for_line(tmp_path: Path) -> None:
    split = tmp_path / "split.jsonl"
    write_split(split, IDS)
    plan = shards.shard(split, 2, tmp_path / "sh")
    lines = split.read_bytes().splitlines(keepends=True)
    assert (tmp_path / "sh/splits/0.jsonl").read_bytes() == b"".join(lines[0::2])
    assert (tmp_path / "sh/splits/1.jsonl").read_bytes() == b"".join(lines[1::2])
    assert [p["episodes"] for p in plan["parts"]] == [IDS[0::2], IDS[1::2]]
    assert plan["split"] == str(split) and plan["split_sha256"] == hashlib.sha256(split.read_bytes()).hexdigest()
    assert shards.shard(split, 2, tmp_path / "sh") == plan  # the same command again: nothing changes
    with pytest.raises(shards.ShardError, match="holds 2 shards of another split or count"):
        shards.shard(split, 3, tmp_path / "sh")
    with pytest.raises(shards.ShardError, match=r"--shards 6: give 1 to 5"):
        shards.shard(split, 6, tmp_path / "other")


def test_the_merged_shards_are_the_whole_build_file_for_file(sharded: tuple[Path, Path, dict[str, str]]) -> None:
    root, out, whole = sharded
    assert shards.merge(root, out) == 0
    merged = tree(out)
    assert {"manifest.json", "export.jsonl", "README.md", "dataset_info.json"} <= merged.keys()
    assert len([k for k in merged if k.endswith("export.parquet")]) == len(IDS)
    assert merged == whole
    run = json.loads((out / f"dataset-{json.loads((out / 'manifest.json').read_text())['split_sha256'][:8]}"
                      / RUN_FILE).read_text())
    assert run["episodes"] == len(IDS) and [m["shard"] for m in run["merged_from"]] == [0, 1]
    assert shards.merge(root, out) == 0 and tree(out) == whole  # again: nothing to copy, the same files
    shutil.rmtree(out)
    assert shards.merge(root, out, link=True) == 0 and tree(out) == whole
    assert (out / "episodes" / IDS[0] / "episode.json").stat().st_nlink == 2


def test_a_failed_episode_is_no_missing_one(tmp_path: Path) -> None:
    split = tmp_path / "split.jsonl"
    write_split(split, IDS)
    root = tmp_path / "sh"
    shards.shard(split, 2, root)
    fake_build(root / "shards/0", root / "splits/0.jsonl", failed=(IDS[4], IDS[2]))
    fake_build(root / "shards/1", root / "splits/1.jsonl")
    assert shards.merge(root, tmp_path / "ds") == 1
    failed = [json.loads(x)["episode_id"] for x in (tmp_path / "ds/failed.jsonl").read_text().splitlines()]
    assert failed == [IDS[2], IDS[4]]  # split order
    assert json.loads((tmp_path / "ds/manifest.json").read_text())["counts"]["failed"] == 2


def refused(root: Path, out: Path) -> str:
    with pytest.raises(shards.ShardError) as exc:
        shards.merge(root, out)
    message = str(exc.value)
    assert "\n" not in message and not out.exists()
    return message


def test_a_missing_shard_or_episode_is_refused_by_name(sharded: tuple[Path, Path, dict[str, str]]) -> None:
    root, out, _ = sharded
    shutil.rmtree(root / "shards/1")
    message = refused(root, out)
    assert f"shard 1 ({root / 'shards/1'}) is not built" in message and f"{IDS[1]}, {IDS[3]}" in message
    assert "--array=1 " in message
    fake_build(root / "shards/1", root / "splits/1.jsonl", assembled=[IDS[1]])
    assert f"shard 1 ({root / 'shards/1'}) misses 1 of its 2 episodes: {IDS[3]}. " in refused(root, out)


@pytest.mark.parametrize(("change", "field"), [
    ({"config": EpisodeConfig(look="flat", capture_every_m=20.0)}, "capture_every_m"),
    ({"config": EpisodeConfig(look="flat", capture_every_m=50.0, uav_speed_mps=12.0)}, "config_hash"),
    ({"made_by": {**provenance(), "commit": "0" * 40}}, "provenance.commit"),
    ({"made_by": {**provenance(), "packages": {**provenance()["packages"], "numpy": "0.0"}}},
     "provenance.packages.numpy"),
])
def test_shards_of_another_configuration_or_agos_are_refused(sharded: tuple[Path, Path, dict[str, str]],
                                                             change: dict[str, Any], field: str) -> None:
    root, out, _ = sharded
    shutil.rmtree(root / "shards/1")
    fake_build(root / "shards/1", root / "splits/1.jsonl", **change)
    message = refused(root, out)
    assert message.startswith(f"shard 1 ({root / 'shards/1'}): {field} is "), message


def test_a_shard_of_another_split_is_refused(sharded: tuple[Path, Path, dict[str, str]], tmp_path: Path) -> None:
    root, out, _ = sharded
    other = tmp_path / "other.jsonl"
    write_split(other, [IDS[1]])
    shutil.rmtree(root / "shards/1")
    fake_build(root / "shards/1", other)
    assert refused(root, out).startswith(f"shard 1 ({root / 'shards/1'}): split_sha256 ")


def test_merging_needs_the_plan(tmp_path: Path) -> None:
    with pytest.raises(shards.ShardError, match=r"no shards\.json; make the shards first"):
        shards.merge(tmp_path, tmp_path / "ds")


def test_a_resumed_build_lists_a_failed_episode_once(tmp_path: Path) -> None:
    """On resume the stored records come back to the assembler: a failure already listed stays one line."""
    from rich.console import Console

    from agos.deploy.dataset.build import FAILED, Assembler
    from agos.runtime.schemas import EpisodeRecord

    record = EpisodeRecord(
        run_id="r", episode_id=IDS[0], difficulty="easy", status="finished", termination="budget_exhausted",
        success=False, ground_observed=False, n_confirm=0, ugv_path_length_m=100.0, shortest_path_length_m=50.0,
        final_distance_m=10.0, uav_budget=80, uav_first_visible_step=3, candidates=[], decisions_uav=10,
        decisions_ugv=5, sim_time_s=60.0, wall_time_s=1.0, worker_id="w", town_id="t", asset_sha256="0" * 64, seed=1,
        renderer="pybullet-tiny")
    assembler = Assembler(tmp_path, {}, Console(quiet=True))
    assembler(record)
    assembler(record)  # the resumed build's pass over the stored records
    lines = (tmp_path / FAILED).read_text().splitlines()
    assert [json.loads(line)["episode_id"] for line in lines] == [IDS[0]]
