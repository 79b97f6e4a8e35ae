"""What keeps an episode a search rather than a one-cue lookup (docs/VALIDITY.md): background
traffic painted as real traffic is, a target unique by its full description but not by its paint,
and a UGV that starts beyond the CONFIRM distance."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
from scipy.stats import chisquare

from agos.world.episodes.sampling import (
    DIFFICULTIES,
    MIN_START_DISTANCE_M,
    UNIQUE_MARGIN_M,
    confusable,
    draw_candidate,
    unique_in_region,
)
from agos.world.sim.confirm import ConfirmConfig, ConfirmEvidence, check_confirm
from agos.world.towns.asset import Town, build_town
from agos.world.towns.catalog import PAINT_SHARES, VIVID_COLOURS
from agos.world.towns.layout import ParkedVehicle, park_background
from agos.world.towns.placement import ParkingSlot
from agos.world.towns.procedural import TOWNS


@pytest.fixture(scope="module")
def towns() -> dict[str, Town]:
    return {town_id: build_town(*TOWNS[town_id]) for town_id in sorted(TOWNS)}


def test_survey_shares_are_a_distribution() -> None:
    assert sum(PAINT_SHARES.values()) == pytest.approx(1.0)
    assert all(p in PAINT_SHARES for p in VIVID_COLOURS)


def test_background_paints_follow_the_survey(towns: dict[str, Town]) -> None:
    """Every parked vehicle of the six towns, against the survey's shares: a chi-square
    goodness-of-fit test that a wrong table (the neutral-only traffic of before) fails at once."""
    counts = Counter(p.colour for t in towns.values() for p in t.layout.parked)
    n = sum(counts.values())
    assert n >= 2000, n
    paints = sorted(PAINT_SHARES)
    observed = [counts.get(p, 0) for p in paints]
    expected = [PAINT_SHARES[p] * n for p in paints]
    assert chisquare(observed, expected).pvalue > 0.001, dict(zip(paints, observed, strict=True))
    neutral_only = [n * 0.25 if p in ("white", "black", "silver", "grey") else 1e-9 for p in paints]
    assert chisquare(observed, np.asarray(neutral_only) * n / sum(neutral_only)).pvalue < 1e-12


def test_a_large_sample_of_one_draw_matches_the_shares() -> None:
    slots = [type("Slot", (), {"slot_id": k})() for k in range(20_000)]
    parked = park_background(slots, 1.0, np.random.default_rng(3))  # type: ignore[arg-type]
    counts = Counter(p.colour for p in parked)
    paints = sorted(PAINT_SHARES)
    assert chisquare([counts.get(p, 0) for p in paints], [PAINT_SHARES[p] * len(parked) for p in paints]).pvalue > 0.001


def draws(towns: dict[str, Town], per_town: int) -> list[tuple[Town, object]]:
    out = []
    for town in towns.values():
        for k in range(per_town):
            difficulty = DIFFICULTIES[k % 3]
            spec = draw_candidate(town, difficulty, k, seed=1000 + k, split=None, look="rich")
            if spec is not None:
                out.append((town, spec))
    return out


def test_every_draw_has_a_unique_target_and_a_far_ugv_start(towns: dict[str, Town]) -> None:
    """Over 300 and more episode draws on every procedural town: the target is the only vehicle
    of its description within reach of the UAV's eyes, other vehicles share its paint, and the
    UGV's first position is beyond the CONFIRM distance (so its first six views cannot confirm)."""
    sample = draws(towns, 125)  # 327 of 750 draws succeed (342 of 660 before the stripe fell below the table's floor)
    assert len(sample) >= 300, len(sample)
    confirm = ConfirmConfig()
    assert confirm.max_distance_m < MIN_START_DISTANCE_M
    shared_paint = 0
    for town, spec in sample:
        layout = town.layout
        slots = {s.slot_id: s for s in layout.slots}
        x0, y0, x1, y1 = spec.region_world_m
        seen = [p for p in layout.parked
                if x0 - UNIQUE_MARGIN_M <= slots[p.slot_id].position_world_m[0] <= x1 + UNIQUE_MARGIN_M
                and y0 - UNIQUE_MARGIN_M <= slots[p.slot_id].position_world_m[1] <= y1 + UNIQUE_MARGIN_M]
        t = spec.target
        if not (t.roof or t.rack or t.stripe):
            assert not [p for p in seen if (p.model, p.colour) == (t.model, t.colour)], spec.episode_id
        assert not [p for p in seen if confusable(t, p.model, p.colour, "rich")], spec.episode_id
        shared_paint += any(p.colour == t.colour for p in seen)
        start = town.roads.positions_world_m[town.roads.parse_anchor_id(spec.ugv_start_waypoint)]
        distance = math.dist(start, t.position_world_m[:2])
        assert distance >= MIN_START_DISTANCE_M, spec.episode_id
        # What the checker says at the start, however clear the view: too far.
        evidence = ConfirmEvidence(True, 10_000, distance, True)
        assert check_confirm(evidence, confirm), spec.episode_id
    assert shared_paint / len(sample) > 0.5, shared_paint  # the paint alone rarely names the target


