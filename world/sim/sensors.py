"""Cameras of the UAV and UGV, their intrinsics and poses, the grid overlay and reference views.

Camera frames follow OpenCV (x right, y down, z forward). The UAV's nadir camera looks straight
down (pitch -90 deg) with image up = world +y (north). UGV cameras sit 1.7 m above the road;
the six STOP_OBSERVE views are at yaw offsets of +60 (front-left), 0, -60 (front-right),
+120 (back-left), 180 and -120 (back-right) degrees from the heading, 70 deg wide each, so
neighbouring views overlap by 10 deg.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from agos.runtime.camera import (  # noqa: F401 - re-exported: sensors is where callers look for them
    GRID_COLS,
    GRID_ROWS,
    _pose,
    cell_of_pixel,
    cell_polygon_world,
    footprint_world,
    ground_to_pixel,
    intrinsics_for,
    parse_cell,
    pixel_to_ground,
)
from agos.runtime.codec import encode_jpeg, encode_png
from agos.runtime.episode_config import CameraConfig
from agos.runtime.schemas import CameraIntrinsics, ImageFrame
from agos.world.sim.scene import STUDIO_OFFSET_M, RenderResult, Scene

UGV_CAMERA_HEIGHT_M = 1.7
SIX_VIEWS: tuple[tuple[str, float], ...] = (
    ("front_left", 60.0), ("front", 0.0), ("front_right", -60.0),
    ("back_left", 120.0), ("back", 180.0), ("back_right", -120.0),
)
DEPTH_SCALE_M = 0.005
"""Depth PNGs store uint16 units of 5 mm (0 to 327 m)."""



@dataclass
class Shot:
    """A rendered view and the camera that took it."""

    name: str
    render: RenderResult
    intrinsics: CameraIntrinsics
    world_from_camera: np.ndarray
    """4x4 camera pose, OpenCV axes."""


def shoot(scene: Scene, name: str, eye: np.ndarray, forward: np.ndarray, up: np.ndarray,
          fov_deg: float, size_px: int) -> Shot:
    render = scene.render(eye, forward, up, fov_deg=fov_deg, width_px=size_px, height_px=size_px)
    return Shot(name, render, intrinsics_for(size_px, size_px, fov_deg), _pose(eye, forward, up))


def nadir(scene: Scene, xy: tuple[float, float], altitude_m: float, cam: CameraConfig) -> Shot:
    # A hair above the nominal altitude: a camera level with mesh vertices can drop geometry.
    eye = np.array([xy[0], xy[1], altitude_m + 0.013])
    return shoot(scene, "nadir", eye, np.array([0.0, 0.0, -1.0]), np.array([0.0, 1.0, 0.0]),
                 cam.nadir_fov_deg, cam.nadir_px)


def ground_view(scene: Scene, name: str, xy: tuple[float, float], yaw_rad: float,
                cam: CameraConfig) -> Shot:
    eye = np.array([xy[0], xy[1], UGV_CAMERA_HEIGHT_M])
    forward = np.array([math.cos(yaw_rad), math.sin(yaw_rad), -0.05])
    return shoot(scene, name, eye, forward, np.array([0.0, 0.0, 1.0]), cam.ground_fov_deg, cam.ground_px)


def six_views(scene: Scene, xy: tuple[float, float], heading_rad: float, cam: CameraConfig) -> list[Shot]:
    return [ground_view(scene, name, xy, heading_rad + math.radians(offset), cam)
            for name, offset in SIX_VIEWS]


def target_pixels(shot: Shot, target_uid: int) -> int:
    """Visibility oracle: pixels of the target's instance in a view (never shown to agents)."""
    return int(np.count_nonzero(shot.render.instance == target_uid))


def grid_overlay(rgb: np.ndarray) -> np.ndarray:
    """The nadir image with the 5x5 grid drawn and each cell labelled A1 (top-left) ... E5."""
    out = rgb.copy()
    h, w = out.shape[:2]
    for k in range(1, GRID_COLS):
        x = round(k * w / GRID_COLS)
        cv2.line(out, (x, 0), (x, h - 1), (255, 255, 0), 1)
    for k in range(1, len(GRID_ROWS)):
        y = round(k * h / len(GRID_ROWS))
        cv2.line(out, (0, y), (w - 1, y), (255, 255, 0), 1)
    for r, row in enumerate(GRID_ROWS):
        for c in range(GRID_COLS):
            org = (round(c * w / GRID_COLS) + 3, round(r * h / len(GRID_ROWS)) + 14)
            cv2.putText(out, f"{row}{c + 1}", org, cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
            cv2.putText(out, f"{row}{c + 1}", org, cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 0), 1, cv2.LINE_AA)
    return out


