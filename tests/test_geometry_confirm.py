"""Planar geometry (agos/world/geometry.py) and the CONFIRM checker (agos/world/confirm.py)."""

from __future__ import annotations

import math

import pytest

from agos.runtime.geometry import (
    centroid,
    distance_to_polygon,
    distance_to_polygon_boundary,
    distance_to_segment,
    point_in_polygon,
)
from agos.world.sim.confirm import ConfirmConfig, ConfirmEvidence, check_confirm

SQUARE = [(0.0, 0.0), (10.0, 0.0), (10.0, 10.0), (0.0, 10.0)]
# An L shape: the square [0,10]^2 minus its top-right quarter [5,10]x[5,10].
L_SHAPE = [(0.0, 0.0), (10.0, 0.0), (10.0, 5.0), (5.0, 5.0), (5.0, 10.0), (0.0, 10.0)]


@pytest.mark.parametrize("p", [(5.0, 5.0), (0.1, 9.9), (9.99, 0.01)])
def test_point_inside_square(p) -> None:
    assert point_in_polygon(p, SQUARE)


@pytest.mark.parametrize("p", [(-0.1, 5.0), (10.1, 5.0), (5.0, 10.5), (5.0, -3.0), (20.0, 20.0)])
def test_point_outside_square(p) -> None:
    assert not point_in_polygon(p, SQUARE)


@pytest.mark.parametrize("p", [(0.0, 0.0), (10.0, 10.0), (5.0, 0.0), (10.0, 3.0), (0.0, 7.5), (2.5, 10.0)])
def test_boundary_counts_as_inside(p) -> None:
    assert point_in_polygon(p, SQUARE)
    assert distance_to_polygon(p, SQUARE) == 0.0


def test_concave_polygon() -> None:
    assert point_in_polygon((2.0, 8.0), L_SHAPE)
    assert point_in_polygon((8.0, 2.0), L_SHAPE)
    assert not point_in_polygon((7.5, 7.5), L_SHAPE)  # in the notch
    assert point_in_polygon((5.0, 7.0), L_SHAPE)  # on the notch edge
    # from the notch point (8, 7) the nearest boundary is the edge y=5 (2 m) ...
    assert distance_to_polygon((8.0, 7.0), L_SHAPE) == pytest.approx(2.0)
    # ... and from (6, 9) it is the edge x=5 (1 m)
    assert distance_to_polygon((6.0, 9.0), L_SHAPE) == pytest.approx(1.0)


def test_triangle_orientation_does_not_matter() -> None:
    tri = [(0.0, 0.0), (4.0, 0.0), (0.0, 3.0)]
    for poly in (tri, tri[::-1]):
        assert point_in_polygon((1.0, 1.0), poly)
        assert not point_in_polygon((3.0, 2.0), poly)
        # distance from (4, 3) to the hypotenuse 3x + 4y = 12: |12 + 12 - 12| / 5
        assert distance_to_polygon((4.0, 3.0), poly) == pytest.approx(12 / 5)


@pytest.mark.parametrize("p", [(5.0, 5.0), (1.0, 9.0), (0.0, 0.0)])
def test_distance_zero_inside(p) -> None:
    assert distance_to_polygon(p, SQUARE) == 0.0


def test_distance_boundary_inside_is_positive() -> None:
    # the boundary distance is not clipped to 0: only distance_to_polygon is
    assert distance_to_polygon_boundary((5.0, 4.0), SQUARE) == pytest.approx(4.0)
    assert distance_to_polygon_boundary((1.0, 9.0), SQUARE) == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("p", "expected"),
    [
        ((13.0, 5.0), 3.0),  # right of the right edge
        ((5.0, -2.5), 2.5),  # below the bottom edge
        ((-4.0, 12.0), math.hypot(4.0, 2.0)),  # nearest the top-left corner
        ((13.0, 14.0), 5.0),  # 3-4-5 from corner (10, 10)
        ((-1.0, -1.0), math.sqrt(2.0)),
    ],
)
def test_distance_outside(p, expected) -> None:
    assert distance_to_polygon(p, SQUARE) == pytest.approx(expected)


@pytest.mark.parametrize(
    ("p", "a", "b", "expected"),
    [
        ((0.0, 3.0), (-5.0, 0.0), (5.0, 0.0), 3.0),  # perpendicular foot inside the segment
        ((8.0, 4.0), (-5.0, 0.0), (5.0, 0.0), 5.0),  # beyond b: distance to b (3-4-5)
        ((-8.0, -4.0), (-5.0, 0.0), (5.0, 0.0), 5.0),  # before a: distance to a
        ((2.0, 0.0), (-5.0, 0.0), (5.0, 0.0), 0.0),  # on the segment
        ((4.0, 5.0), (1.0, 1.0), (1.0, 1.0), 5.0),  # degenerate segment: a point
        ((0.0, 2.0), (0.0, 0.0), (2.0, 2.0), math.sqrt(2.0)),  # diagonal, foot at (1, 1)
    ],
)
def test_distance_to_segment(p, a, b, expected) -> None:
    assert distance_to_segment(p, a, b) == pytest.approx(expected)
    assert distance_to_segment(p, b, a) == pytest.approx(expected)


