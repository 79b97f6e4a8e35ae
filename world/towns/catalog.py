"""Vehicle body types and paint colours.

A body type is a small set of boxes (body, cabin, glass band, cargo) whose proportions differ
from type to type, so types can be told apart from 80 m above (roof/glass pattern, length) and
from the ground (panel height).

Paints are drawn as real traffic is painted (:data:`PAINT_SHARES`, from a published survey of
the colours of the world's new cars; docs/WORLD.md gives the source and the mapping): background
traffic takes any paint, so a target's paint is shared by other vehicles of its region as often
as chance gives. Targets take a *vivid* paint (:data:`VIVID_COLOURS`) with the survey's shares
among those; the reason is written in docs/WORLD.md. ``NEAR_COLOURS`` defines which vivid paints
count as "a near colour" for hard-episode look-alikes.
"""

from __future__ import annotations

from dataclasses import dataclass

RGB = tuple[float, float, float]

COLOURS: dict[str, RGB] = {
    # neutral paints (and brown): background traffic only
    "white": (0.90, 0.90, 0.88),
    "black": (0.07, 0.07, 0.08),
    "silver": (0.62, 0.63, 0.66),
    "grey": (0.36, 0.36, 0.38),
    "brown": (0.36, 0.25, 0.16),
    # vivid paints: targets, their look-alikes and background traffic
    "red": (0.82, 0.08, 0.07),
    "maroon": (0.40, 0.02, 0.13),
    "blue": (0.08, 0.28, 0.88),
    "navy": (0.06, 0.09, 0.42),
    "green": (0.08, 0.62, 0.20),
    "olive": (0.38, 0.44, 0.08),
    "yellow": (0.95, 0.80, 0.08),
    "orange": (0.96, 0.45, 0.04),
}
VIVID_COLOURS: tuple[str, ...] = (
    "red", "maroon", "blue", "navy", "green", "olive", "yellow", "orange",
)
NEAR_COLOURS: dict[str, tuple[str, ...]] = {
    "red": ("maroon", "orange"),
    "maroon": ("red",),
    "blue": ("navy",),
    "navy": ("blue",),
    "green": ("olive",),
    "olive": ("green",),
    "yellow": ("orange",),
    "orange": ("yellow", "red"),
}
PAINT_SHARES: dict[str, float] = {
    # Axalta, Global Automotive Color Popularity Report 2020 (68th edition), world production:
    # white 38, black 19, grey 15, silver 9, blue 7, red 5, beige/brown 3, yellow/gold 2, green 1,
    # other 1 (percent). Where the palette has two shades of a survey colour they share it evenly;
    # "other" becomes orange.
    "white": 0.38, "black": 0.19, "grey": 0.15, "silver": 0.09, "brown": 0.03,
    "blue": 0.035, "navy": 0.035, "red": 0.025, "maroon": 0.025,
    "yellow": 0.02, "green": 0.005, "olive": 0.005, "orange": 0.01,
}
"""Share of each paint among vehicles: what background traffic is painted with (sums to 1)."""


def paint_weights(paints: tuple[str, ...]) -> list[float]:
    """:data:`PAINT_SHARES` of ``paints``, normalised to sum to 1 (a draw among those paints)."""
    shares = [PAINT_SHARES[p] for p in paints]
    return [w / sum(shares) for w in shares]


GLASS: RGB = (0.10, 0.13, 0.16)
TYRE: RGB = (0.05, 0.05, 0.05)
CARGO_WHITE: RGB = (0.93, 0.93, 0.93)


@dataclass(frozen=True)
class Part:
    """An axis-aligned box in the vehicle frame (x forward, y left, z up; metres)."""

    center_m: tuple[float, float, float]
    half_extents_m: tuple[float, float, float]
    paint: str
    """``body`` (the vehicle's colour), ``glass``, ``tyre`` or ``cargo``."""


@dataclass(frozen=True)
class BodyType:
    name: str
    length_m: float
    width_m: float
    height_m: float
    parts: tuple[Part, ...]


