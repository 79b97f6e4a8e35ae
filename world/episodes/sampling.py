"""Episode sampling per difficulty (paper Table 1) and solvability checks (episode files: files.py).

easy: 150 m x 150 m region, no distractors; mid: 300 m x 300 m, none; hard: 300 m x 300 m with
2-3 look-alikes, each differing from the target in one cue (world/episodes/lookalikes.py).
Targets and look-alikes are parked on drivable roads (free parking slots inside the region, not
under decks, not on plazas). Every episode is checked solvable by rendering
(:mod:`agos.world.sim.evidence`); a region that fails is resampled. Two more rules keep every
episode a search: the target is the only vehicle of its full description (body type, paint,
attributes) in everything the UAV can see (:func:`unique_in_region`), though its paint and its
type alone recur as chance gives; and the UGV starts beyond the CONFIRM distance
(``MIN_START_DISTANCE_M``).

The vehicles follow the look of the scene that samples (and checks) the episode:

* ``flat`` (the boxes): six body types, look-alikes of the target's type in a near colour, or of
  its colour on another type, alternately;
* ``rich`` (the meshes): seven body types (a bus only in a slot whose neighbours on the lane are
  free), half of the cars among the targets with one attribute (two-tone roof, roof rack, stripe), and hard
  episodes whose 2-3 look-alikes take distinct kinds (another body type, a near paint, one
  attribute more or less) in a random order, each only from the pairs the cue bench found
  separable from the ground. Their ids say ``rich`` (``grid-s7-hard-000-rich-v1``); the flat look
  refuses them (agos.world.sim.episode_vehicles).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from agos.runtime.episode_config import DEFAULT_LOOK
from agos.runtime.schemas import DIFFICULTIES, Difficulty, EpisodeSpec, TownRef, VehicleSpec
from agos.world.episodes.files import EpisodeFileError as EpisodeFileError  # re-exported: read and write them from files.py
from agos.world.episodes.files import read_episodes as read_episodes
from agos.world.episodes.files import write_episodes as write_episodes
from agos.world.episodes.lookalikes import ATTRIBUTES, KINDS, separable
from agos.world.towns.asset import Town
from agos.world.towns.catalog import BODY_TYPES, NEAR_COLOURS, VIVID_COLOURS, paint_weights
from agos.world.towns.layout import TownLayout
from agos.world.towns.look.vehicles import ATTRIBUTE_BODY_TYPES, RICH_BODY_TYPES, ROOF_COLOUR, contrast_colour
from agos.world.towns.placement import ParkingSlot

REGION_SIZE_M: dict[str, float] = {"easy": 150.0, "mid": 300.0, "hard": 300.0}
EPISODE_VERSION = 1
MIN_START_DISTANCE_M = 60.0
"""The UGV starts at least this far from the target in a straight line, so farther by road: beyond
the 50 m CONFIRM distance (world/sim/confirm.py) with a margin, so no episode is confirmed from
where it starts."""
UNIQUE_MARGIN_M = 50.0
"""The target is unique by its description within this far outside its region: the UAV at the
region's edge sees half a nadir footprint (about 46 m) beyond it."""
TARGET_PAINT_P = paint_weights(VIVID_COLOURS)
"""A target's paint: a vivid one, with the survey's shares among them (blue and red most often)."""
MIN_LOOKALIKE_SPACING_M = 30.0
DECISION_BUDGET = 80
MAX_ATTEMPTS = 40
TARGET_ATTRIBUTE_P = 0.5
"""Rich look: the share of targets that carry one attribute."""
LONG_VEHICLE_CLEAR_M = 9.5
"""Rich look: a bus (11 m) parks only where no parked vehicle's slot on its lane is nearer than this."""


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
        spec = draw_candidate(town, difficulty, index, ep_seed, split, scene.look)
        if spec is not None and _solvable(town, scene, spec):
            return spec
    raise Unsolvable(f"town {town.town_id}: no solvable {difficulty} episode in {MAX_ATTEMPTS} attempts")


