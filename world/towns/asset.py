"""Frozen town assets: one canonical document per town, hashed, saved and served by hash.

The document holds every number an episode can depend on — lanes, fine graph, decision
anchors and edges, UAV grid, surfaces, buildings, trees, decks, parking slots and parked
vehicles — as integers (millimetres, micro-radians, colour per mille) and strings, packed with
msgpack in a fixed key order. Its sha256 is the asset hash: the same inputs give the same hash
on any machine. Every :class:`Town` in use, freshly generated or loaded, is rebuilt *from* that
document, so all workers run on bit-identical geometry.

On disk an asset is a directory with ``asset.msgpack`` and a human-readable ``manifest.json``.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import networkx as nx
import numpy as np

from agos.runtime.settings import local_dirs
from agos.world.towns.buildcache import entry_path, read_entry, write_entry
from agos.world.towns.dressing import DRESSING_VERSION, Dressing, Facade, Lamp, RoofUnit
from agos.world.towns.lanes import Lane, LaneNetwork
from agos.world.towns.layout import Deck, ParkedVehicle, TownLayout
from agos.world.towns.placement import Building, ParkingSlot, Tree
from agos.world.towns.roadgraph import RoadGraphs, _build_decision_graph, build_road_graphs
from agos.world.towns.streets import Surface
from agos.world.towns.uavgrid import UavGrid, UavNode, build_uav_grid

ASSET_FORMAT = 2
"""2: the rich look's dressing (façades, rooftop units, lamps, street trees, sun, texture seed and
the dressing version) is part of the document, so the hash covers the look."""


class AssetMismatch(ValueError):
    """An episode names a town hash that differs from the town found here."""


class AssetError(ValueError):
    """A missing, corrupt or tampered asset; the message names the path and the reason."""


@dataclass
class Town:
    layout: TownLayout
    roads: RoadGraphs
    uav_grid: UavGrid
    sha256: str
    document: bytes

    @property
    def town_id(self) -> str:
        return self.layout.town_id


# ----- encoding --------------------------------------------------------------------------------
def _mm(a: Any) -> list:
    return np.round(np.asarray(a, dtype=float) * 1000).astype(np.int64).ravel().tolist()


def _from_mm(v: list, cols: int = 2) -> np.ndarray:
    return (np.asarray(v, dtype=np.int64) / 1000.0).reshape(-1, cols) if cols else np.asarray(v, np.int64) / 1000.0


def town_document(layout: TownLayout, roads: RoadGraphs, grid: UavGrid) -> dict[str, Any]:
    lanes = [[lid, _mm(ln.centre_m), _mm(ln.width_m), sorted(ln.successors), int(ln.in_junction), ln.road_id,
              None if ln.parking_offset_m is None else round(ln.parking_offset_m * 1000), int(ln.covered),
              sorted(ln.lane_changes)]
             for lid, ln in sorted(layout.network.lanes.items())]
    return {
        "format": ASSET_FORMAT,
        "town_id": layout.town_id, "generator": layout.generator, "seed": layout.seed,
        "lanes": lanes,
        "warnings": list(layout.network.warnings),
        "surfaces": [[s.kind, s.shape, _mm(s.polygon_m)] for s in layout.surfaces],
        "buildings": [[*_mm(b.center_world_m), *_mm(b.size_m), *[round(c * 1000) for c in b.colour],
                       round(b.yaw_rad * 1e6)] for b in layout.buildings],
        "trees": [[*_mm(t.position_world_m), *_mm([t.height_m, t.crown_radius_m])] for t in layout.trees],
        "decks": [[_mm(d.polygon_m), *_mm([d.bottom_m, d.top_m])] for d in layout.decks],
        "slots": [[s.slot_id, *_mm(s.position_world_m), round(s.yaw_rad * 1e6), s.lane_id, int(s.covered), int(s.plaza)]
                  for s in layout.slots],
        "parked": [[p.slot_id, p.model, p.colour] for p in layout.parked],
        "fine_nodes": _mm(roads.positions_world_m),
        "fine_lane": roads.node_lane,
        "fine_edges": sorted([u, v] for u, v in roads.fine.edges()),
        "anchors": sorted([n, k] for n, k in roads.anchors.items()),
        "decision_edges": sorted(e.fine_nodes for e in roads.decision_edges.values()),
        "uav_nodes": sorted([n.node_id, n.i, n.j, *_mm(n.position_world_m)] for n in grid.nodes.values()),
        "uav_spacing_mm": round(grid.spacing_m * 1000), "uav_altitude_mm": round(grid.altitude_m * 1000),
        "dressing": _dressing_document(layout),
    }


def _dressing_document(layout: TownLayout) -> list | None:
    d = layout.dressing
    if d is None:
        return None
    if len(d.facades) != len(layout.buildings):
        raise ValueError(f"town {layout.town_id}: {len(d.facades)} façades for {len(layout.buildings)} buildings")
    return [d.version, d.texture_seed, round(d.sun_azimuth_rad * 1e6), round(d.sun_elevation_rad * 1e6),
            [[f.style, f.ground] for f in d.facades],
            [[u.building, *_mm(u.offset_m), *_mm(u.size_m)] for u in d.roof_units],
            [[*_mm(lamp.position_world_m), round(lamp.arm_yaw_rad * 1e6)] for lamp in d.lamps],
            [[*_mm(t.position_world_m), *_mm([t.height_m, t.crown_radius_m])] for t in d.street_trees]]


def _dressing_from_document(doc: list | None) -> Dressing | None:
    if doc is None:
        return None
    version, seed, azimuth, elevation, facades, units, lamps, trees = doc
    if version != DRESSING_VERSION:  # what the scene derives from the dressing would not be what was hashed
        raise AssetError(f"dressing version {version!r} is not {DRESSING_VERSION} (re-import or rebuild the town)")
    return Dressing(
        version, seed, azimuth / 1e6, elevation / 1e6, tuple(Facade(style, ground) for style, ground in facades),
        tuple(RoofUnit(u[0], (u[1] / 1000, u[2] / 1000), (u[3] / 1000, u[4] / 1000, u[5] / 1000)) for u in units),
        tuple(Lamp((lp[0] / 1000, lp[1] / 1000), lp[2] / 1e6) for lp in lamps),
        tuple(Tree((t[0] / 1000, t[1] / 1000), t[2] / 1000, t[3] / 1000) for t in trees))


def encode_document(doc: dict[str, Any]) -> bytes:
    return msgspec.msgpack.encode(doc)


def town_from_document(data: bytes) -> Town:
    doc = msgspec.msgpack.decode(data)
    if doc.get("format") != ASSET_FORMAT:
        raise AssetError(f"asset format {doc.get('format')!r} is not {ASSET_FORMAT}")
    lanes = {}
    for lid, centre, width, succ, in_j, road, park, cov, changes in doc["lanes"]:
        lanes[lid] = Lane(lid, _from_mm(centre), _from_mm(width, 0), list(succ), bool(in_j), road,
                          None if park is None else park / 1000.0, bool(cov), list(changes))
    network = LaneNetwork(lanes, list(doc["warnings"]))
    layout = TownLayout(
        doc["town_id"], doc["generator"], doc["seed"], network,
        surfaces=[Surface(kind, _from_mm(poly), shape) for kind, shape, poly in doc["surfaces"]],
        buildings=[Building((b[0] / 1000, b[1] / 1000), (b[2] / 1000, b[3] / 1000, b[4] / 1000),
                            (b[5] / 1000, b[6] / 1000, b[7] / 1000), b[8] / 1e6) for b in doc["buildings"]],
        trees=[Tree((t[0] / 1000, t[1] / 1000), t[2] / 1000, t[3] / 1000) for t in doc["trees"]],
        decks=[Deck(_from_mm(poly), lo / 1000, hi / 1000) for poly, lo, hi in doc["decks"]],
        slots=[ParkingSlot(s[0], (s[1] / 1000, s[2] / 1000), s[3] / 1e6, s[4], bool(s[5]), bool(s[6]))
               for s in doc["slots"]],
        parked=[ParkedVehicle(*p) for p in doc["parked"]],
        dressing=_dressing_from_document(doc["dressing"]))
    pos = _from_mm(doc["fine_nodes"])
    fine = nx.DiGraph()
    fine.add_nodes_from(range(len(pos)))
    for u, v in doc["fine_edges"]:
        fine.add_edge(u, v, length_m=float(np.linalg.norm(pos[v] - pos[u])))
    covered = np.array([lanes[lid].covered for lid in doc["fine_lane"]], dtype=bool)
    roads = RoadGraphs(pos, fine, {n: k for n, k in doc["anchors"]}, list(doc["fine_lane"]), covered)
    _build_decision_graph(roads)
    if sorted(e.fine_nodes for e in roads.decision_edges.values()) != doc["decision_edges"]:
        raise AssetError("decision edges do not follow from the stored fine graph and anchors")
    grid = UavGrid({n[0]: UavNode(n[0], n[1], n[2], (n[3] / 1000, n[4] / 1000, n[5] / 1000)) for n in doc["uav_nodes"]},
                   doc["uav_spacing_mm"] / 1000, doc["uav_altitude_mm"] / 1000)
    return Town(layout, roads, grid, hashlib.sha256(data).hexdigest(), data)


def freeze(layout: TownLayout) -> Town:
    """Build graphs and grid for a layout and return the town rebuilt from its canonical document."""
    roads = build_road_graphs(layout.network)
    _, anchor_xy = roads.anchor_array()
    grid = build_uav_grid(roads.positions_world_m, anchor_xy)
    return town_from_document(encode_document(town_document(layout, roads, grid)))


# ----- procedural towns, files and the local cache -----------------------------------------------
_INVALID = (ValueError, KeyError, TypeError, IndexError, RecursionError, nx.NetworkXException)
"""What parsing a document that is not a valid town raises."""


def generate_town(generator: str, seed: int) -> Town:
    """A procedural town built from its recipe, here and now (no cache)."""
    from agos.world.towns.procedural import build_layout

    return freeze(build_layout(generator, seed))


@functools.lru_cache(maxsize=8)
def build_town(generator: str, seed: int) -> Town:
    """:func:`generate_town`'s town, through the build cache (world/towns/buildcache.py): a document an
    earlier process froze from the same code is rebuilt into the town (what :func:`freeze` does with the
    document it encodes, so the town is the same), else the town is generated and its document stored."""
    entry = entry_path(cache_dir(), f"town-{generator}-s{seed}.msgpack")
    data = read_entry(entry)
    if data is not None:
        try:
            town = town_from_document(data)
        except _INVALID:
            town = None
        if town is not None and (town.layout.generator, town.layout.seed) == (generator, seed):
            return town
    town = generate_town(generator, seed)
    write_entry(entry, town.document)
    return town


def manifest(town: Town) -> dict[str, Any]:
    roads = town.roads
    return {"asset_id": town.town_id, "format": ASSET_FORMAT, "sha256": town.sha256, "generator": town.layout.generator,
            "seed": town.layout.seed, "lanes": len(town.layout.network.lanes), "fine_nodes": roads.fine.number_of_nodes(),
            "decision_nodes": roads.decision.number_of_nodes(), "uav_nodes": len(town.uav_grid.nodes),
            "warnings": len(town.layout.network.warnings)}


def save_town(town: Town, out_dir: Path) -> Path:
    """Write ``town`` into ``out_dir`` (``asset.msgpack``, ``manifest.json``). Each file appears whole or
    not at all (written beside, then renamed), the asset first: an interrupted save (Ctrl-C in ``agos
    map import``) leaves no cut file, and a manifest of an older asset is refused by its hash."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for name, data in (("asset.msgpack", town.document),
                       ("manifest.json", (json.dumps(manifest(town), indent=2) + "\n").encode())):
        part = out_dir / f".{name}.{os.getpid()}.part"  # workers caching the same town each write their own
        part.write_bytes(data)
        os.replace(part, out_dir / name)
    return out_dir