def reference_views(scene: Scene, uid: int, position_world_m: tuple[float, float, float], yaw_rad: float,
                    cam: CameraConfig) -> list[ImageFrame]:
    """Render the target alone, in the studio far from the town, from above and from four
    ground-level sides; the background is removed (black RGB, alpha 0 in the PNG)."""
    scene.move(uid, np.asarray(STUDIO_OFFSET_M))
    try:
        centre = np.asarray(position_world_m) + STUDIO_OFFSET_M
        views = [top_view_camera("ref_top", centre, yaw_rad)]
        # Side views from the UGV camera height, so painted heights compare with ground views.
        for name, off in (("ref_front_left", 35.0), ("ref_side", 90.0), ("ref_rear", 180.0 - 35.0),
                          ("ref_front", 0.0)):
            a = yaw_rad + math.radians(off)
            dist = 11.0
            eye = centre + [dist * math.cos(a), dist * math.sin(a), UGV_CAMERA_HEIGHT_M]
            views.append((name, eye, centre + [0, 0, 1.0] - eye, np.array([0.0, 0.0, 1.0]), 40.0, dist))
        return [isolated_view(scene, uid, view, centre, yaw_rad, cam.reference_px) for view in views]
    finally:
        scene.move(uid, -np.asarray(STUDIO_OFFSET_M))


IsolatedCamera = tuple[str, np.ndarray, np.ndarray, np.ndarray, float, float]
"""(frame name, eye, forward, up, horizontal FOV in degrees, distance to the object in metres)."""

TOP_VIEW_HEIGHT_M, TOP_VIEW_FOV_DEG = 150.0, 4.0
"""The reference top view: high and narrow, nearly orthographic, so roof height does not change scale."""


def top_view_camera(name: str, centre: np.ndarray, yaw_rad: float) -> IsolatedCamera:
    """A camera straight above ``centre`` with image up along the vehicle's heading ``yaw_rad``."""
    return (name, centre + [0, 0, TOP_VIEW_HEIGHT_M], np.array([0.0, 0.0, -1.0]),
            np.array([math.cos(yaw_rad), math.sin(yaw_rad), 0.0]), TOP_VIEW_FOV_DEG, TOP_VIEW_HEIGHT_M)


def isolated_view(scene: Scene, uid: int, camera: IsolatedCamera, centre: np.ndarray, yaw_rad: float,
                  size: int) -> ImageFrame:
    """One view of the body ``uid`` alone (every other pixel black, alpha 0 in the PNG) as a frame with
    its camera pose in the vehicle's frame (origin on the road under its centre, x forward) and the
    metres per pixel at the object's distance."""
    name, eye, forward, up, fov, dist = camera
    shot = shoot(scene, name, eye, forward, up, fov, size)
    mask = shot.render.instance == uid
    rgba = np.zeros((size, size, 4), np.uint8)
    rgba[mask, :3] = shot.render.rgb[mask]
    rgba[mask, 3] = 255
    object_from_world = _object_frame(centre, yaw_rad)
    return ImageFrame(
        name=name, kind="rgb", encoding="png", data=encode_png(rgba), intrinsics=shot.intrinsics,
        world_from_camera=(object_from_world @ shot.world_from_camera).flatten().tolist(),
        metres_per_px=2 * dist * math.tan(math.radians(fov) / 2) / size)


def _object_frame(centre: np.ndarray, yaw_rad: float) -> np.ndarray:
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    world_from_object = np.array([[c, -s, 0, centre[0]], [s, c, 0, centre[1]], [0, 0, 1, centre[2]], [0, 0, 0, 1]])
    return np.linalg.inv(world_from_object)


def frames_of(shot: Shot, scene: Scene, cam: CameraConfig, *, with_grid: bool = False,
              semantic: bool = True) -> list[ImageFrame]:
    """Encode a shot as wire frames: RGB (and the grid-overlay RGB), depth PNG, semantic PNG."""
    pose = shot.world_from_camera.flatten().tolist()
    rgb_bytes = encode_jpeg(shot.render.rgb) if cam.rgb_encoding == "jpeg" else encode_png(shot.render.rgb)
    frames = [ImageFrame(name=shot.name, kind="rgb", encoding=cam.rgb_encoding, data=rgb_bytes,
                         intrinsics=shot.intrinsics, world_from_camera=pose)]
    if with_grid:
        grid = grid_overlay(shot.render.rgb)
        data = encode_jpeg(grid) if cam.rgb_encoding == "jpeg" else encode_png(grid)
        frames.append(ImageFrame(name=shot.name, kind="rgb_grid", encoding=cam.rgb_encoding, data=data,
                                 intrinsics=shot.intrinsics, world_from_camera=pose))
    depth = np.clip(shot.render.depth_m / DEPTH_SCALE_M, 0, 65535).astype(np.uint16)
    frames.append(ImageFrame(name=shot.name, kind="depth", encoding="png", data=encode_png(depth),
                             intrinsics=shot.intrinsics, world_from_camera=pose, depth_scale_m=DEPTH_SCALE_M))
    if semantic:
        frames.append(ImageFrame(name=shot.name, kind="semantic", encoding="png",
                                 data=encode_png(scene.semantic(shot.render.instance)),
                                 intrinsics=shot.intrinsics, world_from_camera=pose))
    return frames
