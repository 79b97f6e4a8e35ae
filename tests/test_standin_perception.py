"""The VLM stand-in's eyes (agents/vlm/standin/perception.py) on synthetic views without depth:
the heuristic's detection fed with what a VLM request carries, never colour alone.

From above: a straight-down camera 80 m over a flat street and a reference top view of the target
(RGBA, nose up, 0.0655 m per pixel, as the world renders it); from the ground: a camera 1.7 m up
looking along +x at a vehicle seen broadside. Every image goes through JPEG as agents get it.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from agos.agents.heuristic.colour_match import TargetProfile
from agos.agents.vlm import protocol
from agos.agents.vlm.agos_prompts import uav_prompt, ugv_prompt
from agos.agents.vlm.request import Memory
from agos.agents.vlm.standin import brain
from agos.agents.vlm.standin.perception import (
    PaintBottom,
    aerial_metres_per_px,
    detect_from_above_rgb,
    find_target_rgb,
    ground_view_from_rgb,
    top_template,
)
from agos.runtime.camera import intrinsics_for, pixel_to_ground

ALTITUDE_M = 80.0
AERIAL_PX = 512
AERIAL = intrinsics_for(AERIAL_PX, AERIAL_PX, 60.0)
# OpenCV camera looking down: image x along world +x, image y along world -y.
DOWN = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, ALTITUDE_M], [0.0, 0.0, 0.0, 1.0]])
REF_M_PER_PX = 0.0655
ASPHALT = (92, 92, 94)
GLASS = (30, 34, 40)
BLUE = (20, 71, 224)
NAVY = (15, 23, 107)
SKY = (170, 200, 235)


def jpeg(rgb: np.ndarray) -> np.ndarray:
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(rgb.astype(np.uint8), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    return cv2.cvtColor(cv2.imdecode(data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def profile(rgb: tuple[int, int, int], *, length_m: float = 4.6, width_m: float = 1.8, height_m: float = 1.4) -> TargetProfile:
    """What the references of a sunlit vehicle of this paint and size would give."""
    h, s, v = cv2.cvtColor(np.uint8([[rgb]]), cv2.COLOR_RGB2HSV)[0, 0].astype(float)
    return TargetProfile(hue=h, saturation=s, value_top=v, value_side=(0.8 * v, v), length_m=length_m, width_m=width_m,
                         paint_top_m=height_m, body_length_m=length_m, body_width_m=width_m, body_height_m=height_m,
                         paint_fraction=0.75)


def reference_top(colour, *, length_m: float = 4.6, width_m: float = 1.8) -> np.ndarray:
    """A car's top reference: paint with a windscreen and a rear window, nose up, background transparent."""
    ref = np.zeros((160, 160, 4), np.uint8)

    nose = 80 - length_m / 2 / REF_M_PER_PX

    def rect(y0_m: float, y1_m: float, half_w_m: float, rgb) -> None:  # y measured from the nose, downwards
        v0, v1 = round(nose + y0_m / REF_M_PER_PX), round(nose + y1_m / REF_M_PER_PX)
        u0, u1 = round(80 - half_w_m / REF_M_PER_PX), round(80 + half_w_m / REF_M_PER_PX)
        ref[v0:v1, u0:u1, :3] = rgb
        ref[v0:v1, u0:u1, 3] = 255

    rect(0.0, length_m, width_m / 2, colour)
    rect(1.3, 2.1, 0.85 * width_m / 2, GLASS)
    rect(length_m - 1.3, length_m - 0.7, 0.85 * width_m / 2, GLASS)
    return ref


class Street:
    """A nadir view under construction (RGB only: the stand-in gets no depth)."""

    def __init__(self) -> None:
        self.rgb = np.zeros((AERIAL_PX, AERIAL_PX, 3), np.uint8)
        self.rgb[:] = ASPHALT

    @staticmethod
    def px(x_m: float, y_m: float, height_m: float = 1.4) -> tuple[int, int]:
        depth = ALTITUDE_M - height_m
        return round(AERIAL.cx_px + x_m * AERIAL.fx_px / depth), round(AERIAL.cy_px - y_m * AERIAL.fy_px / depth)

    def box(self, x_m: float, y_m: float, length_m: float, width_m: float, colour) -> None:
        u0, v0 = self.px(x_m - length_m / 2, y_m + width_m / 2)
        u1, v1 = self.px(x_m + length_m / 2, y_m - width_m / 2)
        self.rgb[v0:v1, u0:u1] = colour

    def car(self, x_m: float, y_m: float, colour, *, length_m: float = 4.6, width_m: float = 1.8) -> None:
        """A car nosing towards +x: paint, a windscreen and a rear window, as the reference has them."""
        self.box(x_m, y_m, length_m, width_m, colour)
        self.box(x_m + length_m / 2 - 1.7, y_m, 0.8, 0.85 * width_m, GLASS)
        self.box(x_m - length_m / 2 + 1.0, y_m, 0.6, 0.85 * width_m, GLASS)

    def detect(self, target: TargetProfile, ref: np.ndarray):
        template = top_template(ref, REF_M_PER_PX, aerial_metres_per_px(ALTITUDE_M, AERIAL, target), target)
        assert template is not None
        return detect_from_above_rgb(jpeg(self.rgb), target, template, intrinsics=AERIAL, world_from_camera=DOWN)


def ground_xy(detection) -> tuple[float, float]:
    return pixel_to_ground(detection.u_px, detection.v_px, DOWN, AERIAL)


