"""Pure camera helpers of agos/world/sensors.py (no rendering)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agos.world.sim import sensors
from agos.world.sim.sensors import (
    GRID_ROWS,
    cell_of_pixel,
    cell_polygon_world,
    grid_overlay,
    intrinsics_for,
    parse_cell,
    pixel_to_ground,
)

EYE = np.array([10.0, 20.0, 80.0])
DOWN = np.array([0.0, 0.0, -1.0])
NORTH = np.array([0.0, 1.0, 0.0])
INTR = intrinsics_for(512, 512, 60.0)
HALF = 80.0 * math.tan(math.radians(30.0))  # half the ground footprint of the nadir view (46.19 m)


def _nadir_pose(eye: np.ndarray = EYE, up: np.ndarray = NORTH) -> np.ndarray:
    return sensors._pose(eye, forward=DOWN, up=up)


def _approx_points(points, expected, abs_tol: float = 1e-9) -> None:
    assert len(points) == len(expected)
    for p, e in zip(points, expected, strict=True):
        assert p == pytest.approx(e, abs=abs_tol)


# --- intrinsics ----------------------------------------------------------------------------------


def test_intrinsics_square() -> None:
    f = 256.0 / math.tan(math.radians(30.0))
    assert INTR.fx_px == pytest.approx(f)
    assert INTR.fy_px == pytest.approx(f)
    assert INTR.fx_px == pytest.approx(443.4050067376326)
    assert (INTR.width_px, INTR.height_px) == (512, 512)
    assert (INTR.cx_px, INTR.cy_px) == (256.0, 256.0)


def test_intrinsics_use_vertical_fov() -> None:
    intr = intrinsics_for(640, 480, 90.0)
    assert intr.fx_px == pytest.approx(240.0)  # (480 / 2) / tan(45 deg)
    assert intr.fy_px == pytest.approx(240.0)
    assert (intr.cx_px, intr.cy_px) == (320.0, 240.0)
    assert (intr.width_px, intr.height_px) == (640, 480)


# --- grid cells ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("cell", "expected"),
    [("A1", (0, 0)), ("E5", (4, 4)), ("C4", (2, 3)), ("B1", (1, 0)), ("A5", (0, 4)), ("c3", (2, 2))],
)
def test_parse_cell(cell: str, expected) -> None:
    assert parse_cell(cell) == expected


@pytest.mark.parametrize("bad", ["F1", "A6", "A0", "A", "11", "", "AA", "A11", "E55", " A1", "Z9", "1A"])
def test_parse_cell_rejects(bad: str) -> None:
    with pytest.raises(ValueError, match=r"A1\.\.E5"):
        parse_cell(bad)


@pytest.mark.parametrize(
    ("u", "v", "expected"),
    [
        (0, 0, "A1"),
        (511, 0, "A5"),
        (0, 511, "E1"),
        (511, 511, "E5"),
        (512, 512, "E5"),  # the far edge is clamped into the last cell
        (-3, -3, "A1"),
        (256, 256, "C3"),
        (102.39, 0, "A1"),
        (102.4, 0, "A2"),  # cells are 512 / 5 = 102.4 px wide
        (0, 409.6, "E1"),
        (0, 409.5, "D1"),
    ],
)
def test_cell_of_pixel(u, v, expected: str) -> None:
    assert cell_of_pixel(u, v, 512, 512) == expected


def test_cell_of_pixel_matches_parse_cell() -> None:
    for r, row in enumerate(GRID_ROWS):
        for c in range(5):
            u, v = (c + 0.5) * 640 / 5, (r + 0.5) * 480 / 5
            cell = cell_of_pixel(u, v, 640, 480)
            assert cell == f"{row}{c + 1}"
            assert parse_cell(cell) == (r, c)


# --- poses and ground projection -----------------------------------------------------------------


def test_nadir_pose_axes() -> None:
    pose = _nadir_pose()
    np.testing.assert_allclose(pose[:3, 0], [1.0, 0.0, 0.0])  # image right = east
    np.testing.assert_allclose(pose[:3, 1], [0.0, -1.0, 0.0])  # image down = south
    np.testing.assert_allclose(pose[:3, 2], [0.0, 0.0, -1.0])  # looking down
    np.testing.assert_allclose(pose[:3, 3], EYE)
    np.testing.assert_allclose(pose[3], [0.0, 0.0, 0.0, 1.0])


def test_image_centre_projects_below_camera() -> None:
    assert pixel_to_ground(256.0, 256.0, _nadir_pose(), INTR) == pytest.approx((10.0, 20.0))


@pytest.mark.parametrize(
    ("u", "v", "expected"),
    [
        (0.0, 0.0, (10.0 - HALF, 20.0 + HALF)),  # top-left = north-west
        (512.0, 0.0, (10.0 + HALF, 20.0 + HALF)),  # top-right = north-east
        (512.0, 512.0, (10.0 + HALF, 20.0 - HALF)),
        (0.0, 512.0, (10.0 - HALF, 20.0 - HALF)),
        (384.0, 256.0, (10.0 + HALF / 2, 20.0)),
    ],
)
def test_corners_project_hand_computed(u, v, expected) -> None:
    assert pixel_to_ground(u, v, _nadir_pose(), INTR) == pytest.approx(expected)


def test_ground_plane_height() -> None:
    # a ground plane 5 m up is 75 m below the camera
    half = 75.0 * math.tan(math.radians(30.0))
    assert pixel_to_ground(0.0, 0.0, _nadir_pose(), INTR, ground_z_m=5.0) == pytest.approx(
        (10.0 - half, 20.0 + half))


def test_rotated_nadir_camera() -> None:
    # image up = world +x: the top edge of the image looks east, image right looks south
    pose = _nadir_pose(up=np.array([1.0, 0.0, 0.0]))
    assert pixel_to_ground(256.0, 0.0, pose, INTR) == pytest.approx((10.0 + HALF, 20.0))
    assert pixel_to_ground(512.0, 256.0, pose, INTR) == pytest.approx((10.0, 20.0 - HALF))


def test_forward_camera_centre_ray() -> None:
    # 1.7 m high, looking along +x with a 1:20 downward slope: the centre ray meets the road 34 m ahead
    pose = sensors._pose(np.array([0.0, 0.0, 1.7]), np.array([1.0, 0.0, -0.05]), np.array([0.0, 0.0, 1.0]))
    intr = intrinsics_for(256, 256, 70.0)
    assert pixel_to_ground(128.0, 128.0, pose, intr) == pytest.approx((34.0, 0.0))


def test_cell_polygon_centre_cell() -> None:
    side = 2 * 80.0 * math.tan(math.radians(30.0)) / 5
    s = side / 2
    polygon = cell_polygon_world("C3", _nadir_pose(), INTR)
    # image order: top-left, top-right, bottom-right, bottom-left (image up = north)
    _approx_points(polygon, [(10.0 - s, 20.0 + s), (10.0 + s, 20.0 + s), (10.0 + s, 20.0 - s),
                             (10.0 - s, 20.0 - s)])
    assert side == pytest.approx(18.475208614068)


def test_cell_polygon_corner_cells() -> None:
    side = 2 * HALF / 5
    a1 = cell_polygon_world("A1", _nadir_pose(), INTR)
    _approx_points(a1, [(10.0 - HALF, 20.0 + HALF), (10.0 - HALF + side, 20.0 + HALF),
                        (10.0 - HALF + side, 20.0 + HALF - side), (10.0 - HALF, 20.0 + HALF - side)])
    e5 = cell_polygon_world("E5", _nadir_pose(), INTR)
    assert e5[2] == pytest.approx((10.0 + HALF, 20.0 - HALF))
    b4 = cell_polygon_world("B4", _nadir_pose(), INTR)  # row 1 (second from the north), column 3
    assert b4[0] == pytest.approx((10.0 - HALF + 3 * side, 20.0 + HALF - side))


def test_cell_polygon_rejects_bad_cell() -> None:
    with pytest.raises(ValueError):
        cell_polygon_world("F1", _nadir_pose(), INTR)


# --- grid overlay --------------------------------------------------------------------------------


def test_grid_overlay_draws_lines_without_touching_input() -> None:
    image = np.zeros((100, 100, 3), np.uint8)
    out = grid_overlay(image)
    assert not image.any()
    assert out.shape == image.shape
    for x in (20, 40, 60, 80):
        assert out[99, x].tolist() == [255, 255, 0]  # bottom row, clear of the labels
    for y in (20, 40, 60, 80):
        assert out[y, 99].tolist() == [255, 255, 0]
    assert out[99, 30].tolist() == [0, 0, 0]
