"""Vehicles built of boxes, ray-cast in numpy: the target's reference views as the world makes them
(background removed, camera posed in the vehicle's frame) and a UGV's ground view with metric
depth, for tests of the heuristic's judges without a simulator.

A vehicle is a list of :class:`Part` boxes in its own frame (x forward, y left, z up, metres,
origin on the road under its centre). Faces are lit by their direction (tops brightest, as the
world's sun), every image goes through JPEG as agents get it (references stay PNG).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from agos.agents.heuristic.ground import GroundView
from agos.runtime.camera import intrinsics_for
from agos.runtime.codec import encode_png
from agos.runtime.schemas import CameraIntrinsics, ImageFrame

GLASS = (23, 28, 36)
GREY_BOX = (128, 130, 135)
DARK = (13, 13, 13)
ASPHALT = (92, 92, 94)
SKY = (170, 200, 235)
EYE_M = 1.7
"""The UGV's camera height, also the side references'."""
LIGHT = {"top": 1.0, "x": 0.85, "y": 0.75}
"""Brightness of faces facing up, along x and along y."""


@dataclass(frozen=True)
class Part:
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    rgb: tuple[int, int, int]


def car(paint: tuple[int, int, int], *, length_m: float, width_m: float, height_m: float,
        roof_box: bool = False, cabin_share: float = 0.5) -> list[Part]:
    """A car: a painted lower body to 0.9 m, a painted cabin over the middle ``cabin_share`` of its
    length to ``height_m`` with glass on its sides, ends and top edge band; ``roof_box``: a grey
    cargo box 0.45 m high on the roof (what makes a roof rack show from the ground)."""
    hl, hw = length_m / 2, width_m / 2
    cab_l, cab_w = length_m * cabin_share / 2, hw - 0.1
    parts = [Part((-hl, -hw, 0.25), (hl, hw, 0.9), paint),
             Part((-cab_l, -cab_w, 0.9), (cab_l, cab_w, height_m), paint),
             # glass a centimetre proud of the cabin's sides and ends, up to 0.1 m under its roof
             Part((-cab_l + 0.15, -cab_w - 0.01, 0.95), (cab_l - 0.15, cab_w + 0.01, height_m - 0.1), GLASS),
             Part((-cab_l - 0.01, -cab_w + 0.1, 0.95), (cab_l + 0.01, cab_w - 0.1, height_m - 0.1), GLASS),
             Part((-hl + 0.4, -hw - 0.02, 0.0), (-hl + 1.0, hw + 0.02, 0.6), DARK),  # wheels
             Part((hl - 1.0, -hw - 0.02, 0.0), (hl - 0.4, hw + 0.02, 0.6), DARK)]
    if roof_box:
        parts.append(Part((-0.6, -0.55, height_m), (0.6, 0.55, height_m + 0.45), GREY_BOX))
    return parts


def pickup(paint: tuple[int, int, int]) -> list[Part]:
    """A pickup: a painted body to 1.1 m over 5.3 m (the load bed's walls at the rear) and a short
    painted cab behind the hood to 1.85 m, with glass on its sides and ends."""
    return [Part((-2.65, -1.0, 0.4), (2.65, 1.0, 1.1), paint),
            Part((-0.4, -0.9, 1.1), (1.2, 0.9, 1.85), paint),
            Part((-0.25, -0.91, 1.15), (1.05, 0.91, 1.75), GLASS),
            Part((-0.41, -0.8, 1.15), (1.21, 0.8, 1.75), GLASS),
            Part((-2.2, -1.02, 0.0), (-1.4, 1.02, 0.75), DARK), Part((1.4, -1.02, 0.0), (2.2, 1.02, 0.75), DARK)]


def bus(paint: tuple[int, int, int]) -> list[Part]:
    """A bus: an 11 x 2.5 m painted box to 3.1 m with a band of windows from 1.3 to 2.7 m all round."""
    return [Part((-5.5, -1.25, 0.3), (5.5, 1.25, 3.1), paint),
            Part((-5.51, -1.26, 1.3), (5.51, 1.26, 2.7), GLASS),
            Part((-4.5, -1.27, 0.0), (-3.5, 1.27, 1.0), DARK), Part((3.0, -1.27, 0.0), (4.0, 1.27, 1.0), DARK)]


def box_truck(paint: tuple[int, int, int]) -> list[Part]:
    """A box truck: a painted cargo box (7.4 m long with the cab, 3.3 m high) and a lower painted cab
    with a windscreen."""
    return [Part((-3.7, -1.2, 1.0), (1.8, 1.2, 3.3), paint),
            Part((1.9, -1.1, 0.5), (3.7, 1.1, 2.4), paint),
            Part((3.71, -0.9, 1.45), (3.72, 0.9, 2.3), GLASS),
            Part((-3.5, -0.6, 0.5), (1.9, 0.6, 1.0), DARK),
            Part((-3.0, -1.22, 0.0), (-2.0, 1.22, 1.0), DARK), Part((2.3, -1.12, 0.0), (3.2, 1.12, 1.0), DARK)]


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """4x4 pose of an OpenCV camera (x right, y down, z forward) at ``eye`` looking at ``target``
    (image up towards ``up``, default world +z)."""
    up = np.array([0.0, 0.0, 1.0]) if up is None else up
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, np.cross(z, x), z, eye
    return pose


def _rays(intr: CameraIntrinsics, pose: np.ndarray) -> np.ndarray:
    vs, us = np.mgrid[0:intr.height_px, 0:intr.width_px].astype(np.float64)
    cam = np.stack([(us - intr.cx_px) / intr.fx_px, (vs - intr.cy_px) / intr.fy_px, np.ones_like(us)], -1)
    return cam @ pose[:3, :3].T  # (H, W, 3), z component along the optical axis is 1


def cast(parts: list[Part], intr: CameraIntrinsics, pose: np.ndarray, *, ground: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(RGB, depth along the optical axis in metres, hit mask) of the parts (world frame) seen by a
    camera; ``ground``: a grey street at z = 0 and sky behind, else nothing (depth inf)."""
    d = _rays(intr, pose)
    eye = pose[:3, 3]
    h, w = d.shape[:2]
    depth = np.full((h, w), np.inf)
    rgb = np.zeros((h, w, 3), np.float64)
    hit = np.zeros((h, w), bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for part in parts:
            lo, hi = np.asarray(part.lo), np.asarray(part.hi)
            t1, t2 = (lo - eye) / d, (hi - eye) / d
            near, far = np.minimum(t1, t2), np.maximum(t1, t2)
            t_in, t_out = np.nanmax(near, -1), np.nanmin(far, -1)
            ok = (t_in <= t_out) & (t_in > 0) & (t_in < depth)
            axis = np.nanargmax(near, -1)
            light = np.where(axis == 2, LIGHT["top"], np.where(axis == 0, LIGHT["x"], LIGHT["y"]))
            rgb[ok] = np.asarray(part.rgb, np.float64) * light[ok, None]
            depth[ok], hit[ok] = t_in[ok], True
        if ground:
            t_g = -eye[2] / d[:, :, 2]
            road = (t_g > 0) & (t_g < depth) & ~hit
            sky = ~hit & ~road
            depth[road], rgb[road] = t_g[road], ASPHALT
            depth[sky], rgb[sky] = 300.0, SKY
    return np.clip(rgb, 0, 255).astype(np.uint8), depth, hit


def placed(parts: list[Part], x_m: float, y_m: float) -> list[Part]:
    """The parts moved to (x, y) in the world (vehicles stay along world x)."""
    return [Part((p.lo[0] + x_m, p.lo[1] + y_m, p.lo[2]), (p.hi[0] + x_m, p.hi[1] + y_m, p.hi[2]), p.rgb) for p in parts]


def references(parts: list[Part], *, size_px: int = 160) -> list[ImageFrame]:
    """The reference views of a vehicle (its own frame) as the world renders them: a nearly
    orthographic top view with its scale, and four side views from the UGV's camera height at
    11 m, posed in the vehicle's frame, background transparent."""
    frames = []
    views = [("ref_top", np.array([0.0, 0.0, 150.0]), np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]), 4.0, 150.0)]
    for name, off in (("ref_front_left", 35.0), ("ref_side", 90.0), ("ref_rear", 145.0), ("ref_front", 0.0)):
        a = math.radians(off)
        views.append((name, np.array([11 * math.cos(a), 11 * math.sin(a), EYE_M]), np.array([0.0, 0.0, 1.0]),
                      np.array([0.0, 0.0, 1.0]), 40.0, 11.0))
    for name, eye, target, up, fov, dist in views:
        intr = intrinsics_for(size_px, size_px, fov)
        pose = look_at(eye, target, up)
        rgb, _, hit = cast(parts, intr, pose, ground=False)
        rgba = np.zeros((size_px, size_px, 4), np.uint8)
        rgba[hit, :3], rgba[hit, 3] = rgb[hit], 255
        frames.append(ImageFrame(name=name, kind="rgb", encoding="png", data=encode_png(rgba), intrinsics=intr,
                                 world_from_camera=pose.flatten().tolist(),
                                 metres_per_px=2 * dist * math.tan(math.radians(fov) / 2) / size_px))
    return frames


def ground_view(vehicles: list[list[Part]], *, yaw_deg: float = 0.0, name: str = "front", size_px: int = 256) -> GroundView:
    """A UGV view from the origin at the camera height, looking along ``yaw_deg`` (from world +x),
    70 deg wide, of the vehicles (world frame) on a street, as JPEG."""
    intr = intrinsics_for(size_px, size_px, 70.0)
    a = math.radians(yaw_deg)
    eye = np.array([0.0, 0.0, EYE_M])
    pose = look_at(eye, eye + np.array([math.cos(a), math.sin(a), 0.0]))
    rgb, depth, _ = cast([p for v in vehicles for p in v], intr, pose, ground=True)
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    jpeg = cv2.cvtColor(cv2.imdecode(data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return GroundView(name, jpeg, depth.astype(np.float32), intr, pose)
