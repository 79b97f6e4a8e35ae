"""`agos episodes split` over imported towns: the paper's layout, its checks, and its files pinned.

Same arguments, same files, byte for byte, whatever the number of workers: the sha256 of every file
a split writes (train/val/test.jsonl and manifest.json) are pinned in
``world/episodes/pinned_splits.json``. The full ``--preset paper`` build (7,910 episodes, about 50
CPU-minutes) is too long for a test, so the test runs the same command at a small size over two
CARLA towns and a procedural test town (needs ``../shared/maps/carla``, skipped without it), with
1 and 2 workers; the full build's hashes are pinned beside them and checked when
``AGOS_PAPER_SPLIT_DIR`` names a directory that build wrote.

When an intended change (sampling, towns, the episode format) moves the hashes, re-pin the small
entries (~1 min) and say why in the commit::

    .venv/bin/python tests/test_paper_splits.py --repin

and, for the full preset, run its command (``pinned_splits.json``, ``paper.command``) and record
what it wrote::

    .venv/bin/python tests/test_paper_splits.py --pin-paper DIR
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from agos.runtime.episode_config import EpisodeConfig
from agos.world.episodes.sampling import DIFFICULTIES
from agos.world.episodes.splits import PAPER_COUNTS, PAPER_TRAINVAL_MAPS, SplitTown, check_disjoint, file_hashes, plan_jobs

REPO = Path(__file__).resolve().parents[1]
CARLA = REPO.parent / "shared" / "maps" / "carla"
PINNED = REPO / "world" / "episodes" / "pinned_splits.json"
REPIN = "re-pin: .venv/bin/python tests/test_paper_splits.py --repin (and say why in the commit)"

# The small entries: (name, split arguments, worker counts to run). {maps} is the CARLA maps folder;
# manifests hold no path, so the hashes do not depend on where it is.
SMALL = [
    ("carla2-flat", ["--towns", "{maps}/Town01.xodr,{maps}/Town02.xodr", "--test-town", "parks-s23",
                     "--train", "6", "--val", "3", "--test", "3", "--seed", "1", "--look", "flat"], [1, 2]),
    ("carla2-rich", ["--towns", "{maps}/Town02.xodr,{maps}/Town01.xodr", "--test-town", "parks-s23",
                     "--train", "6", "--val", "0", "--test", "3", "--seed", "2", "--look", "rich"], [1]),
]
PAPER_ARGS = ["--preset", "paper", "--test-town", "parks-s23", "--seed", "1", "--look", "rich"]


def agos_split(out: Path, args: list[str], *, workers: int, cache: Path) -> subprocess.CompletedProcess:
    """``agos episodes split`` as a user runs it, with a private asset cache (a fresh machine's)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("AGOS_")} | {"AGOS_ASSET_CACHE": str(cache)}
    argv = [a.replace("{maps}", str(CARLA)) for a in args]
    maps = [] if "--maps" in argv else ["--maps", str(CARLA)]
    return subprocess.run([sys.executable, "-m", "agos.deploy.cli", "episodes", "split", "--out", str(out), *argv,
                           "--workers", str(workers), *maps],
                          capture_output=True, text=True, timeout=300, env=env, cwd=REPO)


def _pinned() -> dict:
    return json.loads(PINNED.read_text())


# -- the pins -----------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def small_builds(tmp_path_factory) -> dict[tuple[str, int], Path]:
    """Every small entry built with each of its worker counts: {(name, workers): its directory}."""
    if not (CARLA / "Town01.xodr").exists():
        pytest.skip(f"the CARLA maps are not in {CARLA}")
    root = tmp_path_factory.mktemp("splits")
    built = {}
    for name, args, worker_counts in SMALL:
        for workers in worker_counts:
            out = root / f"{name}-w{workers}"
            proc = agos_split(out, args, workers=workers, cache=root / "cache")
            assert proc.returncode == 0, proc.stderr[-2000:]
            built[(name, workers)] = out
    return built


@pytest.mark.e2e  # the split's worker processes
@pytest.mark.parametrize("name,workers", [(n, w) for n, _, ws in SMALL for w in ws])
def test_small_split_files_match_the_pins(small_builds, name, workers) -> None:
    entry = _pinned()["small"][name]
    assert entry["args"] == next(a for n, a, _ in SMALL if n == name), f"{name}: arguments changed; {REPIN}"
    got = file_hashes(small_builds[(name, workers)])
    assert set(got) == set(entry["files"]), f"{name}: files {sorted(got)} != pinned {sorted(entry['files'])}; {REPIN}"
    moved = [f"{f} {got[f][:12]} (pinned {entry['files'][f][:12]})" for f in sorted(got) if got[f] != entry["files"][f]]
    assert not moved, f"{name} with --workers {workers}: same arguments, other bytes: {', '.join(moved)}; " \
                      f"if the change is intended, {REPIN}"


@pytest.mark.e2e  # the split's worker processes
def test_the_files_do_not_depend_on_the_number_of_workers(small_builds) -> None:
    for name, _, worker_counts in SMALL:
        if len(worker_counts) > 1:
            first, *others = (file_hashes(small_builds[(name, w)]) for w in worker_counts)
            assert all(o == first for o in others), f"{name}: files differ between --workers {worker_counts}"


def test_the_full_paper_preset_is_pinned_with_its_command() -> None:
    paper = _pinned()["paper"]
    assert paper["args"] == PAPER_ARGS
    assert paper["command"] == "agos episodes split --out splits-paper " + " ".join(PAPER_ARGS)
    assert paper["files"] is None or set(paper["files"]) == {"train.jsonl", "val.jsonl", "test.jsonl", "manifest.json"}


@pytest.mark.skipif(not os.environ.get("AGOS_PAPER_SPLIT_DIR"), reason="set AGOS_PAPER_SPLIT_DIR to a full preset build")
def test_a_full_paper_preset_build_matches_the_pin() -> None:
    paper = _pinned()["paper"]
    if paper["files"] is None:
        pytest.skip("the full preset is not pinned yet")
    assert file_hashes(Path(os.environ["AGOS_PAPER_SPLIT_DIR"])) == paper["files"]


# -- what the manifest says ---------------------------------------------------------------------------

@pytest.mark.e2e  # the split's worker processes
def test_the_manifest_records_towns_look_counts_and_files(small_builds) -> None:
    out = small_builds[("carla2-rich", 1)]
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["look"] == "rich" and manifest["seed"] == 2 and manifest["preset"] is None
    assert manifest["counts"] == {"train": 6, "val": 0, "test": 3}
    assert manifest["per_difficulty"]["test"] == {"easy": 1, "mid": 1, "hard": 1}
    assert [t["town_id"] for t in manifest["towns"]["trainval"]] == ["Town02", "Town01"]
    assert [t["town_id"] for t in manifest["towns"]["test"]] == ["parks-s23"]
    assert all(len(t["sha256"]) == 64 for ts in manifest["towns"].values() for t in ts)
    assert manifest["files"] == {k: v for k, v in file_hashes(out).items() if k != "manifest.json"}
    assert not (out / "val.jsonl").exists()
    test_lines = (out / "test.jsonl").read_text().splitlines()
    assert all('"parks-s23-test-' in line and '-rich-v1"' in line for line in test_lines)
    # imported towns land in the asset cache, where agos eval finds them
    cache = out.parent / "cache"
    assert all((cache / t["sha256"] / "asset.msgpack").exists() for t in manifest["towns"]["trainval"])


# -- checks before any sampling: one line, exit 2 -------------------------------------------------------

def _refused(agos, tmp_path: Path, *args: str) -> str:
    """``agos episodes split ARGS`` in this process (the guard holds it to starting nothing): its one line."""
    maps = [] if "--maps" in args else ["--maps", str(CARLA)]
    proc = agos("episodes", "split", "--out", tmp_path / "never", *args, "--workers", "1", *maps,
                env={"AGOS_ASSET_CACHE": str(tmp_path / "cache")}, cwd=REPO)
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("episodes error: "), proc.stderr
    assert not (tmp_path / "never").exists()
    return lines[0]


def test_the_paper_preset_needs_a_test_town(tmp_path, agos) -> None:
    line = _refused(agos, tmp_path, "--preset", "paper")
    assert "--test-town" in line and "Town01" in line


def test_the_paper_preset_needs_its_maps(tmp_path, agos) -> None:
    line = _refused(agos, tmp_path, "--preset", "paper", "--test-town", "parks-s23", "--maps", str(tmp_path / "nowhere"))
    assert str(tmp_path / "nowhere" / "Town01.xodr") in line and "--maps" in line


def test_an_unknown_town_is_named(tmp_path, agos) -> None:
    line = _refused(agos, tmp_path, "--towns", "grid-s7,atlantis", "--test-town", "parks-s23")
    assert "'atlantis'" in line and "agos map import" in line
    line = _refused(agos, tmp_path, "--towns", "grid-s7", "--test-town", str(tmp_path / "Town99.xodr"))
    assert "Town99.xodr" in line


def test_the_test_town_must_be_held_out(tmp_path, agos) -> None:
    line = _refused(agos, tmp_path, "--towns", "grid-s7,parks-s23")
    assert "parks-s23" in line and "--test-town" in line


def test_disjointness_is_by_id_and_by_asset() -> None:
    a, b = SplitTown("Town01", "opendrive", 0, "a" * 64, "x"), SplitTown("Town02", "opendrive", 0, "b" * 64, "y")
    check_disjoint([a, b], [SplitTown("parks-s23", "parks", 23, "c" * 64, "parks-s23")])
    with pytest.raises(ValueError, match="test town"):
        check_disjoint([a, b], [SplitTown("renamed", "opendrive", 0, "a" * 64, "z")])
    with pytest.raises(ValueError, match="given twice"):
        check_disjoint([a, SplitTown("Town01", "opendrive", 0, "d" * 64, "w")], [])


# -- the paper's counts and balance -----------------------------------------------------------------------

def test_the_paper_counts_are_spread_evenly_over_towns_and_difficulties() -> None:
    towns = [SplitTown(n, "opendrive", 0, str(i) * 64, n) for i, n in enumerate(PAPER_TRAINVAL_MAPS)]
    test_town = [SplitTown("parks-s23", "parks", 23, "f" * 64, "parks-s23")]
    jobs = plan_jobs(train=PAPER_COUNTS["train"], val=PAPER_COUNTS["val"], test=PAPER_COUNTS["test"],
                     trainval_towns=towns, test_towns=test_town, seed=1, look="rich")
    for split, total in PAPER_COUNTS.items():
        cells: dict[tuple[str, str], int] = {}
        for j in jobs:
            if j.split == split:
                cells[(j.town.town_id, j.difficulty)] = cells.get((j.town.town_id, j.difficulty), 0) + j.count
        assert sum(cells.values()) == total
        assert max(cells.values()) - min(cells.values()) <= 1, f"{split}: {cells}"
        per_difficulty = [sum(n for (_, d), n in cells.items() if d == diff) for diff in DIFFICULTIES]
        assert max(per_difficulty) - min(per_difficulty) <= 1, f"{split}: {per_difficulty}"
        if split == "test":
            assert cells == {("parks-s23", d): 70 for d in DIFFICULTIES}
    assert all(j.count <= 10 for j in jobs)


def test_the_samplers_default_look_is_the_episode_configurations() -> None:
    from agos.deploy.cli import build_parser

    default = EpisodeConfig.model_fields["look"].default
    parser = build_parser()
    for argv in (["episodes", "split", "--out", "x"], ["episodes", "sample", "--out", "x"]):
        assert parser.parse_args(argv).look == default


# -- re-pinning -------------------------------------------------------------------------------------------

def _repin_small() -> None:
    import tempfile

    pinned = _pinned() if PINNED.exists() else {}
    with tempfile.TemporaryDirectory() as tmp:
        small = {}
        for name, args, _ in SMALL:
            out = Path(tmp) / name
            proc = agos_split(out, args, workers=2, cache=Path(tmp) / "cache")
            if proc.returncode != 0:
                sys.exit(proc.stderr)
            small[name] = {"args": args, "files": file_hashes(out)}
    pinned["small"] = small
    if pinned.get("paper", {}).get("files"):  # whatever moved the small files moved the full preset's too
        print("the full preset's pin is cleared: build it again and --pin-paper it")
    pinned["paper"] = {"args": PAPER_ARGS, "command": "", "files": None}
    _write(pinned)


def _pin_paper(out_dir: Path) -> None:
    manifest = json.loads((out_dir / "manifest.json").read_text())
    want = {"preset": "paper", "seed": 1, "look": PAPER_ARGS[PAPER_ARGS.index("--look") + 1], "counts": PAPER_COUNTS}
    got = {k: manifest.get(k) for k in want}
    if got != want or [t["town_id"] for t in manifest["towns"]["test"]] != ["parks-s23"]:
        sys.exit(f"{out_dir} is not the pinned preset's build ({got}); run the command in {PINNED.name}")
    pinned = _pinned()
    pinned["paper"]["files"] = file_hashes(out_dir)
    _write(pinned)


def _write(pinned: dict) -> None:
    pinned["about"] = ("sha256 of the files `agos episodes split` writes, pinned: the same arguments give the same "
                       "files byte for byte. Checked by tests/test_paper_splits.py, which says how to re-pin.")
    pinned["paper"]["args"] = PAPER_ARGS
    pinned["paper"]["command"] = "agos episodes split --out splits-paper " + " ".join(PAPER_ARGS)
    order = ["about", "small", "paper"]
    PINNED.write_text(json.dumps({k: pinned[k] for k in order}, indent=2) + "\n")
    print(f"wrote {PINNED}")


if __name__ == "__main__":
    if sys.argv[1:] == ["--repin"]:
        _repin_small()
    elif len(sys.argv) == 3 and sys.argv[1] == "--pin-paper":
        _pin_paper(Path(sys.argv[2]))
    else:
        sys.exit(__doc__)