def test_from_above_the_target_is_found_where_it_stands() -> None:
    street = Street()
    street.car(6.0, -3.0, BLUE)
    found = street.detect(profile(BLUE), reference_top(BLUE))
    assert found, "the target, whole and in the sun, is detected"
    x, y = ground_xy(found[0])
    assert abs(x - 6.0) < 1.0 and abs(y + 3.0) < 1.0
    assert found[0].length_m == pytest.approx(4.6, abs=0.6) and found[0].width_m == pytest.approx(1.8, abs=0.5)


def test_from_above_a_same_paint_vehicle_of_another_size_is_not_the_target() -> None:
    """Paint alone would take the truck or the van: their paint is the target's, their silhouettes
    are not. The truck is no detection at all; the van, 0.7 m longer and without the car's glass,
    ranks below the target and below the bar of a clear match."""
    street = Street()
    street.car(-12.0, 0.0, BLUE)
    street.box(12.0, 0.0, 7.4, 2.4, BLUE)  # a box truck's roof in the target's paint
    street.box(0.0, 12.0, 5.3, 2.1, BLUE)  # a van's roof
    found = street.detect(profile(BLUE), reference_top(BLUE))
    assert found and abs(ground_xy(found[0])[0] + 12.0) < 1.0 and abs(ground_xy(found[0])[1]) < 1.0
    others = found[1:]
    assert all(ground_xy(d)[0] < 5.0 for d in others), "nothing is found on the truck"
    assert all(d.score < brain.CLEAR_MATCH for d in others)


def test_from_above_a_near_paint_is_not_the_target() -> None:
    street = Street()
    street.car(-10.0, 5.0, NAVY)  # the target's body in navy: blue is not navy, in the sun or in shade
    street.car(10.0, -5.0, (11, 16, 75))
    assert street.detect(profile(BLUE), reference_top(BLUE)) == []


EYE_M = 1.7
GROUND_PX = 256
GROUND = intrinsics_for(GROUND_PX, GROUND_PX, 70.0)
# OpenCV camera: x right (world -y), y down (world -z), z forward (world +x).
LEVEL = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, EYE_M], [0.0, 0.0, 0.0, 1.0]])
SILL = PaintBottom(0.3, 0.25, 0.35)


def broadside(colour, *, distance_m: float = 10.0, length_m: float, height_m: float, width_m: float = 1.8) -> np.ndarray:
    """A vehicle across the view, its near face ``distance_m`` ahead, painted from its 0.3 m sill to
    ``height_m``; its roof when lower than the camera. RGB only."""
    us, vs = np.meshgrid(np.arange(GROUND_PX) + 0.5, np.arange(GROUND_PX) + 0.5)
    a, b = (us - GROUND.cx_px) / GROUND.fx_px, (vs - GROUND.cy_px) / GROUND.fy_px
    rgb = np.zeros((GROUND_PX, GROUND_PX, 3), np.float32)
    rgb[:] = SKY
    rgb[b > 0] = ASPHALT
    z_face, y_face = EYE_M - b * distance_m, -a * distance_m
    rgb[(z_face >= 0.3) & (z_face <= height_m) & (np.abs(y_face) <= length_m / 2)] = colour
    if height_m < EYE_M:
        t_roof = (EYE_M - height_m) / np.maximum(b, 1e-6)
        rgb[(b > 0) & (t_roof > distance_m) & (t_roof < distance_m + width_m) & (np.abs(a * t_roof) <= length_m / 2)] = colour
    return jpeg(rgb)


def find(rgb: np.ndarray, target: TargetProfile):
    view = ground_view_from_rgb("front", rgb, target, intrinsics=GROUND, world_from_camera=LEVEL, bottom=SILL)
    return find_target_rgb([view], target, min_pixels=40)


def test_from_the_ground_the_target_stands_at_its_painted_height_and_place() -> None:
    """Where the paint meets the road gives the distance without a depth image."""
    found = find(broadside(BLUE, length_m=3.9, height_m=1.52), profile(BLUE, length_m=3.9, height_m=1.52))
    assert len(found) == 1
    assert found[0].top_m == pytest.approx(1.52, abs=0.12) and found[0].distance_m == pytest.approx(10.0, abs=1.0)
    assert abs(found[0].y_m) < 0.5


def test_from_the_ground_a_same_paint_vehicle_of_another_height_is_not_the_target() -> None:
    target = profile(BLUE, length_m=3.9, height_m=1.52)
    assert find(broadside(BLUE, length_m=3.9, height_m=2.1), target) == []  # a van's height
    assert find(broadside(BLUE, length_m=3.9, height_m=1.2), target) == []  # a lower body


def test_the_stand_in_answers_the_same_request_the_same_way(observations) -> None:
    """Deterministic: a request answered twice, and again with the reference cache emptied, gets
    the same reply; every reply's action is one the state allows."""
    uav = next(o for o in observations if o.role == "uav")
    six = next(o for o in observations if o.role == "ugv" and o.mode == "stop_6view")
    for request in (protocol.split_request(uav_prompt(uav, Memory()).messages()),
                    protocol.split_request(ugv_prompt(six, Memory()).messages())):
        first = brain.respond(request)
        assert brain.respond(request) == first
        brain._references.clear()
        assert brain.respond(request) == first
        assert request.state is not None and first["action"] in request.state["legal_actions"]
