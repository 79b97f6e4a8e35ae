"""A quick, representative subset of an episode file: ``agos episodes subset SPLIT --per-cell N --seed S
--out FILE``.

The episodes are grouped into cells by (town, difficulty) and each cell gives ``N`` of its episodes
(all of them when it has fewer), so every town and level of the split is in the subset in the same
proportion. Which ones is decided by rank alone: an episode's rank is the sha256 of
``"<seed>:<episode_id>"``, and a cell keeps its ``N`` lowest. The draw therefore depends on nothing
but the seed and the episode ids (no random generator whose stream could change between Python or
numpy versions), and it is stable: adding episodes to a split changes a cell's draw only where a new
episode ranks lower. The subset keeps the split's lines byte for byte, in the split's order, so its
episodes are the split's own (same ids, same seeds, same records when played).
"""

from __future__ import annotations

import hashlib
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from agos.runtime.schemas import EpisodeSpec
from agos.runtime.textfiles import one_line
from agos.world.episodes.files import EpisodeFileError, read_episodes

Cell = tuple[str, str]
"""(town id, difficulty)."""


def rank(seed: int, episode_id: str) -> str:
    """The draw's order key of an episode under ``seed`` (lowest first)."""
    return hashlib.sha256(f"{seed}:{episode_id}".encode()).hexdigest()


def cell_of(spec: EpisodeSpec) -> Cell:
    return spec.town.town_id, spec.difficulty


def draw(episodes: list[EpisodeSpec], *, per_cell: int, seed: int) -> list[int]:
    """Indices (ascending, i.e. in file order) of the ``per_cell`` lowest-ranked episodes of each cell."""
    if per_cell < 1:
        raise ValueError(f"--per-cell {per_cell}: give at least 1 episode per cell")
    cells: dict[Cell, list[int]] = {}
    for k, spec in enumerate(episodes):
        cells.setdefault(cell_of(spec), []).append(k)
    chosen: list[int] = []
    for members in cells.values():
        chosen += sorted(members, key=lambda k: rank(seed, episodes[k].episode_id))[:per_cell]
    return sorted(chosen)


@dataclass(frozen=True)
class Subset:
    """What :func:`write_subset` wrote."""

    path: Path
    chosen: int
    total: int
    cells: dict[Cell, tuple[int, int]]
    """Per cell: (episodes chosen, episodes in the split)."""
    sha256: str

    def summary(self, per_cell: int, seed: int) -> str:
        """One line for the console, and the cells that had fewer than ``per_cell`` episodes."""
        short = [f"{town}/{level} {n}" for (town, level), (n, size) in self.cells.items() if size < per_cell]
        towns = sorted({town for town, _ in self.cells})
        return (f"wrote {self.chosen} of {self.total} episodes to {self.path} ({per_cell} per town x difficulty cell, "
                f"seed {seed}; {len(self.cells)} cells over {', '.join(towns)}; sha256 {self.sha256[:16]})"
                + (f"; cells with fewer episodes than {per_cell}, taken whole: {', '.join(short)}" if short else ""))


def write_subset(split: Path, out: Path, *, per_cell: int, seed: int) -> Subset:
    """Read ``split`` (checked as every episode file is: world/episodes/files.py), draw, and write the
    chosen lines to ``out`` (written beside and renamed, so it is whole or absent). Refuses to write
    over ``split`` itself (EpisodeFileError, one line)."""
    if out.resolve() == split.resolve():
        raise EpisodeFileError(one_line(f"--out {out} is the split itself; give another file"))
    episodes = read_episodes(split)
    lines = [line for line in split.read_bytes().split(b"\n") if line.strip()]  # read_episodes' lines, in order
    chosen = draw(episodes, per_cell=per_cell, seed=seed)
    text = b"".join(lines[k].rstrip(b"\r") + b"\n" for k in chosen)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_bytes(text)
    tmp.replace(out)
    sizes = Counter(cell_of(e) for e in episodes)
    taken = Counter(cell_of(episodes[k]) for k in chosen)
    return Subset(out, len(chosen), len(episodes), {c: (taken[c], sizes[c]) for c in sizes},
                  hashlib.sha256(text).hexdigest())
