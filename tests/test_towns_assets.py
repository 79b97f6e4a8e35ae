"""Procedural towns, frozen town assets (hash, save/load, cache, fetch), the OpenDRIVE import
through ``agos map``, and the top-down map."""

from __future__ import annotations

import json
import re
from collections import Counter
from pathlib import Path

import msgpack
import networkx as nx
import numpy as np
import pytest

from agos.world.towns import asset
from agos.world.towns.asset import AssetError, AssetMismatch, build_town, generate_town, load_town, open_town, save_town, town_for
from agos.world.towns.procedural import RECIPES, TEST_TOWNS, TOWNS, resolve
from agos.world.towns.topdown import COLOURS_BGR, region_map

MAPS = Path(__file__).resolve().parents[2] / "shared" / "maps"
TOWN01 = MAPS / "carla" / "Town01.xodr"
ZERO_WIDTH = MAPS / "opendrive-samples" / "zero_width.xodr"


def town(town_id: str) -> asset.Town:
    return build_town(*TOWNS[town_id])


def plan(town_id: str):
    generator, seed = TOWNS[town_id]
    return RECIPES[generator].plan(np.random.default_rng(seed))


# -- the six towns --------------------------------------------------------------------------------


@pytest.mark.parametrize("town_id", sorted(TOWNS))
def test_every_town_builds_with_sane_graphs(town_id):
    t = town(town_id)
    roads = t.roads
    assert t.town_id == town_id
    n = roads.fine.number_of_nodes()
    assert n > 1000
    largest = max(nx.strongly_connected_components(roads.fine), key=len)
    assert len(largest) / n >= 0.95
    fine = [d["length_m"] for _, _, d in roads.fine.edges(data=True)]
    decision = [e.length_m for e in roads.decision_edges.values()]
    assert 1.5 <= float(np.median(fine)) <= 2.5
    assert 7.0 <= float(np.median(decision)) <= 13.0
    assert max(fine) < 15.0  # lane changes are the longest fine edges
    assert {"cruise", "junction_entry", "junction_exit"} <= set(roads.anchors.values())
    assert len(t.uav_grid.nodes) > 50
    assert t.layout.slots and t.layout.buildings
    assert len(roads.node_lane) == n and roads.covered.shape == (n,)


def test_tee_town_has_t_junctions_and_dead_ends():
    p = plan("tee-s17")
    degree = Counter(p.degree())
    assert degree[3] >= 10  # T-junctions
    assert degree[1] >= 1  # dead-end spurs
    assert max(p.degree()) == 3  # staggered: no four-way crossings
    kinds = Counter(town("tee-s17").roads.anchors.values())
    assert kinds["dead_end"] == degree[1]


def test_deck_town_has_decks_over_covered_lanes():
    t = town("deck-s19")
    assert t.layout.decks
    assert any(s.covered for s in plan("deck-s19").streets)
    covered_lanes = {lid for lid, ln in t.layout.network.lanes.items() if ln.covered}
    assert covered_lanes
    roads = t.roads
    on_covered = np.array([lid in covered_lanes for lid in roads.node_lane])
    assert on_covered.any()
    np.testing.assert_array_equal(roads.covered, on_covered)
    assert any(s.covered for s in t.layout.slots)
    for slot in t.layout.slots:
        assert slot.covered == (slot.lane_id in covered_lanes)
    for deck in t.layout.decks:
        assert deck.bottom_m > 4.0 and deck.top_m > deck.bottom_m


def test_parks_town_has_parks_plazas_and_plaza_slots():
    t = town("parks-s23")
    kinds = Counter(s.kind for s in t.layout.surfaces)
    assert kinds["park"] >= 1 and kinds["plaza"] >= 1
    plaza_slots = [s for s in t.layout.slots if s.plaza]
    assert plaza_slots
    for s in plaza_slots:
        assert s.lane_id == "" and not s.covered
    assert t.layout.trees  # parks are planted
    assert len({s.slot_id for s in t.layout.slots}) == len(t.layout.slots)


