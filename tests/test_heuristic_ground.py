"""The heuristic UGV's checks of its six views on synthetic ground views: paint in its light,
body height and length, not colour alone (:func:`find_target`, the paint-only policy's and the
stand-in's), and the heuristic's own judge against the side references (:func:`judge_views`:
outline and paint tops, paint bands, leads).

A synthetic view is a camera 1.7 m over a flat street looking along +x (a UGV's view), with a
vehicle seen broadside: a painted face, and a roof when the vehicle is lower than the camera; or
box-built vehicles ray-cast with their reference views (tests/support/boxcars.py). Depth is metric
(z along the optical axis); every image goes through JPEG as agents get it.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np
import pytest

from agos.agents.heuristic import ground
from agos.agents.heuristic.colour_match import TargetProfile, profile_from_references
from agos.agents.heuristic.ground import (
    CONFIRM_RANGE_M,
    PROFILE_TOLERANCE_M,
    TOO_CLOSE_M,
    GroundJudgement,
    GroundView,
    SideReference,
    find_target,
    judge_views,
    profile_error,
    side_reference,
)
from agos.runtime.camera import intrinsics_for

from support import boxcars

EYE_M = 1.7
SIZE_PX = 256
INTR = intrinsics_for(SIZE_PX, SIZE_PX, 70.0)
# OpenCV camera: x right (world -y), y down (world -z), z forward (world +x).
POSE = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, EYE_M], [0.0, 0.0, 0.0, 1.0]])
ASPHALT = (92, 92, 94)
SKY = (170, 200, 235)
BLUE = (20, 71, 224)
NAVY = (15, 23, 107)
GREEN = (20, 158, 51)


def profile(rgb: tuple[int, int, int], *, length_m: float, height_m: float, width_m: float = 1.8) -> TargetProfile:
    """What the references of a sunlit vehicle of this paint and size would give."""
    h, s, v = cv2.cvtColor(np.uint8([[rgb]]), cv2.COLOR_RGB2HSV)[0, 0].astype(float)
    return TargetProfile(hue=h, saturation=s, value_top=v, value_side=(0.8 * v, v), length_m=length_m, width_m=width_m,
                         paint_top_m=height_m, body_length_m=length_m, body_width_m=width_m, body_height_m=height_m,
                         paint_fraction=0.75)


def broadside(colour, *, distance_m: float = 10.0, length_m: float, height_m: float, width_m: float = 1.8,
              shade: bool = False) -> GroundView:
    """A vehicle across the view (length along world y), its near face ``distance_m`` ahead. In
    shade, the vehicle is darkened to 62% and the street around it turns bluish, as the world
    draws a building's shadow."""
    us, vs = np.meshgrid(np.arange(SIZE_PX) + 0.5, np.arange(SIZE_PX) + 0.5)
    a = (us - INTR.cx_px) / INTR.fx_px  # ray per unit of depth: x = t, y = -a t, z = EYE - b t
    b = (vs - INTR.cy_px) / INTR.fy_px
    depth = np.full((SIZE_PX, SIZE_PX), 300.0)
    rgb = np.zeros((SIZE_PX, SIZE_PX, 3), np.float32)
    rgb[:] = SKY
    ground = b > 0
    t = np.where(ground, EYE_M / np.maximum(b, 1e-6), np.inf)
    depth[ground] = np.minimum(t[ground], 300.0)
    rgb[ground] = ASPHALT
    if shade:
        near_car = ground & (t > distance_m - 3.0) & (t < distance_m + width_m + 3.0)
        rgb[near_car] = np.float32(ASPHALT) * np.float32([0.52, 0.55, 0.64])
    paint = np.float32(colour) * (0.62 if shade else 1.0)
    z_face, y_face = EYE_M - b * distance_m, -a * distance_m
    face = (z_face >= 0.3) & (z_face <= height_m) & (np.abs(y_face) <= length_m / 2)
    depth[face] = distance_m
    rgb[face] = paint
    if height_m < EYE_M:  # the roof, seen from above
        t_roof = (EYE_M - height_m) / np.maximum(b, 1e-6)
        roof = (b > 0) & (t_roof > distance_m) & (t_roof < distance_m + width_m) & (np.abs(a * t_roof) <= length_m / 2)
        depth[roof] = t_roof[roof]
        rgb[roof] = paint
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(rgb.astype(np.uint8), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    jpeg = cv2.cvtColor(cv2.imdecode(data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return GroundView("front", jpeg, depth.astype(np.float32), INTR, POSE)


HATCHBACK = {"length_m": 3.9, "height_m": 1.52}


def test_the_target_broadside_is_found_at_its_height_and_place() -> None:
    found = find_target([broadside(GREEN, **HATCHBACK)], profile(GREEN, **HATCHBACK))
    assert len(found) == 1
    assert abs(found[0].top_m - 1.52) < 0.12 and abs(found[0].distance_m - 10.0) < 1.5
    assert abs(found[0].y_m) < 0.5 and found[0].length_m < 3.9 + 0.5


def test_a_taller_or_longer_vehicle_of_the_same_paint_is_not_the_target() -> None:
    target = profile(GREEN, **HATCHBACK)
    assert find_target([broadside(GREEN, length_m=4.9, height_m=1.82)], target) == []  # an SUV
    assert find_target([broadside(GREEN, length_m=5.3, height_m=1.52)], target) == []  # longer
    assert find_target([broadside(GREEN, length_m=3.9, height_m=1.30)], target) == []  # lower


def test_a_navy_vehicle_in_the_sun_is_not_a_blue_target_but_a_blue_one_in_shade_is() -> None:
    target = profile(BLUE, **HATCHBACK)
    assert find_target([broadside(NAVY, **HATCHBACK)], target) == []
    assert len(find_target([broadside(BLUE, **HATCHBACK, shade=True)], target)) == 1


def test_a_blue_vehicle_in_shade_is_not_a_navy_target() -> None:
    target = profile(NAVY, **HATCHBACK)
    assert find_target([broadside(NAVY, **HATCHBACK)], target)  # the target itself, sunlit
    assert find_target([broadside(BLUE, **HATCHBACK, shade=True)], target) == []


def test_markings_and_shadows_on_the_street_are_not_objects() -> None:
    view = broadside(GREEN, distance_m=60.0, **HATCHBACK)  # beyond reach: the street alone in range
    rgb = view.rgb.copy()
    rgb[200:210, :] = (40, 160, 60)  # a green painted band across the street (flat)
    flat = GroundView("front", rgb, view.depth_m, INTR, POSE)
    assert find_target([flat], profile(GREEN, **HATCHBACK)) == []


# ----- the heuristic UGV's judge (judge_views) against box-built vehicles and their references -----

RED = (200, 30, 25)
ROOF_BOX_SEDAN = boxcars.car(RED, length_m=4.6, width_m=1.8, height_m=1.4, roof_box=True)
SEDAN = boxcars.car(RED, length_m=4.6, width_m=1.8, height_m=1.4)
SUV = boxcars.car(RED, length_m=4.9, width_m=2.0, height_m=1.8)
VAN = boxcars.car(RED, length_m=5.2, width_m=2.0, height_m=2.1)


@functools.cache
def reference(name: str) -> tuple[TargetProfile, SideReference]:
    """The profile and side reference of one of the vehicles above, from its rendered references."""
    parts = {"roof box sedan": ROOF_BOX_SEDAN, "sedan": SEDAN, "bus": boxcars.bus(RED),
             "box truck": boxcars.box_truck(RED), "pickup": boxcars.pickup(RED)}[name]
    frames = boxcars.references(parts)
    target = profile_from_references(frames)
    return target, side_reference(frames, target)


def judged(vehicle: list[boxcars.Part], target: str, *, x_m: float = 9.0, y_m: float = 3.5,
           yaw_deg: float = 20.0) -> GroundJudgement:
    view = boxcars.ground_view([boxcars.placed(vehicle, x_m, y_m)], yaw_deg=yaw_deg)
    return judge_views([view], *reference(target), min_pixels=40)


def test_the_side_reference_measures_the_outline_the_paint_and_its_bands() -> None:
    _, side = reference("roof box sedan")
    assert side.top_m == pytest.approx(1.85, abs=0.05)  # the roof box's top
    assert side.paint_top_m == pytest.approx(1.4, abs=0.05)  # the painted roof under it
    assert side.top_low_m <= side.top_m
    broadside = np.asarray(side.bands[1])  # ref_side
    lower, glass = broadside[1], broadside[3]  # 0.6-0.9 m (painted door), 1.2-1.5 m (side windows)
    assert lower > 0.9 and glass < 0.6
    _, bus_side = reference("bus")
    _, truck_side = reference("box truck")
    middle = slice(4, 7)  # 1.5-2.4 m: a bus's windows, a box truck's painted box
    assert np.nanmax(np.asarray(bus_side.bands[1])[middle]) < 0.2
    assert np.nanmin(np.asarray(truck_side.bands[1])[middle]) > 0.8


def test_a_roof_box_target_is_confirmed_and_taller_bodies_of_its_paint_are_not() -> None:
    found = judged(ROOF_BOX_SEDAN, "roof box sedan")
    assert len(found.matches) == 1 and found.matches[0].top_m == pytest.approx(1.85, abs=0.1)
    assert found.matches[0].distance_m == pytest.approx(9.5, abs=1.5)
    # an SUV's and a van's tops are near the roof box's, but their paint goes all the way up
    suv = judged(SUV, "roof box sedan")
    assert suv.matches == [] and suv.leads == []
    assert find_target([boxcars.ground_view([boxcars.placed(SUV, 9.0, 3.5)], yaw_deg=20.0)],
                       reference("roof box sedan")[0]), "the old check took the SUV"
    assert judged(VAN, "roof box sedan").matches == []


def test_a_plain_twin_is_not_a_roof_box_target_nor_the_other_way_round() -> None:
    assert judged(SEDAN, "roof box sedan").matches == []
    assert judged(ROOF_BOX_SEDAN, "sedan").matches == []
    assert len(judged(SEDAN, "sedan").matches) == 1


def test_the_paint_bands_tell_a_box_truck_from_a_bus() -> None:
    truck, bus = boxcars.box_truck(RED), boxcars.bus(RED)
    assert len(judged(bus, "bus", x_m=14.0, y_m=6.0).matches) == 1
    assert len(judged(truck, "box truck", x_m=14.0, y_m=6.0).matches) == 1
    assert judged(truck, "bus", x_m=14.0, y_m=6.0).matches == []  # as tall, painted where a bus has windows
    assert judged(bus, "box truck", x_m=14.0, y_m=6.0).matches == []


def test_the_target_seen_end_on_is_confirmed() -> None:
    assert len(judged(ROOF_BOX_SEDAN, "roof box sedan", x_m=9.0, y_m=0.0, yaw_deg=0.0).matches) == 1


def test_a_far_target_is_a_lead_to_look_at_again_not_a_match() -> None:
    far = judged(ROOF_BOX_SEDAN, "roof box sedan", x_m=30.0, y_m=3.5, yaw_deg=7.0)
    assert far.matches == [] and len(far.leads) == 1
    assert far.leads[0].distance_m > CONFIRM_RANGE_M


def test_the_outline_along_the_body_tells_a_pickups_short_cab_from_a_long_cabin() -> None:
    """As tall, as long, the same paint: an SUV-like body whose cabin covers most of its length is
    not a pickup whose cab stands over a third of it (the outline compared along the body)."""
    long_cabin = boxcars.car(RED, length_m=5.3, width_m=2.0, height_m=1.85, cabin_share=0.75)
    _, side = reference("pickup")
    assert np.nanmax(side.profile_m) == pytest.approx(1.85, abs=0.08) and np.nanmin(side.profile_m) < 1.2
    view = boxcars.ground_view([boxcars.placed(long_cabin, 9.0, 4.0)], yaw_deg=25.0)
    parts = [(p.xy_m, p.top_m) for p in ground._join_parts(ground._parts(view, reference("pickup")[0], 40, False))]
    assert len(parts) == 1 and (profile_error(*parts[0], side) or 0.0) > PROFILE_TOLERANCE_M
    assert judged(long_cabin, "pickup", y_m=4.0, yaw_deg=25.0).matches == []
    target = judged(boxcars.pickup(RED), "pickup", y_m=4.0, yaw_deg=25.0)
    assert len(target.matches) == 1


def test_the_target_right_beside_the_camera_is_a_lead_to_see_from_further() -> None:
    """Stopped beside a box truck, the view shows a painted wall and the cab's side, not its top:
    neither a match nor refused, but a lead (the UGV looks again from a road option further off)."""
    beside = judged(boxcars.box_truck(RED), "box truck", x_m=0.0, y_m=2.6, yaw_deg=90.0)
    assert beside.matches == [] and len(beside.leads) == 1
    assert beside.leads[0].distance_m < TOO_CLOSE_M
