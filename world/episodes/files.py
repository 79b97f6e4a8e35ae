"""Episode files: JSONL, one :class:`EpisodeSpec` a line (a contract: docs/ARCHITECTURE.md §8), read
and checked as a whole before anything runs them.

:func:`read_episodes` reads a file and checks what the file alone can tell: each line is an episode
(its fields and their types), with an id that is a key name (runtime/keys.py), a 64-hex asset hash,
non-negative seeds, a region with an area that holds its target, a decision budget of at least 1,
body types and paints the catalog has, at least one active UAV node; and no episode id appears twice
(a duplicate made a run replay one episode forever). :func:`read_split` adds what needs this agos's
towns: every episode's town builds (or is in the local asset cache) with the episode's asset hash and
town id, its start waypoints and active UAV nodes exist there, and, given the run's look, that look
draws every vehicle (the flat look has no bus and no attributes).

An episode file carries no run configuration (runtime/episode_config.py: speeds, cameras, link,
timing, look are the run's, one for every episode); the per-episode values are the spec's own (seed,
decision budget, which a configured budget replaces), so there is no mixture of configurations to
refuse beyond the look the vehicles need.

Every refusal is an :class:`EpisodeFileError` of one line naming the file, the line and the field;
the ``agos`` CLI prints it and exits 2 before any process starts.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path

import msgspec

from agos.runtime import keys
from agos.runtime.codec import field_path, to_json
from agos.runtime.schemas import EpisodeSpec, VehicleSpec
from agos.runtime.textfiles import one_line
from agos.world.towns.asset import AssetError, Town, town_for
from agos.world.towns.catalog import COLOURS
from agos.world.towns.look.vehicles import RICH_BODY_TYPES
from agos.world.towns.procedural import RECIPES
from agos.world.towns.roadgraph import RoadGraphs

IMPORTED = "opendrive"
"""The generator name of an imported town (found by its asset hash in the local cache)."""
_SHA256 = re.compile(r"[0-9a-f]{64}")


class EpisodeFileError(ValueError):
    """A bad episode file; the message (one line) names the file, the line and the field."""


def write_episodes(path: Path, episodes: Iterable[EpisodeSpec]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as fh:
        for ep in episodes:
            fh.write(to_json(ep).decode() + "\n")


_SPEC_LINE = msgspec.json.Decoder(EpisodeSpec)


def read_episodes(path: Path) -> list[EpisodeSpec]:
    """The episodes of a JSONL file, each line checked alone and the file as a whole (no id twice);
    :class:`EpisodeFileError` otherwise."""
    return [spec for _, spec in _read(path)]


def read_split(path: Path, *, look: str | None = None) -> list[EpisodeSpec]:
    """:func:`read_episodes`, then every episode against the town it names as this agos builds it, and
    against ``look`` (the run's) when given. Builds each distinct town once (~0.4 s; cached)."""
    from agos.world.sim.episode_vehicles import LookMismatch, check_look  # the scene module: only here

    numbered = _read(path)
    towns: dict[tuple[str, int, str, str], Town] = {}
    for lineno, spec in numbered:
        where = f"{path}:{lineno}: episode {spec.episode_id}"
        ref = (spec.town.generator, spec.town.seed, spec.town.town_id, spec.asset_sha256)
        if ref not in towns:
            towns[ref] = _town(spec, where)
        problem = _in_town(spec, towns[ref])
        if problem is None and look is not None:
            try:
                check_look(spec, look)
            except LookMismatch as exc:
                problem = str(exc).removeprefix(f"episode {spec.episode_id}: ")
        if problem is not None:
            raise EpisodeFileError(one_line(f"{where}: {problem}"))
    return [spec for _, spec in numbered]


def _read(path: Path) -> list[tuple[int, EpisodeSpec]]:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise EpisodeFileError(one_line(f"{path}: cannot read episode file ({exc.strerror})")) from None
    episodes: list[tuple[int, EpisodeSpec]] = []
    first_line: dict[str, int] = {}
    for lineno, line in enumerate(data.split(b"\n"), start=1):  # "\n" alone: as editors number lines
        if not line.strip():
            continue
        try:
            spec = _SPEC_LINE.decode(line)
        except msgspec.ValidationError as exc:
            field, message = field_path(exc)
            raise EpisodeFileError(one_line(f"{path}:{lineno}: field '{field}': {message}")) from None
        except msgspec.DecodeError as exc:
            raise EpisodeFileError(one_line(f"{path}:{lineno}: not valid JSON ({exc})")) from None
        except UnicodeDecodeError as exc:  # msgspec's, for a name that is not UTF-8
            raise EpisodeFileError(f"{path}:{lineno}: not UTF-8 text (byte {exc.start})") from None
        except RecursionError:
            raise EpisodeFileError(f"{path}:{lineno}: not an episode: nested too deeply") from None
        problem = _problem(spec)
        if problem is not None:
            raise EpisodeFileError(one_line(f"{path}:{lineno}: {problem}"))
        if spec.episode_id in first_line:
            raise EpisodeFileError(one_line(f"{path}:{lineno}: episode id {spec.episode_id} again (first at line "
                                            f"{first_line[spec.episode_id]}): every episode of a file needs its own id"))
        first_line[spec.episode_id] = lineno
        episodes.append((lineno, spec))
    if not episodes:
        raise EpisodeFileError(f"{path}: no episodes in file")
    return episodes


def _problem(spec: EpisodeSpec) -> str | None:
    """What is wrong with one episode on its own (field and reason), or None."""
    try:
        keys.check_chunk(spec.episode_id, what="episode id")
    except ValueError as exc:
        return f"field 'episode_id': {exc}"
    if not _SHA256.fullmatch(spec.asset_sha256):
        return f"field 'asset_sha256': {spec.asset_sha256!r} is not a sha256 (64 lowercase hex digits)"
    for field, seed in (("seed", spec.seed), ("town.seed", spec.town.seed)):
        if seed < 0:
            return f"field '{field}': {seed} is negative"
    x0, y0, x1, y1 = spec.region_world_m
    if not (x0 < x1 and y0 < y1):
        return f"field 'region_world_m': {list(spec.region_world_m)} is not [x0, y0, x1, y1] with x0 < x1 and y0 < y1"
    tx, ty = spec.target.position_world_m[0], spec.target.position_world_m[1]
    if not (x0 <= tx <= x1 and y0 <= ty <= y1):
        return f"field 'target.position_world_m': ({tx:g}, {ty:g}) lies outside the region {list(spec.region_world_m)}"
    if spec.decision_budget < 1:
        return f"field 'decision_budget': {spec.decision_budget}: give at least 1"
    if not spec.active_uav_waypoints:
        return "field 'active_uav_waypoints': empty: the UAV needs at least one node to search"
    for name, vehicle in (("target", spec.target), *((f"distractors.{i}", v) for i, v in enumerate(spec.distractors))):
        problem = _vehicle_problem(vehicle)
        if problem is not None:
            return f"field '{name}.{problem}"
    return None


def _vehicle_problem(vehicle: VehicleSpec) -> str | None:
    """``field': reason`` for a vehicle no look can draw, or None."""
    if vehicle.model not in RICH_BODY_TYPES:
        return f"model': {vehicle.model!r} is not a body type ({', '.join(RICH_BODY_TYPES)})"
    for field, paint in (("colour", vehicle.colour), ("roof", vehicle.roof), ("stripe", vehicle.stripe)):
        if paint is not None and paint not in COLOURS:
            return f"{field}': {paint!r} is not a paint ({', '.join(COLOURS)})"
    return None


def _town(spec: EpisodeSpec, where: str) -> Town:
    """The town ``spec`` names, as this agos has it; :class:`EpisodeFileError` if it cannot be had or
    hashes otherwise. Names are checked before anything is built, so a wrong one costs no build."""
    ref = spec.town
    if ref.generator != IMPORTED:
        if ref.generator not in RECIPES:
            raise EpisodeFileError(one_line(f"{where}: field 'town.generator': unknown town generator {ref.generator!r} "
                                            f"(known: {', '.join(RECIPES)}, or {IMPORTED} for an imported map)"))
        if ref.town_id != f"{ref.generator}-s{ref.seed}":
            raise EpisodeFileError(one_line(f"{where}: field 'town.town_id': {ref.town_id!r}, but generator "
                                            f"{ref.generator} with seed {ref.seed} builds {ref.generator}-s{ref.seed}"))
    try:
        town = town_for(ref.generator, ref.seed, spec.asset_sha256, town_id=ref.town_id)
    except AssetError as exc:
        raise EpisodeFileError(one_line(f"{where}: {exc}; import the map on this host first (agos map import "
                                        "FILE.xodr --out DIR)")) from None
    except ValueError as exc:  # a build that hashes otherwise
        raise EpisodeFileError(one_line(f"{where}: {exc}")) from None
    if town.town_id != ref.town_id:
        raise EpisodeFileError(one_line(f"{where}: field 'town.town_id': {ref.town_id!r}, but asset "
                                        f"{spec.asset_sha256[:12]} is town {town.town_id}"))
    return town


def _in_town(spec: EpisodeSpec, town: Town) -> str | None:
    """Which waypoint of ``spec`` its town does not have, or None."""
    nodes = town.uav_grid.nodes
    if spec.uav_start_waypoint not in nodes:
        return f"field 'uav_start_waypoint': {spec.uav_start_waypoint!r} is not a UAV node of {town.town_id}"
    missing = [n for n in spec.active_uav_waypoints if n not in nodes]
    if missing:
        return f"field 'active_uav_waypoints': {missing[0]!r} is not a UAV node of {town.town_id}"
    try:
        anchor = RoadGraphs.parse_anchor_id(spec.ugv_start_waypoint)
    except ValueError as exc:
        return f"field 'ugv_start_waypoint': {exc}"
    if anchor not in town.roads.anchors:
        return f"field 'ugv_start_waypoint': {spec.ugv_start_waypoint!r} is not a road waypoint of {town.town_id}"
    return None
