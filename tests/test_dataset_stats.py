"""``agos dataset stats``: counts that match the files of a real (tiny) dataset, the figure, and one
clear line for a directory that is not a dataset.

The dataset is made in-process the way a build makes it: the expert plays two episodes of grid-s7
(easy, mid) with the dataset writer as both agents and views every 25 m (the default is 10: fewer
renders, the same code), and each record is assembled by the build's own Assembler;
``export.jsonl`` is the roles' examples joined, as the build writes it at its end (about 7 s).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from rich.console import Console

from agos import Env
from agos.agents.dataset.writer import DatasetWriter
from agos.deploy.cli import main
from agos.deploy.dataset.build import Assembler
from agos.deploy.dataset.stats import _bins, _nice_step, read_dataset
from agos.runtime.episode_config import EpisodeConfig, ToolConfig
from agos.world.episodes.sampling import sample_episode
from agos.world.sim.scene import Scene
from agos.world.towns.asset import open_town

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("dataset")
    town = open_town("grid-s7")
    with Scene(town.layout, look="flat") as scene:
        # seed 4: both UGVs drive (one that starts where it can confirm passes nothing on the way)
        specs = [sample_episode(town, scene, d, 0, seed=4, stream=k) for k, d in enumerate(("easy", "mid"))]
        assembler = Assembler(root, {s.episode_id: s for s in specs}, Console(quiet=True))
        config = EpisodeConfig(look="flat", tools=ToolConfig(expert=True), capture_every_m=25.0)
        for spec in specs:
            with Env(spec, config, run_id="t", scene=scene, town=town) as env:
                record = env.play({r: DatasetWriter(r, root) for r in ("uav", "ugv")})
            assert assembler.assemble(record) is None, spec.episode_id
    with (root / "export.jsonl").open("w") as out:
        for role_export in sorted(root.glob("episodes/*/*/export.jsonl")):
            out.write(role_export.read_text())
    return root


@pytest.mark.slow
def test_the_counts_are_those_of_the_files(dataset: Path) -> None:
    stats = read_dataset(dataset)
    assert sorted(e.difficulty for e in stats.episodes) == ["easy", "mid"]
    for e in stats.episodes:
        ep_dir = dataset / "episodes" / e.episode_id
        doc = json.loads((ep_dir / "episode.json").read_text())
        assert e.decisions == {"uav": doc["outcome"]["decisions_uav"], "ugv": doc["outcome"]["decisions_ugv"]}
        on_disk = [p for p in ep_dir.rglob("*") if p.suffix in (".jpg", ".png")]
        assert e.image_files == len(on_disk)
        assert e.images["depth"] == e.images["semantic"] == len([p for p in on_disk if p.stem.endswith("_depth")])
        assert e.passed_views == len([p for p in on_disk if "passed" in p.parts and p.stem.endswith("_depth")]) > 0
        assert e.export_lines == e.total_decisions
        assert e.bytes == sum(p.stat().st_size for p in ep_dir.rglob("*") if p.is_file())  # no manifest: walked
        assert e.t_f_s <= e.t_arr_s and e.ugv_path_m > 0
    assert stats.export_lines == sum(e.total_decisions for e in stats.episodes)


@pytest.mark.slow
def test_the_command_prints_the_table_and_writes_the_figure(dataset: Path, tmp_path: Path, capsys,
                                                            monkeypatch) -> None:
    monkeypatch.setenv("AGOS_WORLD__UAV_SPEED_MPS", "fast")  # settings that cannot load: stats never reads them
    figure = tmp_path / "figure.png"
    assert main(["dataset", "stats", str(dataset), "--out", str(figure), "--markdown"]) == 0
    out = capsys.readouterr().out
    stats = read_dataset(dataset)
    lines = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]] for line in out.splitlines()
             if line.startswith("| ")}
    assert lines["quantity"] == ["easy", "mid", "overall"]
    assert lines["episodes"] == ["1", "1", "2"]
    decisions = sum(e.decisions["ugv"] for e in stats.episodes)
    assert lines["decisions UGV"][-1] == f"{decisions:,}"
    assert lines["image files"][-1] == f"{sum(e.image_files for e in stats.episodes):,}"
    assert lines["export lines"][-1] == f"{stats.export_lines:,}"
    assert "towns: grid-s7 (2)" in out and f"figure: {figure}" in out
    assert figure.read_bytes()[:8] == PNG_MAGIC and figure.stat().st_size > 20_000


@pytest.mark.slow
def test_the_figure_goes_into_the_dataset_by_default(dataset: Path, capsys) -> None:
    assert main(["dataset", "stats", str(dataset)]) == 0
    out = " ".join(capsys.readouterr().out.split())  # rich wraps at the terminal's width
    assert "overall" in out and "wrong-candidate episodes" in out
    assert (dataset / "stats.png").read_bytes()[:8] == PNG_MAGIC


@pytest.mark.parametrize("make", ["empty", "missing", "manifest only"])
def test_a_directory_that_is_not_a_dataset_is_one_line_and_exit_2(tmp_path: Path, capsys, make: str) -> None:
    target = tmp_path / "data"
    if make != "missing":
        target.mkdir()
    if make == "manifest only":
        (target / "manifest.json").write_text(json.dumps({"format": 1, "episodes": {}}))
    assert main(["dataset", "stats", str(target)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert len(captured.err.strip().splitlines()) == 1
    assert str(target) in captured.err and "agos dataset build" in captured.err
    assert not (target / "stats.png").exists()


def test_bins_are_round_and_cover_every_value() -> None:
    assert [_nice_step(x) for x in (0.7, 3.0, 23.0, 46.0, 460.0)] == [1.0, 5.0, 25.0, 50.0, 500.0]
    values = [12.0, 87.5, 462.0]
    edges = _bins(values, integer=False)
    assert edges[0] <= min(values) and edges[-1] >= max(values) and edges[1] - edges[0] == 50.0
    counts = _bins([4.0, 54.0], integer=True)
    assert counts[0] == 3.5 and all(float(e).is_integer() is False for e in counts)  # whole numbers sit mid-bin


@pytest.mark.slow
def test_the_behaviour_cloning_example_learns_from_the_datasets_files(dataset: Path, monkeypatch) -> None:
    """examples/bc_data_loop.py (docs/LIBRARY.md): one example per decision the files hold, each labelled
    with the expert's action and drawn from the image its decision names; the numpy fit runs."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1]))
    from examples import bc_data_loop

    for role in ("uav", "ugv"):
        lines = [json.loads(line) for f in sorted(dataset.glob(f"episodes/*/{role}/decisions.jsonl"))
                 for line in f.read_text().splitlines()]
        items = list(bc_data_loop.examples(dataset, role, size_px=16))
        assert [bc_data_loop.ACTIONS[role][e.label] for e in items] == [line["action"]["action"] for line in lines]
        assert all(e.image.shape == (16, 16, 3) and e.image.max() > 0 and e.legal[e.label] == 1 for e in items)
        accuracy, n = bc_data_loop.fit(dataset, role, epochs=5)
        assert n == len(lines) and 0.0 < accuracy <= 1.0
        assert 0 < len(list(bc_data_loop.decisions(dataset, role, episodes=1))) < len(lines)  # the first episode's
