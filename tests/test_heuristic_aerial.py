"""The heuristic UAV's aerial detector on synthetic nadir views: shape and context, not colour alone.

A synthetic view is a straight-down camera 80 m over a flat street (the UAV's nadir camera),
with a metric depth image that gives standing things their height, and an RGB image that gives
them paint, glass, shade, lane lines or brick. Every image goes through JPEG as agents get it.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from agos.agents.heuristic.aerial import detect_vehicles_from_above, surface_heights
from agos.agents.heuristic.colour_match import TargetProfile
from agos.agents.heuristic.paint import shade_score
from agos.agents.heuristic.uav import ANNOTATE_SCORE
from agos.runtime.camera import intrinsics_for

ALTITUDE_M = 80.0
SIZE_PX = 512
INTR = intrinsics_for(SIZE_PX, SIZE_PX, 60.0)
# OpenCV camera looking down: image x along world +x, image y along world -y.
POSE = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, ALTITUDE_M], [0.0, 0.0, 0.0, 1.0]])
ASPHALT = (92, 92, 94)
SHADED_ASPHALT = tuple(int(c * s) for c, s in zip(ASPHALT, (0.52, 0.55, 0.64), strict=True))
RED = (209, 20, 18)
BLUE = (20, 71, 224)
NAVY = (15, 23, 107)
YELLOW = (242, 204, 20)


def profile(rgb: tuple[int, int, int], *, length_m: float = 4.6, width_m: float = 1.8, height_m: float = 1.4) -> TargetProfile:
    """A target profile as the references of a sunlit car of this paint would give it."""
    h, s, v = cv2.cvtColor(np.uint8([[rgb]]), cv2.COLOR_RGB2HSV)[0, 0].astype(float)
    return TargetProfile(hue=h, saturation=s, value_top=v, value_side=(0.5 * v, 0.9 * v), length_m=length_m,
                         width_m=width_m, paint_top_m=height_m, body_length_m=length_m, body_width_m=width_m,
                         body_height_m=height_m, paint_fraction=0.75)


class Street:
    """A nadir view under construction: RGB and ground-truth heights, rendered to depth."""

    def __init__(self) -> None:
        self.rgb = np.zeros((SIZE_PX, SIZE_PX, 3), np.uint8)
        self.rgb[:] = ASPHALT
        self.height = np.zeros((SIZE_PX, SIZE_PX), np.float32)

    @staticmethod
    def px(x_m: float, y_m: float, height_m: float = 0.0) -> tuple[int, int]:
        depth = ALTITUDE_M - height_m
        return (round(INTR.cx_px + x_m * INTR.fx_px / depth), round(INTR.cy_px - y_m * INTR.fy_px / depth))

    def box(self, x_m: float, y_m: float, length_m: float, width_m: float, colour, *, height_m: float = 0.0) -> None:
        """An axis-aligned rectangle (x along its length) at a height, seen from above."""
        u0, v0 = self.px(x_m - length_m / 2, y_m + width_m / 2, height_m)
        u1, v1 = self.px(x_m + length_m / 2, y_m - width_m / 2, height_m)
        self.rgb[v0:v1, u0:u1] = colour
        self.height[v0:v1, u0:u1] = height_m

    def car(self, x_m: float, y_m: float, colour, *, length_m: float = 4.6, width_m: float = 1.8,
            height_m: float = 1.4, shade_rear: bool = False) -> None:
        """A car: painted hood, roof and trunk, dark glass between; the rear half darkened by a
        building's shadow (vehicles keep hue and saturation in the shade) if asked."""
        self.box(x_m, y_m, length_m, width_m, colour, height_m=height_m)
        self.box(x_m + 0.5, y_m, 0.8, width_m * 0.85, (30, 34, 40), height_m=height_m)  # windscreen
        self.box(x_m - 1.1, y_m, 0.6, width_m * 0.85, (30, 34, 40), height_m=height_m)  # rear window
        if shade_rear:
            u0, v0 = self.px(x_m - length_m / 2 - 4.0, y_m + width_m / 2 + 4.0)
            u1, v1 = self.px(x_m, y_m - width_m / 2 - 4.0)
            self.rgb[v0:v1, u0:u1] = (self.rgb[v0:v1, u0:u1] * np.float32([0.62, 0.62, 0.62])).astype(np.uint8)
            ground = self.height[v0:v1, u0:u1] == 0
            self.rgb[v0:v1, u0:u1][ground] = SHADED_ASPHALT

    def view(self) -> tuple[np.ndarray, np.ndarray]:
        """JPEG-coded RGB and metric depth (z along the optical axis)."""
        ok, data = cv2.imencode(".jpg", cv2.cvtColor(self.rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 90])
        assert ok
        rgb = cv2.cvtColor(cv2.imdecode(data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        return rgb, (ALTITUDE_M - self.height).astype(np.float32)


def detect(street: Street, target: TargetProfile):
    rgb, depth = street.view()
    return detect_vehicles_from_above(rgb, depth, target, intrinsics=INTR, world_from_camera=POSE)


def test_heights_separate_standing_things_from_the_road_and_from_roofs() -> None:
    street = Street()
    street.car(0.0, 0.0, RED)
    street.box(-20.0, 15.0, 20.0, 20.0, (120, 110, 100), height_m=18.0)  # a building's roof
    _, depth = street.view()
    heights = surface_heights(depth, INTR, POSE)
    u, v = Street.px(0.0, 0.0, 1.4)
    assert heights.height_m[v, u] == pytest.approx(1.4, abs=0.05)
    ru, rv = Street.px(-20.0, 15.0, 18.0)
    assert heights.height_m[rv, ru] == pytest.approx(0.0, abs=0.05)  # a roof is a surface, not an object
    assert heights.base_above_floor_m[rv, ru] == pytest.approx(18.0, abs=0.1)
    assert heights.xyz_m[v, u, 0] == pytest.approx(0.0, abs=0.2) and heights.xyz_m[v, u, 1] == pytest.approx(0.0, abs=0.2)


def test_a_painted_car_half_in_shadow_is_found_with_its_size() -> None:
    street = Street()
    street.car(3.0, -2.0, RED, shade_rear=True)
    found = detect(street, profile(RED))
    assert len(found) == 1
    u, v = Street.px(3.0, -2.0, 1.4)
    assert abs(found[0].u_px - u) < 6 and abs(found[0].v_px - v) < 6
    assert found[0].length_m == pytest.approx(4.6, abs=0.5) and found[0].width_m == pytest.approx(1.8, abs=0.4)


def test_a_car_wholly_in_a_buildings_shadow_is_found() -> None:
    street = Street()
    street.car(0.0, 0.0, RED)
    u0, v0 = Street.px(-8.0, 6.0)
    u1, v1 = Street.px(8.0, -6.0)
    block = street.rgb[v0:v1, u0:u1]
    street.rgb[v0:v1, u0:u1] = (block * np.float32(0.62)).astype(np.uint8)
    street.rgb[v0:v1, u0:u1][street.height[v0:v1, u0:u1] == 0] = SHADED_ASPHALT
    rgb, depth = street.view()
    car = street.height > 1.0
    heights = surface_heights(depth, INTR, POSE)
    assert shade_score(car, rgb, heights.height_m, heights.xyz_m) > 0.8
    assert len(detect(street, profile(RED))) == 1


def test_yellow_lane_lines_and_a_flat_yellow_patch_are_not_vehicles() -> None:
    street = Street()
    street.box(0.0, 0.15, 60.0, 0.15, YELLOW)  # a double centre line
    street.box(0.0, -0.15, 60.0, 0.15, YELLOW)
    street.box(12.0, -8.0, 4.6, 1.8, YELLOW)  # car-sized paint on the road (a box junction's corner)
    assert detect(street, profile(YELLOW)) == []


def test_a_brick_wall_and_a_red_roof_of_the_targets_hue_are_not_vehicles() -> None:
    street = Street()
    brick = (178, 52, 40)
    # A wall seen off-nadir: a band of brick whose pixels rise from the street to the roof.
    u0, _ = Street.px(-30.0, 0.0)
    for i in range(40):
        street.rgb[60:400, u0 + i] = brick if i % 6 else (150, 140, 130)  # mortar courses
        street.height[60:400, u0 + i] = 18.0 * i / 39
    street.box(15.0, 10.0, 12.0, 9.0, brick, height_m=9.0)  # a brick-red roof
    target = profile((200, 48, 36))
    assert detect(street, target) == []


def test_size_and_height_rank_the_target_above_a_look_alike_of_another_body() -> None:
    street = Street()
    street.car(-10.0, 0.0, BLUE, length_m=4.6, width_m=1.8, height_m=1.4)
    street.car(10.0, 0.0, BLUE, length_m=7.4, width_m=2.4, height_m=3.3)  # a box truck of the same paint
    found = detect(street, profile(BLUE))
    assert found and found[0].u_px < SIZE_PX / 2
    assert all(d.u_px < SIZE_PX / 2 for d in found)


def test_a_sunlit_navy_car_ranks_below_a_sunlit_blue_target() -> None:
    street = Street()
    street.car(-10.0, 0.0, NAVY)
    street.car(10.0, 0.0, BLUE)
    found = detect(street, profile(BLUE))
    assert found and found[0].u_px > SIZE_PX / 2


def test_the_side_references_top_ranks_a_body_of_another_height_below_the_annotation_score() -> None:
    """Against the side reference's outline top (``top_m``) the height counts in metres: an SUV
    (1.8 m) for a van (2.1 m) of the same paint and length scores below what the heuristic UAV
    annotates during its first sweep, the van itself well above; without it both rank alike."""
    street = Street()
    street.car(-10.0, 0.0, BLUE, length_m=5.2, width_m=2.0, height_m=2.1)  # the van
    street.car(10.0, 0.0, BLUE, length_m=5.2, width_m=2.0, height_m=1.8)  # an SUV-high body
    van = profile(BLUE, length_m=5.2, width_m=2.0, height_m=2.1)
    rgb, depth = street.view()
    strict = detect_vehicles_from_above(rgb, depth, van, intrinsics=INTR, world_from_camera=POSE, top_m=2.1)
    by_side = {d.u_px < SIZE_PX / 2: d.score for d in strict}
    assert by_side[True] >= ANNOTATE_SCORE > by_side.get(False, 0.0)
    loose = {d.u_px < SIZE_PX / 2: d.score for d in detect(street, van)}
    assert loose[False] >= ANNOTATE_SCORE  # the relative height alone let the lower body through
