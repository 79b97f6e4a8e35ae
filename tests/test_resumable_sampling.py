"""``agos episodes sample``'s resumable file (world/episodes/resumable_sampling.py): the plan its
counts make, what an interrupted sampling's partial file keeps, and going on from it. Units: a stand-in
town and sampler, no scene, no processes."""

from __future__ import annotations

from contextlib import nullcontext
from pathlib import Path
from types import SimpleNamespace

import msgspec
import pytest

from agos.runtime.codec import to_json
from agos.world.episodes import sampling
from agos.world.episodes.resumable_sampling import (
    PARTIAL_SUFFIX,
    ResumableSampling,
    SamplingInterrupted,
    kept_episodes,
    sample_plan,
)
from agos.world.sim import scene as scene_module

from support.episodes import minimal_spec

TOWN = SimpleNamespace(town_id="grid-s7", sha256="ab" * 32, layout=None)


def test_the_plan_of_the_counts() -> None:
    assert sample_plan(difficulty=None, n=1, per_difficulty=2) == [("easy", 2), ("mid", 2), ("hard", 2)]
    assert sample_plan(difficulty="hard", n=3, per_difficulty=None) == [("hard", 3)]
    with pytest.raises(ValueError, match=r"^--per-difficulty 0: give at least 1 episode per difficulty$"):
        sample_plan(difficulty="easy", n=1, per_difficulty=0)
    with pytest.raises(ValueError, match=r"^-n 0: give at least 1 episode of --difficulty mid$"):
        sample_plan(difficulty="mid", n=0, per_difficulty=None)
    with pytest.raises(ValueError, match="give --difficulty D -n N or --per-difficulty N"):
        sample_plan(difficulty=None, n=1, per_difficulty=None)


def test_kept_episodes_are_the_whole_lines_of_the_same_sampling(tmp_path: Path) -> None:
    partial = tmp_path / "e.jsonl.partial"
    assert kept_episodes(partial, b"h\n") == ([], 0)  # no file
    a, b = minimal_spec("a"), minimal_spec("b")
    whole = b"h\n" + to_json(a) + b"\n" + to_json(b) + b"\n"
    partial.write_bytes(whole + b'{"type":"episode_spec","episode_id":"c')  # a line cut short
    kept, end = kept_episodes(partial, b"h\n")
    assert kept == [a, b] and end == len(whole)
    assert kept_episodes(partial, b"another sampling\n") == ([], 0)


def test_an_interrupted_sampling_goes_on_where_it_stopped(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    asked: list[tuple[str, int]] = []
    stop_after = [1]

    def fake_sample(town, scene, difficulty, index, *, seed, stream, **_):  # type: ignore[no-untyped-def]
        if len(asked) == stop_after[0]:
            raise KeyboardInterrupt
        asked.append((difficulty, index))
        return msgspec.structs.replace(minimal_spec(f"{difficulty}-{index}-{seed}"), difficulty=difficulty)

    monkeypatch.setattr(sampling, "sample_episode", fake_sample)
    monkeypatch.setattr(scene_module, "Scene", lambda *_, **__: nullcontext())  # no scene is built
    out = tmp_path / "sub" / "e.jsonl"
    plan = sample_plan(difficulty=None, n=1, per_difficulty=1)
    first = ResumableSampling(TOWN, plan, out, seed=4, look="flat")  # type: ignore[arg-type]
    assert (first.kept, first.total, first.partial) == (0, 3, out.with_name("e.jsonl" + PARTIAL_SUFFIX))
    with pytest.raises(SamplingInterrupted) as stopped:
        first.run()
    assert isinstance(stopped.value, KeyboardInterrupt) and stopped.value.kept == 1
    assert not out.exists() and len(first.partial.read_bytes().splitlines()) == 2  # the header and one episode

    assert ResumableSampling(TOWN, plan, out, seed=5, look="flat").kept == 0  # type: ignore[arg-type]
    stop_after[0] = 99
    again = ResumableSampling(TOWN, plan, out, seed=4, look="flat")  # type: ignore[arg-type]
    assert again.kept == 1
    again.run()
    assert asked == [("easy", 0), ("mid", 0), ("hard", 0)]  # each episode sampled once over both runs
    assert [s.episode_id for s in sampling.read_episodes(out)] == ["easy-0-4", "mid-0-4", "hard-0-4"]
    assert not again.partial.exists()
