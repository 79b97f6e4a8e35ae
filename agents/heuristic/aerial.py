"""Vehicles in a UAV nadir view, found by shape and context as well as by paint colour.

A colour threshold alone mistakes red brick, yellow lane lines, awnings and paint in a shadow for
(or against) the target. This detector uses what the UAV receives besides the colours: its depth
image, intrinsics and pose give every pixel a place in the world, so

- a *height above the surface it stands on* separates things that stand on the road (a vehicle's
  top is 1.3-3.5 m up) from flat paint, drawn shadows and kerbs (a few centimetres), and from
  the roofs of buildings (a roof is a surface of its own, wider than any vehicle);
- the *silhouette* of a standing object, placed in world metres, has a length, a width and a
  height to compare with the reference views, free of perspective (the side of a vehicle seen
  off-nadir lands where the side is);
- the *paint* is matched by hue and saturation over a wide range of brightness: a vehicle in a
  building's shadow keeps its hue and saturation but loses value.

Uses only the agent's own images, intrinsics, pose and the reference-derived
:class:`~agos.agents.heuristic.colour_match.TargetProfile`; no ground truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from agos.agents.heuristic.colour_match import AerialDetection, TargetProfile
from agos.agents.heuristic.paint import MEAN_HUE_TOLERANCE, PAINT_ONLY_TOP_M, hue_match, mean_hue_error, near_hue, shade_score
from agos.runtime.camera import depth_to_world
from agos.runtime.schemas import CameraIntrinsics

GROUND_KERNEL_M = 4.0
"""Side of the square that the ground estimate is opened with: wider than any vehicle (a bus is
2.5 m), so a vehicle drops out of the ground while a roof or a tree crown larger than it stays."""
FLOOR_KERNEL_M = 30.0
"""Window of the street level estimate (the lowest ground nearby): a vehicle stands at it."""
MIN_OBJECT_HEIGHT_M = 0.35
"""Above kerbs (0.12 m), drawn shadows and markings (millimetres): those are never objects."""
OBJECT_HEADROOM_M = 0.7
"""An object's pixels may stand this far above the target's body height (a roof rack, the
depth noise), no more: tree crowns and awnings above a car are cut off its silhouette."""
MAX_BASE_ABOVE_FLOOR_M = 0.6
"""A vehicle's base is the street (or a sidewalk next to it), never a roof."""
SHADE_VALUE_MIN = 0.42
"""Lowest paint value accepted, as a fraction of the reference top view's: a building's shadow
darkens a vehicle to about 60% and JPEG a little more."""
SHADE_RELATIVE_VALUE = 0.7
"""Paint darker than this fraction of the sunlit value is explained as shade; such a match needs
evidence of shade around it (:func:`~agos.agents.heuristic.paint.shade_score`) to score fully."""
GLASS_BRIDGE_M = 1.2
"""Gap across a windscreen or rear window that paint regions of one vehicle are joined over."""
MIN_PAINT_SHARE = 0.4
"""A silhouette must show at least this share of the paint the reference top view shows."""
MIN_SCORE = 0.5
CUT_PENALTY = 0.2
"""Score lost by a silhouette cut by the image's edge (its size is only bounded): one seen whole
ranks first."""
SHADE_PENALTY = 0.3
"""Score lost by paint darker than ``SHADE_RELATIVE_VALUE`` of the reference with sunlit ground
around it: a darker paint in the sun (navy for blue), or the target at a shadow's edge (the
world shades a vehicle by its centre). The UGV tells them apart from close by."""


@dataclass(frozen=True)
class SurfaceHeights:
    """Per pixel of a view: world position (x, y, z in metres) and height above the surface the
    pixel's object stands on; per view: the street level below each pixel."""

    xyz_m: np.ndarray
    """(H, W, 3) world coordinates."""
    height_m: np.ndarray
    """(H, W) height above the local ground (0 on roads, roofs and other wide surfaces)."""
    base_above_floor_m: np.ndarray
    """(H, W) height of the local ground above the street level nearby (roofs: storeys)."""
    metres_per_px: float
    """Ground sampling at street level."""


def surface_heights(depth_m: np.ndarray, intrinsics: CameraIntrinsics, world_from_camera: np.ndarray) -> SurfaceHeights:
    """Back-project a depth image (metric z-depth along the optical axis) to world points, and
    split each point's z into the ground it stands on and its height above it.

    The ground is a grey-level opening of the z map with a square wider than any vehicle: what is
    narrower than that in some direction (a vehicle, a lamp post, a rooftop unit) is removed,
    wider surfaces (roads, plazas, roofs) stay.
    """
    xyz = depth_to_world(depth_m, intrinsics, world_from_camera)
    street_depth = float(np.percentile(depth_m.astype(np.float32), 90))  # most of a nadir view is at street level or above
    metres_per_px = max(street_depth, 1.0) / intrinsics.fy_px
    zw = np.ascontiguousarray(xyz[:, :, 2])
    ground = _opening(zw, GROUND_KERNEL_M / metres_per_px)
    floor = cv2.erode(ground, _square(FLOOR_KERNEL_M / metres_per_px), borderType=cv2.BORDER_REPLICATE)
    return SurfaceHeights(xyz, zw - ground, ground - floor, metres_per_px)


