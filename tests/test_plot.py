"""``agos plot`` (deploy/reports/plot.py): trajectory figures from a run's stored records.

Two run directories are made in-process (one episode, heuristic and random policies, the world's
own engine, a real result store), then drawn through the command line; the PNGs are read back and
must hold each path's colour, the target's and the town's roads, in each panel.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from agos.deploy.cli import main
from agos.deploy.reports.plot import COLOURS
from agos.evaluator.store import ResultStore
from agos.runtime.schemas import EpisodeRecord

ROAD_RGB = (70, 70, 72)  # world/towns/topdown.py, "road" (BGR there)


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> tuple[dict[str, Path], str, list[EpisodeRecord]]:
    from agos import Env
    from agos.agents.registry import make_policy
    from agos.runtime.episode_config import EpisodeConfig
    from agos.world.episodes.sampling import sample_episode, write_episodes
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import open_town

    town = open_town("grid-s7")
    root = tmp_path_factory.mktemp("runs")
    dirs, records = {}, []
    with Scene(town.layout, look="flat") as scene:
        spec = sample_episode(town, scene, "mid", 0, seed=3)
        for policy in ("heuristic", "random"):
            with Env(spec, EpisodeConfig(look="flat"), run_id=policy, scene=scene, town=town) as env:
                record = env.play({r: make_policy(policy, r) for r in ("uav", "ugv")})
            run_dir = root / policy
            write_episodes(run_dir / "episodes.jsonl", [spec])
            with ResultStore(run_dir / "results.sqlite") as store:
                store.add(record)
            (run_dir / "run.json").write_text(json.dumps({"policies": {"uav": policy, "ugv": policy}}))
            dirs[policy], records = run_dir, [*records, record]
    return dirs, spec.episode_id, records


def _pixels(image: np.ndarray, colour: str | tuple[int, int, int], tol: int = 12) -> int:
    """How many pixels of ``image`` (RGB(A) floats from imread) are within ``tol`` of ``colour``."""
    rgb = tuple(int(colour[k:k + 2], 16) for k in (1, 3, 5)) if isinstance(colour, str) else colour
    px = np.round(image[..., :3] * 255).astype(int)
    return int(np.count_nonzero(np.all(np.abs(px - np.array(rgb)) <= tol, axis=-1)))


@pytest.mark.slow
def test_the_step_log_holds_both_paths(runs) -> None:
    _, _, records = runs
    for record in records:
        roles = [s.role for s in record.step_log]
        assert roles.count("uav") == record.decisions_uav and roles.count("ugv") == record.decisions_ugv
        driven = [p for s in record.step_log for p in s.road_path_world_m]
        assert driven and record.ugv_path_length_m > 0
        assert sum(np.hypot(b[0] - a[0], b[1] - a[1]) for a, b in zip(driven, driven[1:], strict=False)) == \
            pytest.approx(record.ugv_path_length_m, rel=0.05)  # the roads as driven (simplified within 0.25 m)
        annotated = [s for s in record.step_log if s.applied == "ANNOTATE_CANDIDATE"]
        assert len(annotated) == len(record.candidates)
        assert all(len(s.candidate_polygon_world_m) == 4 for s in annotated)


@pytest.mark.slow
def test_plot_episode_draws_both_paths_the_target_and_the_map(runs, tmp_path: Path, capsys) -> None:
    dirs, episode, _ = runs
    out = tmp_path / "one.png"
    assert main(["plot", "episode", str(dirs["heuristic"]), episode, "--out", str(out)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    image = imread(out)
    assert image.shape[0] > 800 and image.shape[1] > 800
    for colour in (COLOURS["uav"], COLOURS["ugv"], COLOURS["target"], ROAD_RGB):
        assert _pixels(image, colour) > 100, colour
    assert _pixels(image, COLOURS["confirmed"]) + _pixels(image, COLOURS["false_confirm"]) > 50  # the CONFIRM marker


@pytest.mark.slow
def test_plot_compare_puts_two_policies_side_by_side(runs, tmp_path: Path) -> None:
    dirs, _, _ = runs
    out = tmp_path / "two.png"
    assert main(["plot", "compare", str(dirs["heuristic"]), str(dirs["random"] / "results.sqlite"),  # the episode:
                 "--out", str(out)]) == 0  # the first both runs finished
    image = imread(out)
    left, right = image[:, : image.shape[1] // 2], image[:, image.shape[1] // 2:]
    assert image.shape[1] > 1.7 * image.shape[0]
    for half in (left, right):
        for colour in (COLOURS["uav"], COLOURS["ugv"], COLOURS["target"], ROAD_RGB):
            assert _pixels(half, colour) > 100, colour


@pytest.mark.slow
def test_plot_says_what_is_missing(runs, tmp_path: Path, capsys) -> None:
    dirs, episode, _ = runs
    assert main(["plot", "episode", str(dirs["heuristic"]), "no-such-episode", "--out", str(tmp_path / "x.png")]) == 2
    assert "no record of episode 'no-such-episode'" in capsys.readouterr().err
    assert main(["plot", "episode", str(tmp_path), episode, "--out", str(tmp_path / "x.png")]) == 2
    assert "no results.sqlite" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()
