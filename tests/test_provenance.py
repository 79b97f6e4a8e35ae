"""Provenance (runtime/provenance.py): what made a run or a record, beside the configuration and never in its hash."""

from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
from importlib import metadata
from pathlib import Path

import msgspec
import pytest

from agos.runtime.codec import from_json, to_json
from agos.runtime.episode_config import EpisodeConfig, config_hash
from agos.runtime.failure_records import failure_record
from agos.runtime.provenance import git_state, provenance
from agos.runtime.schemas import EpisodeRecord

from support.episodes import minimal_spec

ROOT = Path(__file__).resolve().parents[1]


def test_provenance_names_the_commit_the_lock_and_the_versions() -> None:
    found = provenance()
    assert found["agos"] == metadata.version("agos")
    assert found["lock_sha256"] == hashlib.sha256((ROOT / "uv.lock").read_bytes()).hexdigest()
    packages = found["packages"]
    for name in ("eclipse-zenoh", "pybullet", "numpy", "httpx"):
        assert packages[name] == metadata.version(name)
    assert any(name.startswith("opencv") for name in packages)
    if (ROOT / ".git").exists():  # a checkout (the tests' usual place)
        assert re.fullmatch(r"[0-9a-f]{40}", found["commit"]) and isinstance(found["dirty"], bool)
    found["packages"]["numpy"] = "changed"
    assert provenance()["packages"]["numpy"] == metadata.version("numpy")  # every call gets its own copy


def test_records_carry_it_beside_the_configuration_and_its_hash_is_unchanged() -> None:
    config = EpisodeConfig.model_validate({"ugv_speed_mps": 6.0})
    record = failure_record("r", minimal_spec("e1"), status="world_crashed", worker_id="w", error="x", config=config)
    assert record.provenance == provenance()
    assert "provenance" not in record.config and record.config == config.model_dump(mode="json")
    assert record.config_hash == config.config_hash() == config_hash(record.config)
    # A record stored before the field existed reads back with it empty, and is otherwise the same record.
    stored = json.loads(to_json(record))  # as the evaluator stores it
    assert list(stored)[-1] == "provenance"  # the last field: every field before it encodes as it did
    del stored["provenance"]
    old = from_json(json.dumps(stored), EpisodeRecord)
    assert old.provenance == {}
    assert msgspec.structs.replace(old, provenance=record.provenance) == record


def test_run_json_carries_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from agos.deploy.run.plan import RUN_FILE, new_plan
    from agos.runtime.settings import load_config
    from agos.world.episodes.files import read_episodes
    from agos.world.episodes.sampling import write_episodes

    monkeypatch.setattr("agos.world.episodes.files.read_split", lambda path, look=None: read_episodes(path))  # a made-up town
    write_episodes(tmp_path / "episodes.jsonl", [minimal_spec("e1")])
    cfg = load_config(overrides={"run": {"episodes_file": str(tmp_path / "episodes.jsonl"), "runs_dir": str(tmp_path)}})
    plan = new_plan(cfg, run_dir=tmp_path / "run", comm="ideal", timing_mode="lockstep", stamp=False)
    meta = json.loads((plan.run_dir / RUN_FILE).read_text())
    assert meta["provenance"] == provenance()
    assert meta["config_hash"] == plan.config.config_hash() == config_hash(meta["episode_config"])
    assert "provenance" not in meta["episode_config"]


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True, text=True).stdout.strip()


def _as_git_says(repo: Path) -> tuple[str, bool]:
    return _git(repo, "rev-parse", "HEAD"), bool(_git(repo, "status", "--porcelain", "--untracked-files=no"))


@pytest.mark.e2e  # starts git, to compare with what provenance reads from .git without it
def test_commit_and_dirty_agree_with_git(tmp_path: Path) -> None:
    repo = tmp_path / "repo"
    repo.mkdir()
    _git(repo, "init", "-q", "-b", "main")
    _git(repo, "config", "user.email", "t@example.org")
    _git(repo, "config", "user.name", "t")
    (repo / "a.txt").write_text("a\n")
    (repo / "d").mkdir()
    (repo / "d" / "x.py").write_text("x\n")
    (repo / "d-e").mkdir()  # sorts between "d" and "d/" in git's tree order
    (repo / "d-e" / "y").write_text("y\n")
    (repo / "d.z").write_text("z\n")
    (repo / "run.sh").write_text("#!/bin/sh\n")
    (repo / "run.sh").chmod(0o755)
    os.symlink("a.txt", repo / "link")
    _git(repo, "add", "-A")
    _git(repo, "commit", "-qm", "one")

    def same(step: str) -> None:
        assert git_state(repo) == _as_git_says(repo), step

    same("clean")
    (repo / "a.txt").write_text("b\n")
    same("modified")
    (repo / "a.txt").write_text("a\n")
    same("modified back: stat differs, content does not")
    (repo / "a.txt").write_text("c\n")
    _git(repo, "add", "a.txt")
    same("staged")
    _git(repo, "commit", "-qm", "two")
    (repo / "untracked").write_text("u\n")
    same("committed, one untracked file")
    (repo / "run.sh").chmod(0o644)
    same("executable bit dropped")
    (repo / "run.sh").chmod(0o755)
    (repo / "d" / "x.py").unlink()
    same("deleted")
    _git(repo, "checkout", "d/x.py")
    _git(repo, "gc", "-q")
    same("packed objects and refs")
    _git(repo, "reset", "-q", "--soft", "HEAD~")
    same("index ahead of HEAD")
    _git(repo, "reset", "-q", "--hard", "main@{1}")
    same("back")
    _git(repo, "worktree", "add", "-q", str(tmp_path / "wt"), "-b", "other")
    assert git_state(tmp_path / "wt") == _as_git_says(tmp_path / "wt")
    assert git_state(repo / "d") == (None, None) and git_state(tmp_path) == (None, None)  # not the top of a checkout
