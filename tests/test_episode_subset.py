"""``agos episodes subset`` (world/episodes/subset.py): N episodes per town x difficulty cell, drawn by the
sha256 rank of seed and id, the split's lines unchanged. Unit tests (no processes)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import msgspec
import pytest

from agos.runtime.schemas import EpisodeSpec, TownRef
from agos.world.episodes.files import EpisodeFileError, write_episodes
from agos.world.episodes.subset import draw, rank, write_subset

from support.episodes import minimal_spec

TOWNS = ("grid-s7", "parks-s23")


def split_specs(per_cell: int = 4) -> list[EpisodeSpec]:
    """``per_cell`` episodes in each of 2 towns x 3 difficulties, interleaved as a split file has them."""
    out = []
    for k in range(per_cell):
        for town in TOWNS:
            for level in ("easy", "mid", "hard"):
                spec = minimal_spec(f"{town}-{level}-{k:03d}-v1")
                out.append(msgspec.structs.replace(spec, difficulty=level,
                                                   town=TownRef(generator=town.split("-")[0], seed=7, town_id=town)))
    return out


def test_each_cell_gives_its_lowest_ranked_episodes_in_file_order() -> None:
    specs = split_specs()
    chosen = draw(specs, per_cell=2, seed=5)
    assert chosen == sorted(chosen) and len(chosen) == 12
    for town in TOWNS:
        for level in ("easy", "mid", "hard"):
            cell = [s.episode_id for s in specs if s.town.town_id == town and s.difficulty == level]
            picked = [specs[k].episode_id for k in chosen if specs[k].episode_id in cell]
            assert sorted(picked) == sorted(sorted(cell, key=lambda e: rank(5, e))[:2])
    assert draw(specs, per_cell=2, seed=5) == chosen  # deterministic
    assert draw(specs, per_cell=2, seed=6) != chosen  # another seed, another draw
    assert draw(specs, per_cell=9, seed=5) == list(range(len(specs)))  # small cells are taken whole
    with pytest.raises(ValueError, match="--per-cell 0: give at least 1"):
        draw(specs, per_cell=0, seed=5)


def test_the_draw_is_pinned() -> None:
    """Seed 0, one per cell: the ids this draw gives, fixed by sha256 alone (a change here changes every
    published subset)."""
    assert rank(0, "x") == hashlib.sha256(b"0:x").hexdigest()
    chosen = [split_specs()[k].episode_id for k in draw(split_specs(), per_cell=1, seed=0)]
    assert chosen == PINNED


PINNED = ["grid-s7-mid-001-v1", "parks-s23-easy-001-v1", "grid-s7-easy-003-v1", "grid-s7-hard-003-v1",
          "parks-s23-mid-003-v1", "parks-s23-hard-003-v1"]


def test_adding_episodes_moves_a_cell_only_where_a_new_one_ranks_lower() -> None:
    specs = split_specs(4)
    before = {specs[k].episode_id for k in draw(specs, per_cell=2, seed=1)}
    more = split_specs(6)
    after = {more[k].episode_id for k in draw(more, per_cell=2, seed=1)}
    new = {s.episode_id for s in more} - {s.episode_id for s in specs}
    assert after - before <= new  # whatever changed was displaced by a new, lower-ranked episode


def test_the_subset_keeps_the_split_lines_byte_for_byte(tmp_path: Path, agos) -> None:
    split = tmp_path / "split.jsonl"
    write_episodes(split, split_specs())
    lines = split.read_bytes().splitlines(keepends=True)
    result = agos("episodes", "subset", split, "--per-cell", "1", "--seed", "0", "--out", tmp_path / "sub.jsonl")
    assert result.returncode == 0, result.stderr
    out = (tmp_path / "sub.jsonl").read_bytes()
    assert out.splitlines(keepends=True) == [lines[k] for k in draw(split_specs(), per_cell=1, seed=0)]
    assert result.stdout.strip() == (f"wrote 6 of 24 episodes to {tmp_path / 'sub.jsonl'} (1 per town x difficulty "
                                     f"cell, seed 0; 6 cells over grid-s7, parks-s23; sha256 "
                                     f"{hashlib.sha256(out).hexdigest()[:16]})")
    whole = agos("episodes", "subset", split, "--per-cell", "5", "--out", tmp_path / "all.jsonl")
    assert whole.returncode == 0 and "taken whole: grid-s7/easy 4," in whole.stdout
    assert (tmp_path / "all.jsonl").read_bytes() == split.read_bytes()
    bad = agos("episodes", "subset", split, "--per-cell", "0", "--out", tmp_path / "x.jsonl")
    assert bad.returncode == 2 and bad.stderr.strip() == "episodes error: --per-cell 0: give at least 1 episode per cell"
    with pytest.raises(EpisodeFileError, match="is the split itself"):
        write_subset(split, split, per_cell=1, seed=0)
    missing = agos("episodes", "subset", tmp_path / "none.jsonl", "--per-cell", "1", "--out", tmp_path / "y.jsonl")
    assert missing.returncode == 2 and "cannot read episode file" in missing.stderr