def test_centroid() -> None:
    assert centroid(SQUARE) == (5.0, 5.0)
    assert centroid([(0.0, 0.0), (6.0, 0.0), (0.0, 3.0)]) == (2.0, 1.0)


# --- CONFIRM checker -----------------------------------------------------------------------------

GOOD = ConfirmEvidence(fresh_stop=True, max_target_pixels=500, distance_m=20.0, line_of_sight=True)
DEFAULT = ConfirmConfig()


def _with(**changes) -> ConfirmEvidence:
    fields = {"fresh_stop": GOOD.fresh_stop, "max_target_pixels": GOOD.max_target_pixels,
              "distance_m": GOOD.distance_m, "line_of_sight": GOOD.line_of_sight}
    fields.update(changes)
    return ConfirmEvidence(**fields)


def test_defaults() -> None:
    assert DEFAULT.require_fresh_stop is True
    assert DEFAULT.min_target_pixels == 50
    assert DEFAULT.max_distance_m == 50.0
    assert DEFAULT.require_line_of_sight is True


def test_good_evidence_passes() -> None:
    assert check_confirm(GOOD, DEFAULT) == []


def test_not_fresh_alone() -> None:
    assert check_confirm(_with(fresh_stop=False), DEFAULT) == ["no fresh STOP_OBSERVE"]


def test_not_visible_alone() -> None:
    assert check_confirm(_with(max_target_pixels=49), DEFAULT) == ["target not visible (49 < 50 px)"]


def test_exactly_min_pixels_passes() -> None:
    assert check_confirm(_with(max_target_pixels=50), DEFAULT) == []


def test_too_far_alone() -> None:
    reasons = check_confirm(_with(distance_m=80.0), DEFAULT)
    assert len(reasons) == 1
    assert reasons[0].startswith("target 80.0 m away")


def test_exactly_50_m_passes_and_50_01_fails() -> None:
    assert check_confirm(_with(distance_m=50.0), DEFAULT) == []
    reasons = check_confirm(_with(distance_m=50.01), DEFAULT)
    assert len(reasons) == 1
    assert "away" in reasons[0]


def test_no_line_of_sight_alone() -> None:
    assert check_confirm(_with(line_of_sight=False), DEFAULT) == ["no clear line of sight"]


def test_all_failures_together_in_order() -> None:
    bad = ConfirmEvidence(fresh_stop=False, max_target_pixels=0, distance_m=120.0, line_of_sight=False)
    reasons = check_confirm(bad, DEFAULT)
    assert len(reasons) == 4
    assert reasons[0] == "no fresh STOP_OBSERVE"
    assert reasons[1] == "target not visible (0 < 50 px)"
    assert reasons[2].startswith("target 120.0 m away")
    assert reasons[3] == "no clear line of sight"


def test_switch_off_fresh_stop() -> None:
    settings = ConfirmConfig(require_fresh_stop=False)
    assert check_confirm(_with(fresh_stop=False), settings) == []
    # the other checks still apply
    assert check_confirm(_with(fresh_stop=False, line_of_sight=False), settings) == ["no clear line of sight"]


def test_switch_off_visibility() -> None:
    settings = ConfirmConfig(min_target_pixels=0)
    assert check_confirm(_with(max_target_pixels=0), settings) == []
    assert check_confirm(_with(max_target_pixels=0, fresh_stop=False), settings) == ["no fresh STOP_OBSERVE"]


def test_raise_visibility_threshold() -> None:
    settings = ConfirmConfig(min_target_pixels=1000)
    assert check_confirm(GOOD, settings) == ["target not visible (500 < 1000 px)"]


def test_switch_off_distance() -> None:
    settings = ConfirmConfig(max_distance_m=math.inf)
    assert check_confirm(_with(distance_m=10_000.0), settings) == []
    tight = ConfirmConfig(max_distance_m=10.0)
    assert len(check_confirm(GOOD, tight)) == 1  # 20 m > 10 m


def test_switch_off_line_of_sight() -> None:
    settings = ConfirmConfig(require_line_of_sight=False)
    assert check_confirm(_with(line_of_sight=False), settings) == []
    assert check_confirm(_with(line_of_sight=False, max_target_pixels=3), settings) == [
        "target not visible (3 < 50 px)"
    ]


def test_everything_off_accepts_anything() -> None:
    settings = ConfirmConfig(require_fresh_stop=False, min_target_pixels=0, max_distance_m=math.inf,
                               require_line_of_sight=False)
    bad = ConfirmEvidence(fresh_stop=False, max_target_pixels=0, distance_m=1e6, line_of_sight=False)
    assert check_confirm(bad, settings) == []
