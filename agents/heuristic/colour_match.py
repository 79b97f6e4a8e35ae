"""Colour-and-size matching of the target against camera images, with OpenCV.

Uses only what an agent receives: the reference views (background removed, with a scale),
its own RGB and depth images, their intrinsics and camera poses. No ground truth.

A :class:`TargetProfile` is read from the references: the paint colour (HSV of the saturated
pixels), the painted and the whole body's length and width seen from above, and the height of
the painted parts and of the body seen from the side. :func:`detect_from_above` finds connected
regions of paint-coloured pixels in a nadir RGB image whose metric size (from the altitude)
agrees with the profile (the heuristic UAV's fallback without a depth image). The heuristic
policies use the depth-aware detectors of :mod:`aerial` and :mod:`ground`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from agos.runtime.codec import decode_image
from agos.runtime.schemas import CameraIntrinsics, ImageFrame

HUE_TOLERANCE = 7  # OpenCV hue units (0-179)
SAT_MIN = 90
VALUE_MIN = 45


@dataclass(frozen=True)
class TargetProfile:
    hue: float
    """Median paint hue (OpenCV units, 0-179)."""
    saturation: float
    value_top: float
    """Median paint value of surfaces facing up (reference top view)."""
    value_side: tuple[float, float]
    """Range of median paint values over the side views."""
    length_m: float
    width_m: float
    paint_top_m: float
    """Height of the highest painted pixel in the side view, metres above the road."""
    body_length_m: float = 0.0
    """Length of the whole body seen from above (the top view's silhouette, paint or not)."""
    body_width_m: float = 0.0
    body_height_m: float = 0.0
    """Height of the body's top in the side view, metres above the road (0: unknown)."""
    paint_fraction: float = 0.0
    """Share of the top view's silhouette that shows the paint (glass, a contrasting roof or a
    stripe lower it)."""
    body_cut: bool = False
    """The top view's silhouette touches the image's edge: ``body_length_m`` and ``body_width_m``
    are lower bounds (a long vehicle framed off centre)."""


def _hsv(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(rgb[:, :, :3]), cv2.COLOR_RGB2HSV)


def _paint_pixels(hsv: np.ndarray, mask: np.ndarray) -> np.ndarray:
    px = hsv[mask]
    return px[(px[:, 1] >= SAT_MIN) & (px[:, 2] >= VALUE_MIN)]


def circular_mean_hue(h: np.ndarray) -> float:
    """Mean of OpenCV hues (0-179) on the hue circle (red sits at both ends)."""
    angles = h.astype(np.float64) * (2 * math.pi / 180.0)
    mean = math.atan2(np.sin(angles).mean(), np.cos(angles).mean())
    return (mean * 180.0 / (2 * math.pi)) % 180.0


def hue_distance(a: np.ndarray | float, b: float) -> np.ndarray:
    d = np.abs(np.asarray(a, dtype=np.float64) - b) % 180.0
    return np.minimum(d, 180.0 - d)


def profile_from_references(references: list[ImageFrame]) -> TargetProfile:
    views = {f.name: f for f in references}
    top = views.get("ref_top")
    if top is None or top.metres_per_px is None:
        raise ValueError("references lack a scaled top view (ref_top)")
    rgba = decode_image(top.data)
    hsv = _hsv(rgba)
    body = rgba[:, :, 3] > 0
    paint = _paint_pixels(hsv, body)
    if len(paint) < 10:
        raise ValueError("the reference top view shows no saturated paint")
    hue, sat = circular_mean_hue(paint[:, 0]), float(np.median(paint[:, 1]))
    value_top = float(np.median(paint[:, 2]))
    paint_mask = body & (hue_distance(hsv[:, :, 0], hue) <= HUE_TOLERANCE) & (hsv[:, :, 1] >= SAT_MIN)
    length_px, width_px = _oriented_size(paint_mask)
    scale = top.metres_per_px

    body_length_px, body_width_px = _oriented_size(body)
    body_cut = bool(body[0].any() or body[-1].any() or body[:, 0].any() or body[:, -1].any())
    paint_fraction = float(paint_mask.sum()) / max(1, int(body.sum()))

    side_values, paint_top, body_top = [], 0.0, 0.0
    for name, frame in views.items():
        if name == "ref_top" or frame.metres_per_px is None:
            continue
        img = decode_image(frame.data)
        shsv = _hsv(img)
        smask = (img[:, :, 3] > 0)
        spaint = _paint_pixels(shsv, smask)
        spaint = spaint[hue_distance(spaint[:, 0], hue) <= HUE_TOLERANCE]
        if len(spaint):
            side_values.append(float(np.median(spaint[:, 2])))
        if name == "ref_side" and frame.world_from_camera is not None and frame.intrinsics is not None:
            side_paint = smask & (hue_distance(shsv[:, :, 0], hue) <= HUE_TOLERANCE) & (shsv[:, :, 1] >= SAT_MIN)
            paint_top = _painted_top_m(frame.intrinsics, frame.world_from_camera, side_paint, width_m=width_px * scale)
            body_top = _painted_top_m(frame.intrinsics, frame.world_from_camera, smask,
                                      width_m=body_width_px * scale)
    if not side_values:
        side_values = [value_top]
    return TargetProfile(hue, sat, value_top, (min(side_values), max(side_values)),
                         length_px * scale, width_px * scale, paint_top,
                         body_length_px * scale, body_width_px * scale, body_top, paint_fraction, body_cut)


def _painted_top_m(intr: CameraIntrinsics, world_from_camera: list[float], mask: np.ndarray, *,
                   width_m: float) -> float:
    """Height of the painted parts in a side reference: rays through the painted pixels meet
    the vehicle's near side (a vertical plane width/2 from its centre line)."""
    vs, us = np.nonzero(mask)
    if len(vs) == 0:
        return 0.0
    pose = np.asarray(world_from_camera).reshape(4, 4)
    rays = pose[:3, :3] @ np.stack([(us - intr.cx_px) / intr.fx_px, (vs - intr.cy_px) / intr.fy_px, np.ones(len(us))])
    eye = pose[:3, 3]
    near = math.hypot(eye[0], eye[1]) - width_m / 2
    t = near / np.hypot(rays[0], rays[1])
    return float(np.percentile(eye[2] + t * rays[2], 97))


def _oriented_size(mask: np.ndarray) -> tuple[float, float]:
    ys, xs = np.nonzero(mask)
    if len(xs) < 3:
        return 0.0, 0.0
    (_, _), (w, h), _ = cv2.minAreaRect(np.column_stack([xs, ys]).astype(np.float32))
    return float(max(w, h)), float(min(w, h))


def paint_mask(rgb: np.ndarray, profile: TargetProfile, value_range: tuple[float, float]) -> np.ndarray:
    hsv = _hsv(rgb)
    m = ((hue_distance(hsv[:, :, 0], profile.hue) <= HUE_TOLERANCE)
         & (np.abs(hsv[:, :, 1].astype(np.float32) - profile.saturation) <= 70)
         & (hsv[:, :, 2] >= value_range[0]) & (hsv[:, :, 2] <= value_range[1]))
    m = cv2.morphologyEx(m.astype(np.uint8), cv2.MORPH_OPEN, np.ones((2, 2), np.uint8))
    return m.astype(bool)


@dataclass(frozen=True)
class AerialDetection:
    u_px: float
    v_px: float
    length_m: float
    width_m: float
    score: float
    """0 (poor) to 1 (perfect) agreement with the profile: size (and, from :mod:`aerial`, height
    and the light the paint is seen in)."""


def detect_from_above(rgb: np.ndarray, profile: TargetProfile, *, altitude_m: float, fy_px: float) -> list[AerialDetection]:
    """Paint-coloured regions of a nadir image with a vehicle-sized footprint, best first."""
    value_range = (profile.value_top * 0.78, min(255.0, profile.value_top * 1.25 + 5))
    mask = paint_mask(rgb, profile, value_range)
    # Bridge windscreens and glass bands (a pixel or two) so a vehicle is one region.
    mask = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    metres_per_px = (altitude_m - 1.5) / fy_px
    found = []
    for k in range(1, n):
        if stats[k, cv2.CC_STAT_AREA] < 12:
            continue
        length_px, width_px = _oriented_size(labels == k)
        length, width = length_px * metres_per_px, width_px * metres_per_px
        err = abs(length - profile.length_m) / profile.length_m + abs(width - profile.width_m) / profile.width_m
        score = max(0.0, 1.0 - err)
        if score >= 0.55:
            found.append(AerialDetection(float(centroids[k][0]), float(centroids[k][1]), length, width, score))
    return sorted(found, key=lambda d: -d.score)