def load_town(path: Path, expected_sha256: str | None = None) -> Town:
    """Load an asset directory (or its ``asset.msgpack``); check its hash against the manifest
    and, if given, against ``expected_sha256``."""
    data_path = path / "asset.msgpack" if path.is_dir() else path
    try:
        data = data_path.read_bytes()
    except OSError as exc:
        raise AssetError(f"{data_path}: cannot read asset ({exc.strerror})") from None
    manifest_path = data_path.parent / "manifest.json"
    if manifest_path.exists():  # a damaged file is caught by its hash before anything parses it
        digest = hashlib.sha256(data).hexdigest()
        recorded = json.loads(manifest_path.read_text()).get("sha256")
        if recorded != digest:
            raise AssetError(f"{data_path}: content hash {digest[:12]} differs from manifest {str(recorded)[:12]}")
    try:
        town = town_from_document(data)
    except _INVALID as exc:
        raise AssetError(f"{data_path}: not a valid agos town asset ({type(exc).__name__}: {exc})") from None
    if expected_sha256 is not None and town.sha256 != expected_sha256:
        raise AssetMismatch(f"{data_path}: asset {town.town_id} has sha256 {town.sha256[:12]}..., "
                            f"the episode expects {expected_sha256[:12]}...")
    return town


def open_town(name: str | Path) -> Town:
    """A town by procedural id (``grid-s7``, ``curved-s99``) or by asset directory (imported map);
    an asset directory is also put in the local cache so workers on this host find it by hash."""
    path = Path(name)
    if (path / "asset.msgpack").exists() or path.suffix == ".msgpack":
        town = load_town(path)
        cache_town(town)
        return town
    from agos.world.towns.procedural import resolve

    return build_town(*resolve(str(name)))