def test_test_town_is_held_out():
    trainval = [t for t in TOWNS if t not in TEST_TOWNS]
    assert len(trainval) == 5
    assert set(TEST_TOWNS) <= set(TOWNS)
    assert not set(TEST_TOWNS) & set(trainval)
    for t in TEST_TOWNS:
        assert RECIPES[TOWNS[t][0]].split == "test"
    for t in trainval:
        assert RECIPES[TOWNS[t][0]].split == "trainval"


def test_resolve_town_ids():
    assert resolve("grid-s7") == ("grid", 7)
    assert resolve("curved-s99") == ("curved", 99)
    with pytest.raises(ValueError, match="grid-s7"):
        resolve("nowhere-s1")


# -- asset hashes -----------------------------------------------------------------------------------


def test_same_town_same_hash_other_seed_other_hash():
    a = generate_town("grid", 7)  # built twice, not read from a cache
    b = generate_town("grid", 7)
    assert a is not b
    assert a.sha256 == b.sha256 == build_town("grid", 7).sha256
    assert a.document == b.document
    assert len(a.sha256) == 64
    assert generate_town("grid", 8).sha256 != a.sha256


def test_save_load_round_trip(tmp_path):
    t = town("grid-s7")
    save_town(t, tmp_path / "grid")
    manifest = json.loads((tmp_path / "grid" / "manifest.json").read_text())
    assert manifest["sha256"] == t.sha256 and manifest["asset_id"] == "grid-s7"
    loaded = load_town(tmp_path / "grid", t.sha256)
    assert loaded.sha256 == t.sha256
    assert loaded.roads.fine.number_of_nodes() == t.roads.fine.number_of_nodes() == manifest["fine_nodes"]
    assert loaded.roads.fine.number_of_edges() == t.roads.fine.number_of_edges()
    assert loaded.roads.decision.number_of_nodes() == manifest["decision_nodes"]
    assert loaded.roads.anchors == t.roads.anchors
    assert len(loaded.uav_grid.nodes) == len(t.uav_grid.nodes) == manifest["uav_nodes"]
    assert len(loaded.layout.network.lanes) == manifest["lanes"]
    assert len(loaded.layout.slots) == len(t.layout.slots)
    assert len(loaded.layout.buildings) == len(t.layout.buildings)
    np.testing.assert_array_equal(loaded.roads.positions_world_m, t.roads.positions_world_m)
    # the asset file alone loads too
    assert load_town(tmp_path / "grid" / "asset.msgpack").sha256 == t.sha256


@pytest.fixture()
def saved(tmp_path) -> Path:
    return save_town(town("grid-s7"), tmp_path / "grid")


@pytest.mark.parametrize("where", [0, 1000, 400_000])
def test_flipped_byte_raises_asset_error_naming_the_path(saved, where):
    data_path = saved / "asset.msgpack"
    data = bytearray(data_path.read_bytes())
    data[where] ^= 0xFF
    data_path.write_bytes(bytes(data))
    with pytest.raises(AssetError, match=re.escape(str(data_path))):
        load_town(saved)



def test_tampered_fine_edge_raises_asset_error(saved):
    data_path = saved / "asset.msgpack"
    doc = msgpack.unpackb(data_path.read_bytes(), raw=False, strict_map_key=False)
    doc["fine_edges"][0][1] = len(doc["fine_lane"]) + 1000  # an edge to a node that does not exist
    data_path.write_bytes(msgpack.packb(doc, use_bin_type=True))
    with pytest.raises(AssetError, match=re.escape(str(data_path))):
        load_town(saved)


def test_manifest_hash_mismatch_raises_asset_error(saved):
    manifest_path = saved / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    manifest["sha256"] = "0" * 64
    manifest_path.write_text(json.dumps(manifest))
    with pytest.raises(AssetError, match=re.escape(str(saved / "asset.msgpack"))) as info:
        load_town(saved)
    assert "manifest" in str(info.value)


def test_missing_asset_raises_asset_error(tmp_path):
    with pytest.raises(AssetError, match=re.escape(str(tmp_path / "none" / "asset.msgpack"))):
        load_town(tmp_path / "none" / "asset.msgpack")
    (tmp_path / "junk.msgpack").write_bytes(b"\x00not msgpack at all")
    with pytest.raises(AssetError, match="not a valid agos town asset"):
        load_town(tmp_path / "junk.msgpack")


