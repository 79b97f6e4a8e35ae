"""The target's paint in a view: hue tolerances, an object's mean hue, and the shade it stands in.

Shared by the aerial (:mod:`aerial`) and the ground (:mod:`ground`) detectors. The world shades
a vehicle standing in a building's shadow by scaling its colour, which keeps hue and saturation
and lowers value; the ground in a drawn shadow is tinted towards blue. So paint is matched by
hue and saturation over a wide range of value, near paints (blue and navy) are told apart by
the mean hue of an object's pixels, and shade is read from the ground around an object.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from agos.agents.heuristic.colour_match import TargetProfile, circular_mean_hue, hue_distance

HUE_TOLERANCE = 7
"""OpenCV hue units (0-179) a paint pixel may be off, as the colour matcher of :mod:`colour_match`."""
DARK_HUE_TOLERANCE = 10
"""The same for dark pixels (paint in shade): JPEG chroma is coarser there."""
SAT_TOLERANCE = 70
WIDE_HUE_TOLERANCE = 15
"""Hues looked at for an object's mean hue: wide enough that a near paint's mean is not pulled
towards the target's by the pixel tolerance."""
MEAN_HUE_TOLERANCE = 3.0
"""Largest distance of an object's mean hue from the paint's: near paints differ by 6 or more
(blue and navy; red and maroon 9, yellow and orange 12); JPEG moves a vehicle's mean by about 1."""
PAINT_ONLY_TOP_M = 3.6
"""A paint-only search (the ``paint-only`` policy) takes standing objects up to a bus's roof,
whatever the reference's height."""
SHADE_RING_M = (0.3, 1.5)
"""The ground looked at for shade: this far (min, max) from an object's footprint. Close, since
the world shades a vehicle by where its centre stands: a ring further out may lie across the
shadow's edge."""
SHADE_GROUND_MAX_M = 0.35
"""Pixels lower than this above their ground are ground (road, sidewalk, markings)."""
SHADE_BLUE_OVER_RED = (1.10, 1.22)
"""Median blue/red of that ground, mapped to shade 0..1: sunlit asphalt and paving are neutral
(about 1.0); a building's drawn shadow darkens red more than blue (about 1.25); a vehicle's own
shadow, a small part of the ring, is a nearly neutral dark grey (about 1.15)."""


def hue_match(hsv: np.ndarray, profile: TargetProfile, *, dark_below: float) -> np.ndarray:
    """Pixels with the paint's hue and saturation at any value; pixels darker than
    ``dark_below`` get the wider dark tolerance."""
    dark = hsv[:, :, 2].astype(np.float32) < dark_below
    hue_ok = hue_distance(hsv[:, :, 0], profile.hue) <= np.where(dark, DARK_HUE_TOLERANCE, HUE_TOLERANCE)
    return hue_ok & saturation_match(hsv, profile)


def saturation_match(hsv: np.ndarray, profile: TargetProfile) -> np.ndarray:
    return np.abs(hsv[..., 1].astype(np.float32) - profile.saturation) <= SAT_TOLERANCE


def near_hue(hsv: np.ndarray, profile: TargetProfile) -> np.ndarray:
    """Saturated pixels within ``WIDE_HUE_TOLERANCE`` of the paint (the sample of a mean hue)."""
    return (hue_distance(hsv[..., 0], profile.hue) <= WIDE_HUE_TOLERANCE) & saturation_match(hsv, profile)


def mean_hue_error(hues: np.ndarray, profile: TargetProfile) -> float:
    """Distance of the circular mean of ``hues`` from the paint's hue (180 for no pixels)."""
    if hues.size == 0:
        return 180.0
    return float(hue_distance(circular_mean_hue(hues), profile.hue))


def shade_score(obj: np.ndarray, rgb: np.ndarray, height_m: np.ndarray, xyz_m: np.ndarray) -> float:
    """0 (sunlit) to 1 (in a building's shadow): how blue-shifted the ground right around an
    object is. The ring is measured in world metres from the object's footprint, so the same
    test serves nadir and ground views.

    ``obj``: the object's pixels; ``height_m``: per pixel, height above its ground; ``xyz_m``:
    per pixel, world position.
    """
    vs, us = np.nonzero(obj)
    if len(us) < 3:
        return 0.0
    (cx, cy), (a, b), angle = cv2.minAreaRect(xyz_m[vs, us, :2].astype(np.float32))
    t = math.radians(angle)
    flat = height_m < SHADE_GROUND_MAX_M
    gx, gy = xyz_m[:, :, 0][flat] - cx, xyz_m[:, :, 1][flat] - cy
    along = np.abs(gx * math.cos(t) + gy * math.sin(t))
    across = np.abs(-gx * math.sin(t) + gy * math.cos(t))
    near, far = SHADE_RING_M
    ring = (along <= a / 2 + far) & (across <= b / 2 + far) & ~((along <= a / 2 + near) & (across <= b / 2 + near))
    if ring.sum() < 20:
        return 0.0
    px = rgb[:, :, :3][flat][ring].astype(np.float32)
    blue_over_red = float(np.median(px[:, 2] / np.maximum(px[:, 0], 1.0)))
    lo, hi = SHADE_BLUE_OVER_RED
    return float(np.clip((blue_over_red - lo) / (hi - lo), 0.0, 1.0))
