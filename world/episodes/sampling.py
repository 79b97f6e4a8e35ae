"""Episode sampling per difficulty (paper Table 1), solvability checks, and episode files.

easy: 150 m x 150 m region, no distractors; mid: 300 m x 300 m, none; hard: 300 m x 300 m with
2-3 look-alikes (the target's body type in a near colour, or its colour on another type).
Targets and look-alikes are parked on drivable roads (free parking slots inside the region, not
under decks, not on plazas). Every episode is checked solvable by rendering
(:mod:`agos.world.sim.evidence`); a region that fails is resampled.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path

import msgspec
import numpy as np

from agos.runtime.codec import field_path, to_json
from agos.runtime.schemas import Difficulty, EpisodeSpec, TownRef, VehicleSpec
from agos.world.towns.asset import Town
from agos.world.towns.catalog import BODY_TYPES, NEAR_COLOURS, VIVID_COLOURS
from agos.world.towns.placement import ParkingSlot

REGION_SIZE_M: dict[str, float] = {"easy": 150.0, "mid": 300.0, "hard": 300.0}
DIFFICULTIES: tuple[Difficulty, ...] = ("easy", "mid", "hard")
EPISODE_VERSION = 1
MIN_START_DISTANCE_M = 40.0
MIN_LOOKALIKE_SPACING_M = 30.0
DECISION_BUDGET = 80
MAX_ATTEMPTS = 40


class EpisodeFileError(ValueError):
    """A bad episode file; the message names the file, the line and the field."""


class Unsolvable(RuntimeError):
    """No solvable episode was found for a town and difficulty within the attempts allowed."""


def town_ref(town: Town) -> TownRef:
    return TownRef(generator=town.layout.generator, seed=town.layout.seed, town_id=town.town_id)


def generate_episodes(town: Town, scene, *, per_difficulty: int, seed: int,
                      difficulties: Iterable[Difficulty] = DIFFICULTIES) -> list[EpisodeSpec]:
    episodes = []
    for d_index, difficulty in enumerate(difficulties):
        for k in range(per_difficulty):
            episodes.append(sample_episode(town, scene, difficulty, k, seed=seed, stream=d_index))
    return episodes


def sample_episode(town: Town, scene, difficulty: Difficulty, index: int, *, seed: int, stream: int = 0,
                   split: str | None = None) -> EpisodeSpec:
    """The ``index``-th episode of a difficulty; deterministic in (town, difficulty, index, seed,
    stream). ``split`` (train, val, test) becomes part of the id, so ids are unique across splits."""
    for attempt in range(MAX_ATTEMPTS):
        ep_seed = int(np.random.SeedSequence([seed, stream, index, attempt]).generate_state(1)[0])
        spec = _candidate(town, difficulty, index, ep_seed, split)
        if spec is not None and _solvable(town, scene, spec):
            return spec
    raise Unsolvable(f"town {town.town_id}: no solvable {difficulty} episode in {MAX_ATTEMPTS} attempts")


def _candidate(town: Town, difficulty: Difficulty, index: int, seed: int, split: str | None) -> EpisodeSpec | None:
    rng = np.random.default_rng(seed)
    layout, roads = town.layout, town.roads
    size = REGION_SIZE_M[difficulty]
    bx0, by0, bx1, by1 = layout.bounds_world_m(pad_m=0.0)
    cx = rng.uniform(bx0 + size / 2, max(bx0 + size / 2, bx1 - size / 2))
    cy = rng.uniform(by0 + size / 2, max(by0 + size / 2, by1 - size / 2))
    region = (round(float(cx - size / 2), 3), round(float(cy - size / 2), 3),
              round(float(cx + size / 2), 3), round(float(cy + size / 2), 3))
    occupied = layout.occupied_slots
    inner = _shrink(region, 10.0)
    free = [s for s in layout.slots if s.slot_id not in occupied and not s.covered and not s.plaza
            and _inside(s.position_world_m, inner)]
    active = town.uav_grid.inside(region)
    if not free or len(active) < 4:
        return None
    order = rng.permutation(len(free))
    target_slot = free[int(order[0])]
    model = str(rng.choice(sorted(BODY_TYPES)))
    colour = str(rng.choice(VIVID_COLOURS))
    target = _vehicle(model, colour, target_slot)
    distractors: list[VehicleSpec] = []
    if difficulty == "hard":
        used = [target_slot.position_world_m]
        for k in range(int(rng.integers(2, 4))):
            if k % 2 == 0:
                look = (model, str(rng.choice(NEAR_COLOURS[colour])))
            else:
                look = (str(rng.choice([m for m in sorted(BODY_TYPES) if m != model])), colour)
            slot = next((free[int(i)] for i in order[1:]
                         if all(math.dist(free[int(i)].position_world_m, u) >= MIN_LOOKALIKE_SPACING_M for u in used)),
                        None)
            if slot is None:
                return None
            used.append(slot.position_world_m)
            distractors.append(_vehicle(*look, slot))
    ids, xy = roads.anchor_array()
    starts = [int(n) for n, p in zip(ids, xy, strict=True)
              if _inside((p[0], p[1]), region) and roads.anchors[int(n)] == "cruise" and not roads.covered[int(n)]
              and math.dist(p, target_slot.position_world_m) >= MIN_START_DISTANCE_M]
    if not starts:
        return None
    return EpisodeSpec(
        episode_id=f"{layout.town_id}-{split + '-' if split else ''}{difficulty}-{index:03d}-v{EPISODE_VERSION}",
        town=town_ref(town),
        asset_sha256=town.sha256, difficulty=difficulty, region_world_m=region, target=target,
        distractors=distractors, uav_start_waypoint=str(rng.choice(active)),
        ugv_start_waypoint=roads.anchor_id(int(rng.choice(starts))), active_uav_waypoints=active,
        decision_budget=DECISION_BUDGET, seed=seed)


def _solvable(town: Town, scene, spec: EpisodeSpec) -> bool:
    from agos.world.episodes.solvability import check, reachable

    uid = scene.add_vehicle(spec.target.model, spec.target.colour, spec.target.position_world_m, spec.target.yaw_rad)
    others = [scene.add_vehicle(d.model, d.colour, d.position_world_m, d.yaw_rad) for d in spec.distractors]
    try:
        start = town.roads.parse_anchor_id(spec.ugv_start_waypoint)
        result = check(scene, town, uid, spec.target.position_world_m, spec.target.yaw_rad, spec.active_uav_waypoints,
                       ugv_start=start, uav_start=spec.uav_start_waypoint)
        return result.solvable and reachable(town, start, result.verifying_anchors)
    finally:
        for body in [uid, *others]:
            scene.remove(body)


def _vehicle(model: str, colour: str, slot: ParkingSlot) -> VehicleSpec:
    x, y = slot.position_world_m
    return VehicleSpec(model=model, colour=colour, position_world_m=(x, y, 0.0), yaw_rad=slot.yaw_rad)


def _shrink(region: tuple[float, float, float, float], m: float) -> tuple[float, float, float, float]:
    return (region[0] + m, region[1] + m, region[2] - m, region[3] - m)


def _inside(p: tuple[float, float], region: tuple[float, float, float, float]) -> bool:
    return region[0] <= p[0] <= region[2] and region[1] <= p[1] <= region[3]


def write_episodes(path: Path, episodes: Iterable[EpisodeSpec]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w") as fh:
        for ep in episodes:
            fh.write(to_json(ep).decode() + "\n")


_SPEC_LINE = msgspec.json.Decoder(EpisodeSpec)


def read_episodes(path: Path) -> list[EpisodeSpec]:
    """Read a JSONL episode file; errors name the file, the line and the field."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise EpisodeFileError(f"{path}: cannot read episode file ({exc.strerror})") from exc
    episodes = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        try:
            episodes.append(_SPEC_LINE.decode(line))
        except msgspec.ValidationError as exc:
            field, message = field_path(exc)
            raise EpisodeFileError(f"{path}:{lineno}: field '{field}': {message}") from exc
        except msgspec.DecodeError as exc:
            raise EpisodeFileError(f"{path}:{lineno}: not valid JSON ({exc})") from exc
    if not episodes:
        raise EpisodeFileError(f"{path}: no episodes in file")
    return episodes