def draw_candidate(town: Town, difficulty: Difficulty, index: int, seed: int, split: str | None,
                   look: str) -> EpisodeSpec | None:
    """One draw of an episode (region, vehicles, starts) before the solvability check by rendering;
    None when the draw breaks a rule (no free slot, a target not unique, no start far enough)."""
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
    ordered = [free[int(i)] for i in order]
    vehicles = _rich_vehicles(rng, difficulty, ordered, layout) if look == "rich" else \
        _flat_vehicles(rng, difficulty, ordered)
    if vehicles is None:
        return None
    target, distractors = vehicles
    if not unique_in_region(target, layout, region, look):
        return None
    ids, xy = roads.anchor_array()
    starts = [int(n) for n, p in zip(ids, xy, strict=True)
              if _inside((p[0], p[1]), region) and roads.anchors[int(n)] == "cruise" and not roads.covered[int(n)]
              and math.dist(p, target_slot.position_world_m) >= MIN_START_DISTANCE_M]
    if not starts:
        return None
    rich = "rich-" if look == "rich" else ""
    return EpisodeSpec(
        episode_id=f"{layout.town_id}-{split + '-' if split else ''}{difficulty}-{index:03d}-{rich}v{EPISODE_VERSION}",
        town=town_ref(town),
        asset_sha256=town.sha256, difficulty=difficulty, region_world_m=region, target=target,
        distractors=distractors, uav_start_waypoint=str(rng.choice(active)),
        ugv_start_waypoint=roads.anchor_id(int(rng.choice(starts))), active_uav_waypoints=active,
        decision_budget=DECISION_BUDGET, seed=seed)


def _flat_vehicles(rng: np.random.Generator, difficulty: Difficulty,
                   slots: list[ParkingSlot]) -> tuple[VehicleSpec, list[VehicleSpec]] | None:
    """The flat look's target and look-alikes: the draws every flat episode file was made with."""
    model = str(rng.choice(sorted(BODY_TYPES)))
    colour = str(rng.choice(VIVID_COLOURS, p=TARGET_PAINT_P))
    target = _vehicle(model, colour, slots[0])
    distractors: list[VehicleSpec] = []
    if difficulty == "hard":
        used = [slots[0].position_world_m]
        for k in range(int(rng.integers(2, 4))):
            if k % 2 == 0:
                look = (model, str(rng.choice(NEAR_COLOURS[colour])))
            else:
                look = (str(rng.choice([m for m in sorted(BODY_TYPES) if m != model])), colour)
            slot = next((s for s in slots[1:]
                         if all(math.dist(s.position_world_m, u) >= MIN_LOOKALIKE_SPACING_M for u in used)), None)
            if slot is None:
                return None
            used.append(slot.position_world_m)
            distractors.append(_vehicle(*look, slot))
    return target, distractors


def _rich_vehicles(rng: np.random.Generator, difficulty: Difficulty, slots: list[ParkingSlot],
                   layout: TownLayout) -> tuple[VehicleSpec, list[VehicleSpec]] | None:
    """The rich look's target (sometimes with an attribute) and, when hard, look-alikes of distinct
    kinds, each differing from the target in one cue a viewer can check from the ground."""
    long_ok = long_slots(layout)
    types = [m for m in RICH_BODY_TYPES if m != "bus" or slots[0].slot_id in long_ok]
    model, colour = str(rng.choice(types)), str(rng.choice(VIVID_COLOURS, p=TARGET_PAINT_P))
    attrs: dict = {}
    if model in ATTRIBUTE_BODY_TYPES and rng.random() < TARGET_ATTRIBUTE_P:
        attrs = _with_attribute({}, str(rng.choice(ATTRIBUTES)), colour)
    target = _vehicle(model, colour, slots[0], attrs)
    distractors: list[VehicleSpec] = []
    if difficulty != "hard":
        return target, distractors
    used = [slots[0].position_world_m]

    def slot_for(kind_model: str) -> ParkingSlot | None:
        return next((s for s in slots[1:] if (kind_model != "bus" or s.slot_id in long_ok)
                     and all(math.dist(s.position_world_m, u) >= MIN_LOOKALIKE_SPACING_M for u in used)), None)

    kinds = [str(k) for k in rng.permutation(list(KINDS))]
    options = {kind: [o for o in _lookalikes(kind, model, colour, attrs) if slot_for(o[0]) is not None]
               for kind in kinds}
    kinds = [k for k in kinds if options[k]]
    if not kinds:
        return None
    for k in range(int(rng.integers(2, 4))):
        kind = kinds[k % len(kinds)]
        fresh = [o for o in options[kind] if slot_for(o[0]) is not None]
        if not fresh:
            return None
        alike_model, alike_colour, alike_attrs = fresh[int(rng.integers(len(fresh)))]
        slot = slot_for(alike_model)
        assert slot is not None, "fresh options have a slot"
        used.append(slot.position_world_m)
        distractors.append(_vehicle(alike_model, alike_colour, slot, alike_attrs))
    return target, distractors


def unique_in_region(target: VehicleSpec, layout: TownLayout, region: tuple[float, float, float, float],
                     look: str = DEFAULT_LOOK) -> bool:
    """No parked vehicle of the town within ``UNIQUE_MARGIN_M`` of ``region`` can be taken for the
    target (:func:`confusable`), so the episode has one answer in everything the UAV can see."""
    slots = {s.slot_id: s for s in layout.slots}
    seen = _shrink(region, -UNIQUE_MARGIN_M)
    return not any(confusable(target, car.model, car.colour, look)
                   and _inside(slots[car.slot_id].position_world_m, seen) for car in layout.parked)