def test_wrong_expected_hash_raises_asset_mismatch(saved):
    with pytest.raises(AssetMismatch, match="expects"):
        load_town(saved, "f" * 64)
    with pytest.raises(AssetMismatch):
        town_for("grid", 7, "f" * 64)
    assert town_for("grid", 7, town("grid-s7").sha256) is town("grid-s7")


def test_unknown_procedural_town_names_the_known_ones():
    with pytest.raises(ValueError) as info:
        town_for("nowhere", 3)
    for generator in ("grid", "irregular", "curved", "tee", "deck", "parks"):
        assert generator in str(info.value)
    with pytest.raises(ValueError) as info:
        open_town("nowhere-town")
    for town_id in TOWNS:
        assert town_id in str(info.value)


def test_open_town_of_an_asset_directory_fills_the_cache(saved, tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv("AGOS_ASSET_CACHE", str(cache))
    assert asset.cache_dir() == cache
    t = open_town(saved)
    cached = cache / t.sha256 / "asset.msgpack"
    assert cached.read_bytes() == (saved / "asset.msgpack").read_bytes()
    assert json.loads((cache / t.sha256 / "manifest.json").read_text())["sha256"] == t.sha256
    assert open_town(str(saved)).sha256 == t.sha256


def test_imported_town_is_fetched_once_then_served_from_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("AGOS_ASSET_CACHE", str(tmp_path / "cache"))
    source = build_town("grid", 9)  # any document will do as the bytes behind a hash
    calls: list[str] = []

    def fetch(sha: str) -> bytes:
        calls.append(sha)
        return source.document

    t = town_for("opendrive", 0, source.sha256, town_id="Somewhere", fetch=fetch)
    assert calls == [source.sha256]
    assert t.sha256 == source.sha256
    assert (tmp_path / "cache" / source.sha256 / "asset.msgpack").read_bytes() == source.document

    def no_fetch(sha: str) -> bytes:
        raise AssertionError("fetched although cached")

    assert town_for("opendrive", 0, source.sha256, town_id="Somewhere", fetch=no_fetch).sha256 == source.sha256


def test_imported_town_rejects_fetched_bytes_with_the_wrong_hash(tmp_path, monkeypatch):
    monkeypatch.setenv("AGOS_ASSET_CACHE", str(tmp_path / "cache"))
    expected = town("grid-s7").sha256
    with pytest.raises(AssetMismatch, match="does not hash"):
        town_for("opendrive", 0, expected, town_id="Elsewhere", fetch=lambda sha: build_town("grid", 9).document)
    assert not (tmp_path / "cache" / expected).exists()
    with pytest.raises(AssetError, match="cannot be fetched"):
        town_for("opendrive", 0, expected, town_id="Elsewhere")
    with pytest.raises(AssetError, match="needs its asset sha256"):
        town_for("opendrive", 0, None, town_id="Elsewhere")


# -- OpenDRIVE import through the CLI (in this process: the agos fixture) --------------------------------


@pytest.fixture
def agos_cached(agos, tmp_path):
    """``agos`` with a private asset cache under ``tmp_path``, run from ``tmp_path``."""
    return lambda *args: agos(*args, env={"AGOS_ASSET_CACHE": str(tmp_path / "cache")}, cwd=tmp_path)


@pytest.mark.skipif(not TOWN01.exists(), reason=f"{TOWN01} not present")
def test_map_import_is_deterministic_and_info_reports_the_graphs(tmp_path, agos_cached):
    outs = []
    for k in range(2):
        out = tmp_path / f"town01-{k}"
        proc = agos_cached("map", "import", TOWN01, "--out", out)
        assert proc.returncode == 0, proc.stderr
        outs.append(out)
    shas = [json.loads((o / "manifest.json").read_text())["sha256"] for o in outs]
    assert shas[0] == shas[1]
    assert (outs[0] / "asset.msgpack").read_bytes() == (outs[1] / "asset.msgpack").read_bytes()
    # the import put it in this host's cache, where a split naming the town by hash finds it
    assert (tmp_path / "cache" / shas[0] / "asset.msgpack").read_bytes() == (outs[0] / "asset.msgpack").read_bytes()
    proc = agos_cached("map", "info", outs[0], "--json")
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    for key in ("fine_nodes", "fine_edges", "decision_nodes", "decision_edges", "uav_nodes", "median_fine_edge_m",
                "median_decision_edge_m", "largest_scc_fraction", "sha256"):
        assert key in info, key
    assert info["sha256"] == shas[0]
    assert 1.5 <= info["median_fine_edge_m"] <= 2.5
    assert 7.0 <= info["median_decision_edge_m"] <= 13.0
    assert info["largest_scc_fraction"] > 0.9
    assert info["fine_nodes"] > 1000 and info["decision_nodes"] > 100 and info["uav_nodes"] > 20
    assert info["fine_edges"] >= info["fine_nodes"] * 0.9


@pytest.mark.skipif(not ZERO_WIDTH.exists(), reason=f"{ZERO_WIDTH} not present")
def test_map_import_of_an_odd_file_warns_and_succeeds(tmp_path, agos_cached):
    proc = agos_cached("map", "import", ZERO_WIDTH, "--out", tmp_path / "zw")
    assert proc.returncode == 0, proc.stderr
    warnings = [line for line in proc.stderr.splitlines() if line.startswith("warning:")]
    assert warnings
    assert all("zero_width.xodr" in w or "more" in w for w in warnings)
    assert (tmp_path / "zw" / "asset.msgpack").exists()
    assert json.loads((tmp_path / "zw" / "manifest.json").read_text())["warnings"] >= len(warnings)


def test_map_import_of_a_non_xml_file_fails_with_one_line(tmp_path, agos_cached):
    bad = tmp_path / "notes.xodr"
    bad.write_text("this is not xml\n")
    proc = agos_cached("map", "import", bad, "--out", tmp_path / "out")
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "notes.xodr" in lines[0]
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "out" / "asset.msgpack").exists()