def _car(name: str, length: float, width: float, body_h: float, hood: float, cabin: float,
         cabin_h: float, clearance: float = 0.3) -> BodyType:
    """A car-like body: lower body along the whole length; a glass band and a roof over the
    cabin section, which starts ``hood`` metres behind the front bumper."""
    hl, hw = length / 2, width / 2
    top = clearance + body_h
    cabin_front = hl - hood
    cabin_cx = cabin_front - cabin / 2
    roof_t = 0.08
    glass_h = cabin_h - roof_t
    parts = [
        Part((0.0, 0.0, clearance + body_h / 2), (hl, hw, body_h / 2), "body"),
        Part((cabin_cx, 0.0, top + glass_h / 2), (cabin / 2 - 0.05, hw - 0.08, glass_h / 2), "glass"),
        Part((cabin_cx, 0.0, top + glass_h + roof_t / 2), (cabin / 2 - 0.15, hw - 0.1, roof_t / 2), "body"),
    ]
    return BodyType(name, length, width, top + cabin_h, tuple(parts + _tyres(length, width)))


def _tyres(length: float, width: float) -> list[Part]:
    dx, dy = length / 2 - 0.8, width / 2 - 0.12
    return [Part((sx * dx, sy * dy, 0.33), (0.33, 0.12, 0.33), "tyre")
            for sx in (1, -1) for sy in (1, -1)]


def _pickup() -> BodyType:
    length, width, clearance, body_h = 5.3, 2.0, 0.4, 0.9
    hl, hw = length / 2, width / 2
    top = clearance + body_h
    parts = [
        Part((0.0, 0.0, clearance + body_h / 2), (hl, hw, body_h / 2), "body"),
        # cabin right behind a 1.4 m hood
        Part((hl - 1.4 - 0.9, 0.0, top + 0.35), (0.85, hw - 0.08, 0.35), "glass"),
        Part((hl - 1.4 - 0.9, 0.0, top + 0.74), (0.75, hw - 0.1, 0.04), "body"),
        # open bed: a dark floor over the rear of the body, visible from above
        Part((-hl + 1.05, 0.0, top + 0.005), (1.05, hw, 0.01), "tyre"),
    ]
    return BodyType("pickup", length, width, top + 0.78, tuple(parts + _tyres(length, width)))


def _van() -> BodyType:
    length, width, clearance = 5.2, 2.0, 0.35
    hl, hw = length / 2, width / 2
    parts = [
        Part((hl - 0.45, 0.0, clearance + 0.45), (0.45, hw, 0.45), "body"),  # short nose
        Part((hl - 1.05, 0.0, clearance + 1.25), (0.15, hw - 0.05, 0.35), "glass"),  # windscreen
        Part((-0.45, 0.0, clearance + 0.95), (hl - 0.75, hw, 0.95), "body"),  # tall box
    ]
    return BodyType("van", length, width, clearance + 1.9, tuple(parts + _tyres(length, width)))


def _box_truck() -> BodyType:
    length, width, clearance = 7.4, 2.4, 0.5
    hl, hw = length / 2, width / 2
    parts = [
        Part((hl - 1.0, 0.0, clearance + 0.55), (1.0, hw - 0.05, 0.55), "body"),  # cab
        Part((hl - 1.0, 0.0, clearance + 1.45), (0.9, hw - 0.1, 0.35), "glass"),
        Part((hl - 1.0, 0.0, clearance + 1.85), (0.85, hw - 0.1, 0.05), "body"),
        Part((-1.05, 0.0, clearance + 1.4), (2.65, hw, 1.4), "body"),  # cargo box up to the cab
    ]
    return BodyType("box_truck", length, width, clearance + 2.8, tuple(parts + _tyres(length, width)))


BODY_TYPES: dict[str, BodyType] = {
    b.name: b
    for b in (
        _car("sedan", 4.6, 1.8, 0.6, hood=1.3, cabin=2.2, cabin_h=0.5),
        _car("hatchback", 3.9, 1.75, 0.65, hood=0.9, cabin=2.3, cabin_h=0.65),
        _car("suv", 4.9, 2.0, 1.0, hood=1.0, cabin=3.3, cabin_h=0.8, clearance=0.4),
        _pickup(),
        _van(),
        _box_truck(),
    )
}


def colour_rgb(name: str) -> RGB:
    try:
        return COLOURS[name]
    except KeyError:
        raise ValueError(f"unknown colour {name!r}; known: {', '.join(COLOURS)}") from None


def body_type(name: str) -> BodyType:
    try:
        return BODY_TYPES[name]
    except KeyError:
        raise ValueError(f"unknown vehicle model {name!r}; known: {', '.join(BODY_TYPES)}") from None
