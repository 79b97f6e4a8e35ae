"""Camera geometry shared by the world and the agents (pure numpy; no PyBullet).

Frames follow OpenCV (x right, y down, z forward). A nadir image is split into a 5 x 5 grid,
cells ``A1`` (top-left) to ``E5``; Ego-to-Allo projection maps a cell to the ground plane.
"""

from __future__ import annotations

import math

import numpy as np

from agos.runtime.schemas import CameraIntrinsics

GRID_ROWS = "ABCDE"
GRID_COLS = 5


def intrinsics_for(width_px: int, height_px: int, fov_deg: float) -> CameraIntrinsics:
    """Pinhole intrinsics of a camera with vertical field of view ``fov_deg``."""
    f = (height_px / 2) / math.tan(math.radians(fov_deg) / 2)
    return CameraIntrinsics(width_px=width_px, height_px=height_px, fx_px=f, fy_px=f,
                            cx_px=width_px / 2, cy_px=height_px / 2)


def _pose(eye: np.ndarray, forward: np.ndarray, up: np.ndarray) -> np.ndarray:
    z = forward / np.linalg.norm(forward)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, eye
    return pose


def cell_polygon_world(cell: str, shot_pose: np.ndarray, intr: CameraIntrinsics,
                       ground_z_m: float = 0.0) -> list[tuple[float, float]]:
    """Ego-to-Allo projection: the ground-plane polygon seen by grid cell ``cell`` of a nadir
    image taken from ``shot_pose`` (corners in image order: top-left, top-right, bottom-right,
    bottom-left)."""
    row, col = parse_cell(cell)
    u0, u1 = col * intr.width_px / GRID_COLS, (col + 1) * intr.width_px / GRID_COLS
    v0, v1 = row * intr.height_px / len(GRID_ROWS), (row + 1) * intr.height_px / len(GRID_ROWS)
    return [pixel_to_ground(u, v, shot_pose, intr, ground_z_m) for u, v in ((u0, v0), (u1, v0), (u1, v1), (u0, v1))]


def footprint_world(shot_pose: np.ndarray, intr: CameraIntrinsics, ground_z_m: float = 0.0) -> list[tuple[float, float]]:
    """The whole nadir view on the ground (corners: top-left, top-right, bottom-right, bottom-left)."""
    w, h = intr.width_px, intr.height_px
    return [pixel_to_ground(u, v, shot_pose, intr, ground_z_m) for u, v in ((0, 0), (w, 0), (w, h), (0, h))]


def pixel_to_ground(u: float, v: float, world_from_camera: np.ndarray, intr: CameraIntrinsics,
                    ground_z_m: float = 0.0) -> tuple[float, float]:
    """Intersect the ray through pixel (u, v) with the plane z = ground_z_m."""
    ray_cam = np.array([(u - intr.cx_px) / intr.fx_px, (v - intr.cy_px) / intr.fy_px, 1.0])
    ray = world_from_camera[:3, :3] @ ray_cam
    eye = world_from_camera[:3, 3]
    if abs(ray[2]) < 1e-9 or (ground_z_m - eye[2]) / ray[2] <= 0:
        raise ValueError(f"pixel ({u:.0f}, {v:.0f}) does not look at the ground plane")
    t = (ground_z_m - eye[2]) / ray[2]
    p = eye + t * ray
    return (float(p[0]), float(p[1]))


def depth_to_world(depth_m: np.ndarray, intr: CameraIntrinsics, world_from_camera: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 world points of a metric depth image (z along the optical axis, OpenCV
    camera: x right, y down)."""
    h, w = depth_m.shape
    us, vs = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    z = depth_m.astype(np.float32)
    cam = np.stack([(us - intr.cx_px) / intr.fx_px * z, (vs - intr.cy_px) / intr.fy_px * z, z], -1)
    pose = np.asarray(world_from_camera, dtype=np.float32).reshape(4, 4)
    return cam @ pose[:3, :3].T + pose[:3, 3]


def parse_cell(cell: str) -> tuple[int, int]:
    """``"C4"`` -> (row 2, col 3); raises ValueError for anything else."""
    if (len(cell) != 2 or cell[0].upper() not in GRID_ROWS or not cell[1].isdigit()
            or not 1 <= int(cell[1]) <= GRID_COLS):
        raise ValueError(f"grid cell {cell!r} is not one of A1..E5")
    return GRID_ROWS.index(cell[0].upper()), int(cell[1]) - 1


def cell_of_pixel(u: float, v: float, width_px: int, height_px: int) -> str:
    col = min(GRID_COLS - 1, max(0, int(u * GRID_COLS / width_px)))
    row = min(len(GRID_ROWS) - 1, max(0, int(v * len(GRID_ROWS) / height_px)))
    return f"{GRID_ROWS[row]}{col + 1}"


def ground_to_pixel(xy: tuple[float, float], world_from_camera: np.ndarray, intr: CameraIntrinsics,
                    ground_z_m: float = 0.0) -> tuple[float, float] | None:
    """Pixel of a ground point, or None when it is behind the camera."""
    p = np.linalg.inv(world_from_camera) @ np.array([xy[0], xy[1], ground_z_m, 1.0])
    if p[2] <= 0:
        return None
    return float(intr.fx_px * p[0] / p[2] + intr.cx_px), float(intr.fy_px * p[1] / p[2] + intr.cy_px)
