"""Episode sampling per difficulty (paper Table 1), solvability by rendering, and the
``agos episodes`` commands.

Full solvability is checked on three towns (grid-s7, tee-s17, parks-s23), one episode per
difficulty each; deck-s19 pins that decks hide the road from the air. The CONFIRM checker's four
conditions are tested in tests/test_geometry_confirm.py and not repeated here.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import msgspec
import numpy as np
import pytest

from agos.runtime.codec import to_json
from agos.runtime.schemas import EpisodeSpec
from agos.world.episodes.sampling import (
    DIFFICULTIES,
    MIN_LOOKALIKE_SPACING_M,
    MIN_START_DISTANCE_M,
    REGION_SIZE_M,
    generate_episodes,
    read_episodes,
    sample_episode,
)
from agos.world.episodes.solvability import UAV_VISIBLE_MIN_PX, check, reachable
from agos.world.episodes.splits import SPLIT_STREAMS
from agos.world.sim import sensors
from agos.world.sim.scene import Scene
from agos.world.towns.asset import Town, build_town
from agos.world.towns.catalog import BODY_TYPES, NEAR_COLOURS, VIVID_COLOURS
from agos.world.towns.lanes import Lane, LaneNetwork
from agos.world.towns.layout import Deck, TownLayout
from agos.world.towns.placement import ParkingSlot
from agos.world.towns.procedural import TEST_TOWNS, TOWNS
from agos.world.towns.streets import strip

pytestmark = pytest.mark.slow  # samples and renders episodes of every town: make test, not make check

SEED = 1
SOLVE_TOWNS = ("grid-s7", "tee-s17", "parks-s23")
CASES = [(t, d) for t in SOLVE_TOWNS for d in DIFFICULTIES]


@pytest.fixture(scope="module")
def worlds():
    out: dict[str, tuple[Town, Scene]] = {}
    for town_id in (*SOLVE_TOWNS, "deck-s19"):
        town = build_town(*TOWNS[town_id])
        out[town_id] = (town, Scene(town.layout, look="flat"))
    yield out
    for _, scene in out.values():
        scene.close()


@pytest.fixture(scope="module")
def episodes(worlds) -> dict[tuple[str, str], EpisodeSpec]:
    return {(t, d): sample_episode(*worlds[t], d, 0, seed=SEED, stream=DIFFICULTIES.index(d)) for t, d in CASES}


def slot_at(town: Town, xy) -> ParkingSlot:
    found = [s for s in town.layout.slots if math.dist(s.position_world_m, xy[:2]) < 1e-3]
    assert len(found) == 1, f"no single slot at {xy}"
    return found[0]


def inside(p, region, margin: float = 0.0) -> bool:
    return region[0] + margin <= p[0] <= region[2] - margin and region[1] + margin <= p[1] <= region[3] - margin


# -- determinism ----------------------------------------------------------------------------------


def test_same_seed_same_episode_other_seed_other_episode(worlds, episodes):
    town, scene = worlds["grid-s7"]
    first = episodes[("grid-s7", "easy")]
    again = sample_episode(town, scene, "easy", 0, seed=SEED, stream=0)
    assert to_json(again) == to_json(first)
    other = sample_episode(town, scene, "easy", 0, seed=SEED + 1, stream=0)
    assert to_json(other) != to_json(first)
    assert other.seed != first.seed
    assert other.episode_id == first.episode_id == "grid-s7-easy-000-v1"


def test_generate_episodes_matches_sample_episode(worlds, episodes):
    town, scene = worlds["tee-s17"]
    generated = generate_episodes(town, scene, per_difficulty=1, seed=SEED)
    assert [e.difficulty for e in generated] == list(DIFFICULTIES)
    for ep in generated:
        assert to_json(ep) == to_json(episodes[("tee-s17", ep.difficulty)])


# -- what an episode holds ----------------------------------------------------------------------------


@pytest.mark.parametrize(("town_id", "difficulty"), CASES)
def test_episode_fields(worlds, episodes, town_id, difficulty):
    town, _ = worlds[town_id]
    ep = episodes[(town_id, difficulty)]
    x0, y0, x1, y1 = ep.region_world_m
    size = REGION_SIZE_M[difficulty]
    assert size == {"easy": 150.0, "mid": 300.0, "hard": 300.0}[difficulty]
    assert x1 - x0 == pytest.approx(size, abs=2e-3) and y1 - y0 == pytest.approx(size, abs=2e-3)
    bx0, by0, bx1, by1 = town.layout.bounds_world_m(pad_m=0.0)
    assert bx0 - 1e-3 <= x0 and by0 - 1e-3 <= y0 and x1 <= bx1 + 1e-3 and y1 <= by1 + 1e-3
    assert ep.asset_sha256 == town.sha256
    assert ep.town.town_id == town_id and (ep.town.generator, ep.town.seed) == TOWNS[town_id]
    assert ep.episode_id == f"{town_id}-{difficulty}-000-v1"
    assert ep.active_uav_waypoints == town.uav_grid.inside(ep.region_world_m)
    assert len(ep.active_uav_waypoints) >= 4
    assert ep.uav_start_waypoint in ep.active_uav_waypoints
    assert ep.target.model in BODY_TYPES and ep.target.colour in VIVID_COLOURS
    if difficulty != "hard":
        assert ep.distractors == []


@pytest.mark.parametrize("town_id", SOLVE_TOWNS)
def test_hard_has_two_or_three_lookalikes(episodes, town_id):
    ep = episodes[(town_id, "hard")]
    target = ep.target
    assert 2 <= len(ep.distractors) <= 3
    for k, d in enumerate(ep.distractors):
        near_colour = d.model == target.model and d.colour in NEAR_COLOURS[target.colour]
        other_type = d.model != target.model and d.colour == target.colour
        assert near_colour or other_type, f"distractor {d} is no look-alike of {target}"
        assert near_colour if k % 2 == 0 else other_type  # the kinds alternate, near colour first
    points = [target.position_world_m[:2]] + [d.position_world_m[:2] for d in ep.distractors]
    for i, p in enumerate(points):
        for q in points[i + 1:]:
            assert math.dist(p, q) >= MIN_LOOKALIKE_SPACING_M


@pytest.mark.parametrize(("town_id", "difficulty"), CASES)
def test_target_on_a_free_open_road_slot_inside_the_region(worlds, episodes, town_id, difficulty):
    town, _ = worlds[town_id]
    ep = episodes[(town_id, difficulty)]
    for vehicle in [ep.target, *ep.distractors]:
        slot = slot_at(town, vehicle.position_world_m)
        assert not slot.covered and not slot.plaza
        assert slot.lane_id in town.layout.network.lanes  # on a drivable road
        assert slot.slot_id not in town.layout.occupied_slots
        assert vehicle.yaw_rad == pytest.approx(slot.yaw_rad)
        assert inside(vehicle.position_world_m, ep.region_world_m, margin=10.0 - 1e-6)


@pytest.mark.parametrize(("town_id", "difficulty"), CASES)
def test_ugv_starts_on_a_cruise_anchor_away_from_the_target(worlds, episodes, town_id, difficulty):
    town, _ = worlds[town_id]
    ep = episodes[(town_id, difficulty)]
    start = town.roads.parse_anchor_id(ep.ugv_start_waypoint)
    assert town.roads.anchors[start] == "cruise"
    assert not town.roads.covered[start]
    xy = town.roads.positions_world_m[start]
    assert inside(xy, ep.region_world_m)
    assert math.dist(xy, ep.target.position_world_m[:2]) >= MIN_START_DISTANCE_M


# -- solvability by rendering ---------------------------------------------------------------------------


@pytest.mark.parametrize(("town_id", "difficulty"), CASES)
def test_sampled_episode_is_solvable(worlds, episodes, town_id, difficulty):
    town, scene = worlds[town_id]
    ep = episodes[(town_id, difficulty)]
    t = ep.target
    uid = scene.add_vehicle(t.model, t.colour, t.position_world_m, t.yaw_rad)
    others = [scene.add_vehicle(d.model, d.colour, d.position_world_m, d.yaw_rad) for d in ep.distractors]
    try:
        result = check(scene, town, uid, t.position_world_m, t.yaw_rad, ep.active_uav_waypoints)
        assert result.solvable
        assert result.verifying_anchors and result.uav_nodes
        for anchor in result.verifying_anchors:
            assert anchor in town.roads.anchors
            assert math.dist(town.roads.positions_world_m[anchor], t.position_world_m[:2]) <= 50.0
        start = town.roads.parse_anchor_id(ep.ugv_start_waypoint)
        assert reachable(town, start, result.verifying_anchors)
        for node_id in result.uav_nodes:
            assert node_id in ep.active_uav_waypoints
            node = town.uav_grid.nodes[node_id]
            shot = sensors.nadir(scene, node.position_world_m[:2], node.position_world_m[2], sensors.CameraConfig())
            assert sensors.target_pixels(shot, uid) >= UAV_VISIBLE_MIN_PX
    finally:
        for body in [uid, *others]:
            scene.remove(body)


def test_reachable_needs_goals_and_a_directed_path(worlds):
    town, _ = worlds["grid-s7"]
    roads = town.roads
    start = min(roads.anchors)
    assert not reachable(town, start, [])
    assert reachable(town, start, [start])
    dead = [n for n in roads.fine.nodes if roads.fine.out_degree(n) == 0]
    assert not dead  # grid-s7 is one strongly connected road network
    assert reachable(town, start, [max(roads.anchors)])


def test_deck_town_targets_are_never_covered(worlds):
    town, scene = worlds["deck-s19"]
    ep = sample_episode(town, scene, "easy", 0, seed=SEED)
    slot = slot_at(town, ep.target.position_world_m)
    assert not slot.covered and not slot.plaza
    assert not town.roads.covered[town.roads.parse_anchor_id(ep.ugv_start_waypoint)]


def test_a_target_under_a_deck_is_not_seen_from_the_air(worlds):
    town, scene = worlds["deck-s19"]
    roads = town.roads
    open_xy = roads.positions_world_m[~roads.covered]

    def clearance(slot: ParkingSlot) -> float:
        return float(np.min(np.hypot(*(open_xy - np.asarray(slot.position_world_m)).T)))

    free = [s for s in town.layout.slots if s.slot_id not in town.layout.occupied_slots and not s.plaza]
    covered = max((s for s in free if s.covered), key=clearance)  # well under the middle of a deck
    assert clearance(covered) > 20.0
    every_node = sorted(town.uav_grid.nodes)
    near = [n for n in every_node if math.dist(town.uav_grid.nodes[n].position_world_m[:2], covered.position_world_m) <= 50]
    assert near  # there are UAV nodes close enough to look
    uid = scene.add_vehicle("sedan", "red", (*covered.position_world_m, 0.0), covered.yaw_rad)
    try:
        hidden = check(scene, town, uid, (*covered.position_world_m, 0.0), covered.yaw_rad, every_node)
    finally:
        scene.remove(uid)
    assert hidden.uav_nodes == []
    # the same car on an open road is seen: the check above is not vacuous
    open_slot = max((s for s in free if not s.covered), key=lambda s: min(
        math.dist(s.position_world_m, c.position_world_m) for c in town.layout.slots if c.covered))
    uid = scene.add_vehicle("sedan", "red", (*open_slot.position_world_m, 0.0), open_slot.yaw_rad)
    try:
        seen = check(scene, town, uid, (*open_slot.position_world_m, 0.0), open_slot.yaw_rad, every_node)
    finally:
        scene.remove(uid)
    assert seen.uav_nodes



def test_a_car_just_inside_a_deck_end_is_hidden_from_an_oblique_uav_view():
    street = np.stack([np.linspace(0.0, 60.0, 61), np.zeros(61)], axis=1)
    centre = street + [0.0, -1.75]
    network = LaneNetwork({"a": Lane("a", centre, np.full(61, 3.5), covered=True)})
    layout = TownLayout("deck-end", "test", 0, network, decks=[Deck(strip(street, -9.5, 9.5), 6.5, 7.5)])
    with Scene(layout, look="flat") as scene:
        uid = scene.add_vehicle("sedan", "red", (6.0, -4.75, 0.0), 0.0)  # 6 m inside the deck's west end
        cam = sensors.CameraConfig()
        assert sensors.target_pixels(sensors.nadir(scene, (6.0, -4.75), 80.0, cam), uid) == 0  # straight above
        oblique = sensors.nadir(scene, (-41.754, -10.488), 80.0, cam)  # a UAV node 48 m away, off the deck end
        assert sensors.target_pixels(oblique, uid) == 0


# -- agos episodes sample / split ----------------------------------------------------------------------


def test_episodes_sample_command(tmp_path, worlds, episodes, agos):
    out = tmp_path / "eps.jsonl"
    cache = {"AGOS_ASSET_CACHE": str(tmp_path / "cache")}
    proc = agos("episodes", "sample", "--town", "grid-s7", "--difficulty", "easy", "-n", "2", "--look", "flat",
                "--out", out, env=cache, cwd=tmp_path)  # the look of the scenes here (a rich split: test_paper_splits)
    assert proc.returncode == 0, proc.stderr
    lines = out.read_text().splitlines()
    assert len(lines) == 2
    parsed = read_episodes(out)
    assert [e.episode_id for e in parsed] == ["grid-s7-easy-000-v1", "grid-s7-easy-001-v1"]
    assert all(e.difficulty == "easy" and e.asset_sha256 == worlds["grid-s7"][0].sha256 for e in parsed)
    # the command samples exactly what the library does for the same seed and stream
    assert lines[0] == to_json(episodes[("grid-s7", "easy")]).decode()
    check_proc = agos("episodes", "check", out, env=cache, cwd=tmp_path)
    assert check_proc.returncode == 0 and "2 valid episodes" in check_proc.stdout


@pytest.fixture(scope="module")
def split_dir(tmp_path_factory) -> Path:
    """``agos episodes split`` in this process, one worker (that worker counts change no file:
    test_paper_splits)."""
    from agos.deploy.cli import main

    out = tmp_path_factory.mktemp("split")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("AGOS_ASSET_CACHE", str(out / "cache"))
        patch.chdir(out)
        code = main(["episodes", "split", "--out", str(out / "d"), "--train", "6", "--val", "3", "--test", "3",
                     "--workers", "1", "--look", "flat"])
    assert code == 0
    return out / "d"


def read_split(split_dir: Path) -> dict[str, list[EpisodeSpec]]:
    return {s: read_episodes(split_dir / f"{s}.jsonl") for s in ("train", "val", "test")}


def test_split_counts_and_towns(split_dir):
    split = read_split(split_dir)
    assert {s: len(v) for s, v in split.items()} == {"train": 6, "val": 3, "test": 3}
    assert json.loads((split_dir / "manifest.json").read_text())["counts"] == {"train": 6, "val": 3, "test": 3}
    trainval = set(TOWNS) - set(TEST_TOWNS)
    assert len(trainval) == 5
    assert {e.town.town_id for e in split["test"]} == set(TEST_TOWNS)
    for s in ("train", "val"):
        assert {e.town.town_id for e in split[s]} <= trainval
    assert sorted(e.difficulty for e in split["test"]) == sorted(DIFFICULTIES)
    for s, eps in split.items():
        assert len({e.episode_id for e in eps}) == len(eps), f"duplicate episode id within {s}"


def test_split_train_and_val_episodes_differ(split_dir):
    split = read_split(split_dir)
    key = lambda e: (e.town.town_id, e.seed)  # noqa: E731
    assert not {key(e) for e in split["train"]} & {key(e) for e in split["val"]}
    assert not {to_json(msgspec.structs.replace(e, episode_id="")) for e in split["train"]} & \
        {to_json(msgspec.structs.replace(e, episode_id="")) for e in split["val"]}


def test_split_train_and_val_share_no_episode_id(split_dir):
    split = read_split(split_dir)
    assert not {e.episode_id for e in split["train"]} & {e.episode_id for e in split["val"]}


def test_split_test_episodes_match_in_process_sampling(split_dir, worlds):
    town, scene = worlds["parks-s23"]
    for ep in read_split(split_dir)["test"]:
        stream = SPLIT_STREAMS["test"] + DIFFICULTIES.index(ep.difficulty)
        expected = sample_episode(town, scene, ep.difficulty, 0, seed=SEED, stream=stream, split="test")
        assert to_json(ep) == to_json(expected)
        assert ep.episode_id == f"parks-s23-test-{ep.difficulty}-000-v1"