def _square(side_px: float) -> np.ndarray:
    k = max(3, math.ceil(side_px) | 1)
    return np.ones((k, k), np.uint8)


def _opening(z: np.ndarray, side_px: float) -> np.ndarray:
    """Grey opening of a z map. Beyond the image the ground is taken at the street level (a low
    percentile of z): a vehicle cut by the image's edge is then narrower than the square and
    drops out of the ground, as it does inside the image."""
    k = _square(side_px)
    street = float(np.percentile(z, 5))
    eroded = cv2.erode(z, k, borderType=cv2.BORDER_CONSTANT, borderValue=street)
    return cv2.dilate(eroded, k)


def shade_tolerant_paint(hsv: np.ndarray, profile: TargetProfile) -> np.ndarray:
    """Pixels whose hue and saturation are the paint's, at any brightness from deep shade
    (``SHADE_VALUE_MIN`` of the sunlit top) to a little above the sunlit top (speculars)."""
    value = hsv[:, :, 2].astype(np.float32)
    value_ok = (value >= SHADE_VALUE_MIN * profile.value_top) & (value <= profile.value_top * 1.25 + 5)
    return hue_match(hsv, profile, dark_below=0.6 * profile.value_top) & value_ok


@dataclass(frozen=True)
class Silhouette:
    """A standing object's measurements in world metres, and its paint."""

    u_px: float
    v_px: float
    length_m: float
    width_m: float
    height_m: float
    paint_share: float
    """Paint pixels over silhouette pixels, relative to the reference's share (1: as the reference)."""
    relative_value: float
    """Median paint value over the reference top view's value."""
    paint_px: int
    hue_error: float
    """Distance of the mean hue of its saturated, near-hued pixels from the paint's."""


def _measure(region: np.ndarray, paint: np.ndarray, heights: SurfaceHeights, hsv: np.ndarray,
             profile: TargetProfile) -> Silhouette | None:
    vs, us = np.nonzero(region)
    if len(us) < 3:
        return None
    xy = heights.xyz_m[vs, us, :2].astype(np.float32)
    (_, _), (a, b), _ = cv2.minAreaRect(xy)
    on_paint = paint[vs, us]
    n_paint = int(on_paint.sum())
    if n_paint == 0:
        return None
    reference_share = profile.paint_fraction if profile.paint_fraction > 0 else 0.8
    tops = heights.height_m[vs, us]
    pu, pv = us[on_paint], vs[on_paint]
    px = hsv[vs, us]
    return Silhouette(
        u_px=float(pu.mean()), v_px=float(pv.mean()),
        # a pixel is a footprint of its own: add one sample to each side of the fitted box
        length_m=float(max(a, b)) + heights.metres_per_px, width_m=float(min(a, b)) + heights.metres_per_px,
        height_m=float(np.percentile(tops, 95)),
        paint_share=n_paint / len(us) / reference_share,
        relative_value=float(np.median(hsv[pv, pu, 2])) / max(profile.value_top, 1.0),
        paint_px=n_paint, hue_error=mean_hue_error(px[near_hue(px, profile), 0], profile))


HEIGHT_FREE_M = 0.10
"""How far a silhouette's top may be from the side reference's outline top without penalty (the
UAV's depth measures a vehicle's top to a few centimetres)."""
HEIGHT_PENALTY_PER_M = 3.0
"""Score lost per metre of top beyond ``HEIGHT_FREE_M``: an SUV for a van (0.28 m lower), a van for
an SUV carrying a roof box (0.3 m) lose most of theirs."""


def _size_error(s: Silhouette, profile: TargetProfile, *, cut: bool = False, top_m: float | None = None) -> float:
    """Relative disagreement of length, width and (half weight) height with the reference. A
    silhouette cut by the image's edge may be shorter or narrower than the target, not longer;
    one measured against a cut reference may be longer, not shorter. With ``top_m`` (the side
    reference's outline top) the height counts in metres instead (``HEIGHT_PENALTY_PER_M``)."""
    length = profile.body_length_m or profile.length_m
    width = profile.body_width_m or profile.width_m
    if cut:
        err = max(0.0, s.length_m - length) / length + max(0.0, s.width_m - width) / width + CUT_PENALTY
    elif profile.body_cut:  # the reference's own size is a lower bound
        err = max(0.0, length - s.length_m) / length + abs(s.width_m - width) / width
    else:
        err = abs(s.length_m - length) / length + abs(s.width_m - width) / width
    if top_m is not None:
        err += HEIGHT_PENALTY_PER_M * max(0.0, abs(s.height_m - top_m) - HEIGHT_FREE_M)
    elif profile.body_height_m > 0:
        err += 0.5 * abs(s.height_m - profile.body_height_m) / profile.body_height_m
    return err


