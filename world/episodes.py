"""Episode sampling per difficulty (paper Table 1) and episode files.

easy: 150 m x 150 m region, no distractors; mid: 300 m x 300 m, none; hard: 300 m x 300 m
with 2-3 look-alikes (the target's body type in a near colour, or its colour on another type).
Targets and look-alikes are parked on roads, in free parking slots inside the region.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from agos.runtime.schemas import Difficulty, EpisodeSpec, TownRef, VehicleSpec
from agos.world.asset import Town
from agos.world.catalog import BODY_TYPES, NEAR_COLOURS, VIVID_COLOURS

REGION_SIZE_M: dict[str, float] = {"easy": 150.0, "mid": 300.0, "hard": 300.0}
DIFFICULTIES: tuple[Difficulty, ...] = ("easy", "mid", "hard")
EPISODE_VERSION = 1
MIN_START_DISTANCE_M = 40.0
MIN_LOOKALIKE_SPACING_M = 30.0
DECISION_BUDGET = 80


class EpisodeFileError(ValueError):
    """A bad episode file; the message names the file, the line and the field."""


def generate_episodes(town: Town, *, per_difficulty: int, seed: int,
                      difficulties: Iterable[Difficulty] = DIFFICULTIES) -> list[EpisodeSpec]:
    episodes = []
    for d_index, difficulty in enumerate(difficulties):
        for k in range(per_difficulty):
            ep_seed = int(np.random.SeedSequence([seed, d_index, k]).generate_state(1)[0])
            episodes.append(sample_episode(town, difficulty, k, ep_seed))
    return episodes


def sample_episode(town: Town, difficulty: Difficulty, index: int, seed: int) -> EpisodeSpec:
    rng = np.random.default_rng(seed)
    layout, roads = town.layout, town.roads
    size = REGION_SIZE_M[difficulty]
    bx0, by0, bx1, by1 = layout.bounds_world_m()
    cx = rng.uniform(bx0 + size / 2, max(bx0 + size / 2, bx1 - size / 2))
    cy = rng.uniform(by0 + size / 2, max(by0 + size / 2, by1 - size / 2))
    region = (float(cx - size / 2), float(cy - size / 2), float(cx + size / 2), float(cy + size / 2))

    occupied = layout.occupied_slots
    inner = _shrink(region, 10.0)
    free = [s for s in layout.slots if s.slot_id not in occupied and _inside(s.position_world_m, inner)]
    if not free:
        raise ValueError(f"town {layout.town_id}: no free parking slot in region {region}")
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
                         if all(math.dist(free[int(i)].position_world_m, u) >= MIN_LOOKALIKE_SPACING_M
                                for u in used)), None)
            if slot is None:
                break
            used.append(slot.position_world_m)
            distractors.append(_vehicle(*look, slot))

    active = town.uav_grid.inside(region)
    uav_start = str(rng.choice(active))
    ids, xy = roads.anchor_array()
    far = [int(n) for n, p in zip(ids, xy, strict=True)
           if _inside((p[0], p[1]), region) and roads.anchors[int(n)] == "cruise"
           and math.dist(p, target_slot.position_world_m) >= MIN_START_DISTANCE_M]
    ugv_start = roads.anchor_id(int(rng.choice(far)))
    return EpisodeSpec(
        episode_id=f"{layout.town_id}-{difficulty}-{index:03d}-v{EPISODE_VERSION}",
        town=TownRef(generator=layout.generator, seed=layout.seed, town_id=layout.town_id),
        asset_sha256=town.sha256, difficulty=difficulty, region_world_m=region,
        target=target, distractors=distractors, uav_start_waypoint=uav_start,
        ugv_start_waypoint=ugv_start, active_uav_waypoints=active,
        decision_budget=DECISION_BUDGET, seed=seed,
    )


def _vehicle(model: str, colour: str, slot) -> VehicleSpec:
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
            fh.write(ep.model_dump_json() + "\n")


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
            data = json.loads(line)
        except json.JSONDecodeError as exc:
            raise EpisodeFileError(f"{path}:{lineno}: not valid JSON ({exc.msg})") from exc
        try:
            episodes.append(EpisodeSpec.model_validate(data))
        except ValidationError as exc:
            err = exc.errors()[0]
            field = ".".join(str(p) for p in err["loc"])
            raise EpisodeFileError(f"{path}:{lineno}: field '{field}': {err['msg']}") from exc
    if not episodes:
        raise EpisodeFileError(f"{path}: no episodes in file")
    return episodes
