"""The small things a new user meets (issue 30, item 6): a sweep refuses a wrong ``--param`` or value
before it draws its progress bar, ``episodes sample`` says what is wrong with a count below 1, ``agos
watch`` says truly what it prints and prints times to the hundredth, and the outputs of the README's
own commands are ignored by git. In-process: nothing starts."""

from __future__ import annotations

from pathlib import Path

import msgspec
import pytest

from agos.runtime.observer import describe
from agos.world.episodes.files import write_episodes

from support.episodes import grid_episodes

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def split(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("split") / "eps.jsonl"
    write_episodes(path, grid_episodes())
    return path


@pytest.mark.parametrize(("flags", "says"), [
    (("--param", "loss.q"), "sweep error: sweep parameter 'loss.q': not a field of a comm profile"),
    (("--param", "loss.p", "--values", "0,2"), "sweep error: sweep parameter loss.p=2: Input should be less than or equal to 1"),
    (("--param", "loss.burst_len"), "sweep error: sweep parameter loss.burst_len: the base profile 'ideal' has no "
                                    "Gilbert-Elliott loss"),
])
def test_sweep_refuses_its_parameter_before_its_progress_bar(split: Path, tmp_path: Path, agos, flags, says: str) -> None:
    out = agos("sweep", "--split", split, "--out", tmp_path / "sweep", *flags)
    assert out.returncode == 2 and out.stderr.strip() == out.stderr.strip().splitlines()[0], out
    assert out.stderr.startswith(says), out
    assert not out.stdout and not (tmp_path / "sweep").exists()  # no bar drawn, nothing made


@pytest.mark.parametrize(("flags", "says"), [
    (("--per-difficulty", "0"), "episodes error: --per-difficulty 0: give at least 1 episode per difficulty"),
    (("--per-difficulty", "-2"), "episodes error: --per-difficulty -2: give at least 1 episode per difficulty"),
    (("--difficulty", "hard", "-n", "0"), "episodes error: -n 0: give at least 1 episode of --difficulty hard"),
    ((), "episodes error: give --difficulty D -n N or --per-difficulty N: how many episodes to sample"),
])
def test_episodes_sample_says_what_is_wrong_with_a_count(tmp_path: Path, agos, flags, says: str) -> None:
    out = agos("episodes", "sample", "--town", "no-such-town", "--out", tmp_path / "e.jsonl", *flags)
    assert out.returncode == 2 and out.stderr.strip() == says  # before the town: a wrong count costs no build


def test_watch_help_says_what_it_prints_by_default(agos) -> None:
    out = agos("watch", "--help")
    text = " ".join(out.stdout.split())
    assert out.returncode == 0 and "print the visualisation stream of every run, one line a message" in text
    assert "--key 'agos/**' prints every message instead" in text
    assert "--episode EP only the messages of one episode" in text
    listed = " ".join(agos("--help").stdout.split())
    assert "print the runs' visualisation stream" in listed and "every message under agos/**" not in listed


def test_watch_prints_times_to_the_hundredth() -> None:
    step = {"type": "step", "v": 3, "role": "ugv", "decision_index": 7, "applied": "STOP_OBSERVE",
            "sim_time_s": 47.27230898491565}
    line = describe("agos/r/viz/w/events", msgspec.msgpack.encode(step))
    assert " ugv#7 STOP_OBSERVE t=47.27 " in line and "47.272" not in line
    coord = {"type": "coordination_state", "v": 3, "sim_time_s": 3.0, "candidates": [{}, {}]}
    assert "t=3.00 candidates=2" in describe("agos/r/viz/w/coord", msgspec.msgpack.encode(coord))


def test_watch_names_each_messages_episode_and_follows_one_by_it(capsys) -> None:
    """Keys name world workers, not episodes: ``agos watch --episode EP`` keeps what names EP in its payload."""
    from agos.runtime.observer import printer

    def step(episode: str) -> bytes:
        return msgspec.msgpack.encode({"type": "step", "v": 3, "episode_id": episode, "role": "uav", "decision_index": 1,
                                       "applied": "WAIT", "sim_time_s": 1.0})

    assert "v3 step ep=e1 uav#1 WAIT t=1.00 " in describe("agos/r/viz/w/events", step("e1"))
    samples = [("agos/r/viz/w/events", step("e1")), ("agos/r/viz/w/events", step("e2")),
               ("agos/r/viz/w/events", b"\x93garbage"), ("agos/r/ctl/manifest", msgspec.msgpack.encode({"v": 3}))]
    for episode, kept in ((None, 4), ("e2", 1)):
        show = printer(episode)
        for key, payload in samples:
            show(key, payload)
        lines = capsys.readouterr().out.splitlines()
        assert len(lines) == kept, lines
    assert "ep=e2" in lines[0]


def test_the_outputs_of_the_readmes_commands_are_ignored() -> None:
    from test_doc_paths import ignored

    for output in ("data/sample", "assets/Town01", "splits/val.jsonl", "splits-paper/test.jsonl", "report/table.md",
                   "rec/ep.rrd", "recordings/ep.rrd", "runs/val-lossy", "certs/ca.key"):
        assert ignored(output), output
    assert not ignored("deploy/configs/demo.toml") and not ignored("world/episodes/files.py")