PAINT_ONLY_MAX_LENGTH_M = 12.5
"""A paint-only search takes standing objects up to a bus's length, whatever the reference's."""


def detect_vehicles_from_above(rgb: np.ndarray, depth_m: np.ndarray, profile: TargetProfile, *,
                               intrinsics: CameraIntrinsics, world_from_camera: np.ndarray,
                               paint_only: bool = False, top_m: float | None = None) -> list[AerialDetection]:
    """Standing objects of a nadir view with the target's paint, size and height, best first.

    A candidate is a group of paint pixels standing 0.35 m or more above their ground, joined
    across glass; its silhouette is the standing object around it (paint, glass and all), measured
    in world metres and compared with the reference's body length, width and height. Paint in
    shade counts when the ground around it is in shade too. ``paint_only``: any vehicle-sized
    object with the paint scores fully (the cue floor of the ``paint-only`` policy): size and
    height are not compared. ``top_m`` (the side reference's outline top,
    :func:`~agos.agents.heuristic.ground.side_reference`): the height is compared with it in metres
    (:func:`_size_error`), as the heuristic UAV does.
    """
    heights = surface_heights(depth_m, intrinsics, world_from_camera)
    top = (PAINT_ONLY_TOP_M if paint_only else max(profile.body_height_m, profile.paint_top_m, 1.2)) + OBJECT_HEADROOM_M
    standing = ((heights.height_m >= MIN_OBJECT_HEIGHT_M) & (heights.height_m <= top)
                & (heights.base_above_floor_m <= MAX_BASE_ABOVE_FLOOR_M))
    hsv = cv2.cvtColor(np.ascontiguousarray(rgb[:, :, :3]), cv2.COLOR_RGB2HSV)
    paint = shade_tolerant_paint(hsv, profile) & standing
    paint = cv2.morphologyEx(paint.astype(np.uint8), cv2.MORPH_OPEN, np.ones((2, 2), np.uint8)) > 0
    joined = cv2.morphologyEx(paint.astype(np.uint8), cv2.MORPH_CLOSE, _square(GLASS_BRIDGE_M / heights.metres_per_px))
    _, objects = cv2.connectedComponents(standing.astype(np.uint8), connectivity=8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(joined, connectivity=8)
    min_px = max(6, int(0.8 / heights.metres_per_px ** 2))  # 0.8 m2 of paint
    max_len = PAINT_ONLY_MAX_LENGTH_M if paint_only else \
        (profile.body_length_m or profile.length_m) * (2.0 if profile.body_cut else 1.6)
    found = []
    for k in range(1, n):
        if stats[k, cv2.CC_STAT_AREA] < min_px:
            continue
        group = labels == k
        # The standing object(s) under the paint: paint, glass and trim of one vehicle. Objects
        # that touch another (a car parked against a tree's trunk, two cars bumper to bumper)
        # give a silhouette too long: then the paint group alone is measured.
        ids = np.unique(objects[group & standing])
        region = np.isin(objects, ids[ids > 0]) if len(ids) else group
        s = _measure(region, paint, heights, hsv, profile)
        if s is None or s.length_m > max_len:
            region = group & standing
            s = _measure(region, paint, heights, hsv, profile)
        if s is None or s.paint_px < min_px or s.paint_share < MIN_PAINT_SHARE or s.hue_error > MEAN_HUE_TOLERANCE:
            continue
        vs, us = np.nonzero(region)
        cut = bool(us.min() <= 0 or vs.min() <= 0 or us.max() >= region.shape[1] - 1 or vs.max() >= region.shape[0] - 1)
        err = CUT_PENALTY * cut if paint_only else _size_error(s, profile, cut=cut, top_m=top_m)
        if s.relative_value < SHADE_RELATIVE_VALUE:
            err += SHADE_PENALTY * (1.0 - shade_score(region, rgb, heights.height_m, heights.xyz_m))
        score = max(0.0, 1.0 - err)
        if score >= MIN_SCORE:
            found.append(AerialDetection(s.u_px, s.v_px, s.length_m, s.width_m, score))
    return sorted(found, key=lambda d: -d.score)