# -- top-down map ---------------------------------------------------------------------------------------


def test_region_map_has_the_requested_size_and_shows_roads():
    t = town("grid-s7")
    x, y = t.roads.positions_world_m[t.roads.fine.number_of_nodes() // 2]
    region = (x - 75.0, y - 75.0, x + 75.0, y + 75.0)
    image, metres_per_px = region_map(t.layout, region, size_px=300, ugv_xy=(x, y), uav_xy=(x + 20, y + 20))
    assert image.shape == (300, 300, 3) and image.dtype == np.uint8
    assert metres_per_px == pytest.approx(0.5)
    road_rgb = np.array(COLOURS_BGR["road"][::-1])
    road_px = int(np.all(image == road_rgb, axis=-1).sum())
    assert road_px > 0.02 * 300 * 300
    magenta = np.all(image == (200, 40, 200), axis=-1).sum()
    assert magenta > 0  # the UGV marker
    default, _ = region_map(t.layout, region)
    assert default.shape == (384, 384, 3)
    far, _ = region_map(t.layout, (5000.0, 5000.0, 5150.0, 5150.0), size_px=64)
    assert not np.all(far == road_rgb, axis=-1).any()


def test_eval_refuses_a_split_whose_towns_cannot_be_had_before_starting_anything(tmp_path, sample_mid_episodes,
                                                                                  agos_cached) -> None:
    """An unknown generator, a build that hashes otherwise, an imported town not in the cache: one line
    naming the file and the episode, exit 2, no run directory made."""
    lines = sample_mid_episodes(1, 3).read_text().splitlines()
    spec = json.loads(lines[0])
    cases = {
        "generator.jsonl": ({**spec, "town": {**spec["town"], "generator": "nosuchgen"}}, "unknown town generator"),
        "hash.jsonl": ({**spec, "asset_sha256": "ff" * 32}, "episode expects asset sha256 ffffffffffff"),
        "imported.jsonl": ({**spec, "town": {**spec["town"], "generator": "opendrive"}, "asset_sha256": "ee" * 32},
                           "agos map import"),
    }
    for name, (bad, says) in cases.items():
        (tmp_path / name).write_text(json.dumps(bad) + "\n")
        out = agos_cached("eval", "--split", name, "--runs-dir", "runs")  # in this process: nothing may start
        assert out.returncode == 2, out.stdout + out.stderr
        assert out.stderr.startswith(f"eval error: {name}:1: episode {spec['episode_id']}: ") and says in out.stderr
        assert len(out.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "runs").exists()