def cache_dir() -> Path:
    return local_dirs().asset_cache


def cache_town(town: Town) -> None:
    """Put ``town`` in this host's asset cache (unless it is there), where workers and split files
    find it by its hash."""
    cached = cache_dir() / town.sha256
    if not (cached / "asset.msgpack").exists():
        save_town(town, cached)


def town_for(generator: str, seed: int, expected_sha256: str | None = None, *, town_id: str | None = None,
             fetch=None) -> Town:
    """The town an episode names: procedural towns are generated; imported ones come from the
    local cache (``AGOS_ASSET_CACHE``), else from ``fetch(sha256) -> bytes`` (zenoh), which is
    then cached. The result must match ``expected_sha256``."""
    if generator != "opendrive":
        town = build_town(generator, seed)
        if expected_sha256 is not None and town.sha256 != expected_sha256:
            raise AssetMismatch(
                f"town {town.town_id}: episode expects asset sha256 {expected_sha256[:12]}..., "
                f"this build gives {town.sha256[:12]}... (different agos version or generator)")
        return town
    if expected_sha256 is None:
        raise AssetError(f"town {town_id}: an imported town needs its asset sha256")
    cached = cache_dir() / expected_sha256
    if not (cached / "asset.msgpack").exists():
        if fetch is None:
            raise AssetError(f"town {town_id}: asset {expected_sha256[:12]} is not in {cache_dir()} and cannot be fetched")
        data = fetch(expected_sha256)
        if hashlib.sha256(data).hexdigest() != expected_sha256:
            raise AssetMismatch(f"town {town_id}: fetched asset does not hash to {expected_sha256[:12]}")
        try:
            save_town(town_from_document(data), cached)
        except _INVALID as exc:
            raise AssetError(f"town {town_id}: fetched asset is not valid ({type(exc).__name__}: {exc})") from None
    return _load_cached(str(cached), expected_sha256)


@functools.lru_cache(maxsize=8)
def _load_cached(path: str, sha: str) -> Town:
    return load_town(Path(path), sha)