def confusable(target: VehicleSpec, model: str, colour: str, look: str) -> bool:
    """Whether a plain vehicle (background traffic carries no attributes) of ``model`` and
    ``colour`` passes for the target: it has the target's full description, or differs from it in
    one cue only, in a pair a viewer cannot tell apart from the ground (the look-alike table's
    floor, :func:`~agos.world.episodes.lookalikes.separable`: a same-paint SUV for a pickup, a
    plain car for one with a two-tone roof). Two cues apart, or one separable cue, it does not."""
    cues: list[tuple[str, str, str]] = []
    if model != target.model:
        cues.append(("type", target.model, model))
    if colour != target.colour:
        if colour not in NEAR_COLOURS.get(target.colour, ()):
            return False  # another paint altogether
        cues.append(("paint", target.colour, colour))
    attributes = [name for name in ATTRIBUTES if getattr(target, name)]
    cues += [("attribute", "plain", name) for name in attributes]
    if not cues:
        return True
    return len(cues) == 1 and not separable(*cues[0], look=look)


def _lookalikes(kind: str, model: str, colour: str, attrs: dict) -> list[tuple[str, str, dict]]:
    """(model, colour, attributes) of every look-alike of one kind the table allows, in a fixed order."""
    if kind == "type":  # a target with an attribute has look-alikes only among the types that carry one
        types = ATTRIBUTE_BODY_TYPES if attrs else RICH_BODY_TYPES
        return [(m, colour, attrs) for m in types if m != model and separable("type", model, m, look="rich")]
    if kind == "paint":
        return [(model, c, attrs) for c in NEAR_COLOURS[colour] if separable("paint", colour, c, look="rich")]
    out: list[tuple[str, str, dict]] = []
    if model not in ATTRIBUTE_BODY_TYPES:
        return out
    for name in ATTRIBUTES:  # one attribute taken away, or one added
        if not separable("attribute", "plain", name, look="rich"):
            continue
        if name in attrs:
            out.append((model, colour, {k: v for k, v in attrs.items() if k != name}))
        else:
            out.append((model, colour, _with_attribute(attrs, name, colour)))
    return out


def _with_attribute(attrs: dict, name: str, paint: str) -> dict:
    """VehicleSpec attribute fields with ``name`` added (a white roof, a stripe in the paint's contrast colour)."""
    value = {"roof": ROOF_COLOUR, "rack": True, "stripe": contrast_colour(paint)}[name]
    return {**attrs, name: value}


def long_slots(layout: TownLayout) -> set[int]:
    """Slots a bus fits in: free, and no occupied slot on the same lane within LONG_VEHICLE_CLEAR_M."""
    occupied = layout.occupied_slots
    taken: dict[str, list[tuple[float, float]]] = {}
    for slot in layout.slots:
        if slot.slot_id in occupied:
            taken.setdefault(slot.lane_id, []).append(slot.position_world_m)
    return {s.slot_id for s in layout.slots
            if all(math.dist(s.position_world_m, p) >= LONG_VEHICLE_CLEAR_M for p in taken.get(s.lane_id, []))}


def _solvable(town: Town, scene, spec: EpisodeSpec) -> bool:
    from agos.world.episodes.solvability import check, reachable
    from agos.world.sim.episode_vehicles import add_episode_vehicles

    uid, *others = add_episode_vehicles(scene, spec)
    try:
        start = town.roads.parse_anchor_id(spec.ugv_start_waypoint)
        result = check(scene, town, uid, spec.target.position_world_m, spec.target.yaw_rad, spec.active_uav_waypoints,
                       ugv_start=start, uav_start=spec.uav_start_waypoint)
        return result.solvable and reachable(town, start, result.verifying_anchors)
    finally:
        for body in [uid, *others]:
            scene.remove(body)


def _vehicle(model: str, colour: str, slot: ParkingSlot, attrs: dict | None = None) -> VehicleSpec:
    x, y = slot.position_world_m
    return VehicleSpec(model=model, colour=colour, position_world_m=(x, y, 0.0), yaw_rad=slot.yaw_rad, **(attrs or {}))


def _shrink(region: tuple[float, float, float, float], m: float) -> tuple[float, float, float, float]:
    return (region[0] + m, region[1] + m, region[2] - m, region[3] - m)


def _inside(p: tuple[float, float], region: tuple[float, float, float, float]) -> bool:
    return region[0] <= p[0] <= region[2] and region[1] <= p[1] <= region[3]
