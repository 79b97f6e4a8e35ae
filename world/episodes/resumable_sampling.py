"""``agos episodes sample``'s file, sampled so that an interruption loses nothing: each episode is
appended to ``OUT.partial`` as soon as it is sampled, and ``OUT`` is written whole at the end. The same
sampling again (same town, seed, look and plan: the partial file's first line) goes on from the
episodes that file kept; sampling is deterministic per episode, so the file is the one an
uninterrupted run writes. What is kept is only ever appended to, never rewritten."""

from __future__ import annotations

import json
from pathlib import Path
from typing import BinaryIO

import msgspec

from agos.runtime.codec import to_json
from agos.runtime.schemas import Difficulty, EpisodeSpec
from agos.world.episodes import sampling
from agos.world.towns.asset import Town

PARTIAL_SUFFIX = ".partial"
"""``agos episodes sample --out OUT`` keeps the episodes sampled so far in ``OUT`` + this."""


class SamplingInterrupted(KeyboardInterrupt):
    """Ctrl-C while sampling: ``kept`` episodes of the plan are in the partial file."""

    def __init__(self, kept: int) -> None:
        super().__init__(kept)
        self.kept = kept


def sample_plan(*, difficulty: Difficulty | None, n: int, per_difficulty: int | None) -> list[tuple[Difficulty, int]]:
    """The (difficulty, count) pairs of ``--difficulty D -n N`` or ``--per-difficulty N`` (which wins);
    ValueError (one line) for counts below 1 or none."""
    if per_difficulty is not None:
        if per_difficulty < 1:
            raise ValueError(f"--per-difficulty {per_difficulty}: give at least 1 episode per difficulty")
        return [(d, per_difficulty) for d in sampling.DIFFICULTIES]
    if difficulty:
        if n < 1:
            raise ValueError(f"-n {n}: give at least 1 episode of --difficulty {difficulty}")
        return [(difficulty, n)]
    raise ValueError("give --difficulty D -n N or --per-difficulty N: how many episodes to sample")


def kept_episodes(partial: Path, header: bytes) -> tuple[list[EpisodeSpec], int]:
    """The episodes an interrupted run of the same sampling (``header``, the file's first line) left in
    ``partial``, in order, and where the last whole one ends; none when there is no such file or it is
    another sampling's."""
    try:
        data = partial.read_bytes()
    except OSError:
        return [], 0
    if not data.startswith(header):
        return [], 0
    kept, end = [], len(header)
    while (stop := data.find(b"\n", end)) >= 0:
        try:
            kept.append(msgspec.json.decode(data[end:stop], type=EpisodeSpec))
        except msgspec.DecodeError:
            break
        end = stop + 1
    return kept, end


class ResumableSampling:
    """The episodes of ``plan`` on ``town`` into ``out``, going on from what ``out``'s partial file kept
    (:attr:`kept`, read when made)."""

    def __init__(self, town: Town, plan: list[tuple[Difficulty, int]], out: Path, *, seed: int, look: str) -> None:
        self.town, self.out, self.seed, self.look = town, out, seed, look
        self.todo = [(d, i) for d, n in plan for i in range(n)]
        self.partial = out.with_name(out.name + PARTIAL_SUFFIX)
        self.header = json.dumps({"sampling": {"town": town.town_id, "asset_sha256": town.sha256, "seed": seed,
                                               "look": look, "plan": [[d, n] for d, n in plan]}}).encode() + b"\n"
        self.episodes, self._end = kept_episodes(self.partial, self.header)
        self.kept = len(self.episodes)
        """Episodes sampled before, by an interrupted run of the same sampling."""

    @property
    def total(self) -> int:
        return len(self.todo)

    def run(self) -> None:
        """Sample the rest, then write ``out`` whole and remove the partial file. Ctrl-C while sampling
        raises :class:`SamplingInterrupted` (a KeyboardInterrupt), the partial file kept."""
        from agos.world.sim.scene import Scene

        fh: BinaryIO
        if self.episodes:
            fh = self.partial.open("r+b")
            fh.truncate(self._end)  # a line cut short by the interruption
            fh.seek(self._end)
        else:
            self.partial.parent.mkdir(parents=True, exist_ok=True)
            fh = self.partial.open("wb")
            fh.write(self.header)
        with fh:
            try:
                if len(self.episodes) < len(self.todo):
                    with Scene(self.town.layout, look=self.look) as scene:
                        for d, i in self.todo[len(self.episodes):]:
                            self.episodes.append(sampling.sample_episode(self.town, scene, d, i, seed=self.seed,
                                                                         stream=sampling.DIFFICULTIES.index(d)))
                            fh.write(to_json(self.episodes[-1]) + b"\n")
                            fh.flush()
            except KeyboardInterrupt:
                raise SamplingInterrupted(len(self.episodes)) from None
        sampling.write_episodes(self.out, self.episodes[:len(self.todo)])
        self.partial.unlink()