def test_uniqueness_looks_beyond_the_region() -> None:
    """A twin of the target 40 m outside the region is in the UAV's view: the draw is refused;
    one 80 m outside is not; an attribute the ground tells apart (the look-alike table's floor) makes
    the target unique whatever its twins, one it cannot does not."""
    from types import SimpleNamespace

    from agos.runtime.schemas import VehicleSpec
    from agos.world.episodes.lookalikes import separable

    layout = SimpleNamespace(slots=[ParkingSlot(0, (0.0, 0.0), 0.0, "lane", False, False)],
                             parked=[ParkedVehicle(0, "sedan", "red")])
    target = VehicleSpec(model="sedan", colour="red", position_world_m=(100.0, 100.0, 0.0), yaw_rad=0.0)
    assert not unique_in_region(target, layout, (40.0, 40.0, 140.0, 140.0))  # type: ignore[arg-type]
    assert unique_in_region(target, layout, (80.0, 80.0, 180.0, 180.0))  # type: ignore[arg-type]
    racked = VehicleSpec(model="sedan", colour="red", position_world_m=(100.0, 100.0, 0.0), yaw_rad=0.0, rack=True)
    assert unique_in_region(racked, layout, (40.0, 40.0, 140.0, 140.0))  # type: ignore[arg-type]
    striped = VehicleSpec(model="sedan", colour="red", position_world_m=(100.0, 100.0, 0.0), yaw_rad=0.0, stripe="white")
    told_apart = separable("attribute", "plain", "stripe", look="rich")  # not since issue 29's town
    assert unique_in_region(striped, layout, (40.0, 40.0, 140.0, 140.0)) == told_apart  # type: ignore[arg-type]
    blue = VehicleSpec(model="sedan", colour="blue", position_world_m=(100.0, 100.0, 0.0), yaw_rad=0.0)
    assert unique_in_region(blue, layout, (40.0, 40.0, 140.0, 140.0))  # type: ignore[arg-type]


def test_what_passes_for_the_target() -> None:
    """One cue apart counts only where the look-alike table says the ground cannot tell the pair
    apart; the rich look's table has pickup vs SUV, plain vs two-tone roof and plain vs stripe below
    its floor."""
    from agos.runtime.schemas import VehicleSpec
    from agos.world.episodes.lookalikes import separable

    def car(model: str, colour: str, **attrs) -> VehicleSpec:
        return VehicleSpec(model=model, colour=colour, position_world_m=(0.0, 0.0, 0.0), yaw_rad=0.0, **attrs)

    assert confusable(car("sedan", "red"), "sedan", "red", "rich")  # the same description
    assert not confusable(car("sedan", "red"), "sedan", "blue", "rich")  # another paint
    assert not confusable(car("sedan", "red"), "van", "red", "rich")  # a type told apart
    assert confusable(car("pickup", "blue"), "suv", "blue", "rich") == (not separable("type", "pickup", "suv", look="rich"))
    assert confusable(car("sedan", "red", roof="white"), "sedan", "red", "rich") == \
        (not separable("attribute", "plain", "roof", look="rich"))
    assert not confusable(car("sedan", "red", stripe="white"), "hatchback", "red", "rich")  # two cues apart
    assert confusable(car("pickup", "blue"), "suv", "blue", "flat") is False  # the flat look: every pair told apart
