"""The target in a UGV's six views, by shape and context as well as by paint colour.

Each pixel of a ground view is placed in the world by its depth, intrinsics and pose. Pixels
standing above the street (not the road, its markings or the shadows drawn on it) are split
into objects where the depth jumps (a car in front of a shop front is another object than the
shop front). Objects with the target's hue are kept; one cut by the edge of a view is joined
with its other part in the neighbouring view. An object is the target when

- its paint has the references' brightness in the light it stands in (a vehicle in a building's
  shadow is darker; shade is read from the ground around it),
- its top stands at the reference's body height (a sedan, a hatchback, an SUV and a van differ
  by 0.2-0.5 m), and
- it is no longer than the target.

Uses only the agent's images, intrinsics, poses and the reference-derived
:class:`~agos.agents.heuristic.perception.TargetProfile`; no ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from agos.agents.heuristic.paint import MEAN_HUE_TOLERANCE, PAINT_ONLY_TOP_M, hue_match, mean_hue_error, near_hue, shade_score
from agos.agents.heuristic.perception import TargetProfile
from agos.runtime.camera import depth_to_world
from agos.runtime.schemas import CameraIntrinsics

MIN_HEIGHT_M = 0.25
"""Above kerbs, markings and drawn shadows."""
HEADROOM_M = 0.7
"""Object pixels higher than the target's body by more than this are not part of a vehicle of
its kind (building storeys, tree crowns): they are cut off before objects are formed."""
DEPTH_JUMP = 0.04
"""Neighbouring pixels whose depths differ by more than this fraction (plus 0.25 m) lie on
different objects."""
MAX_DISTANCE_M = 48.0
JOIN_GAP_M = 0.3
"""Parts of one object seen in two views (cut by the edges between them) lie this close."""
CUT_MEASURED_SHARE = 0.05
"""An object cut by a view's edge that fills this share of the view is close by: its top is in
view, so it is measured as it is."""
TOP_TOLERANCE_M = 0.12
"""How far an object's top may be from the reference's body height, plus one pixel's height at
the object's distance (the sampling of its top edge)."""
LENGTH_TOLERANCE_M = 0.5
"""How much longer than the reference's body an object may look (mirrors, the depth of its
visible faces, a pixel at each end)."""
MIN_PAINT_VALUE = 15
SHADE_DARKENING = 0.62
"""A vehicle in a building's shadow shows its paint about this much darker (the world's shade,
which keeps hue and saturation)."""
VALUE_LOW_FACTOR, VALUE_HIGH_FACTOR = 0.55, 1.15
"""Margins of the expected median paint value. Low: the references show the vehicle's front and
one side; the other side, turned from the sun, is lit by ambient light alone. High: JPEG."""


@dataclass(frozen=True)
class GroundView:
    """One RGB view with its metric depth, intrinsics and pose (OpenCV camera, world frame)."""

    name: str
    rgb: np.ndarray
    depth_m: np.ndarray
    intrinsics: CameraIntrinsics
    world_from_camera: np.ndarray


@dataclass
class _Part:
    """An object with the target's hue as one view shows it, in world coordinates."""

    views: list[str]
    xy_m: np.ndarray
    """(N, 2) positions of its pixels."""
    top_m: np.ndarray
    """(N,) heights of its pixels above the street."""
    paint_value: np.ndarray
    """(M,) HSV values of its paint-hued pixels."""
    hues: np.ndarray
    """HSV hues of its saturated pixels within ``WIDE_HUE_TOLERANCE`` of the paint's (a near paint's
    hue shows in their mean, not cut off by the paint mask's tolerance)."""
    shade: float
    distance_m: float
    px_m: float
    """Size of a pixel at its distance (how finely its top is sampled)."""
    cut: bool
    """Touches the left or right edge of its view, and small there: only part of it is measured."""
    top_cut: bool
    """Touches the top edge of its view: its top is higher than measured."""


@dataclass(frozen=True)
class GroundObject:
    """An object of the six views that matches the target, with its measurements."""

    views: tuple[str, ...]
    pixels: int
    """Paint pixels."""
    distance_m: float
    top_m: float
    """Height of its top above the street (silhouette, paint or not)."""
    length_m: float
    """Longest horizontal extent of its visible surfaces."""
    x_m: float
    y_m: float
    value: float
    """Median value (HSV) of its paint pixels."""
    shade: float
    """0 (sunlit) to 1 (in a building's shadow), from the ground around it."""
    score: float


def expected_value_range(profile: TargetProfile, shade: float) -> tuple[float, float]:
    """The median paint value an object of the target's paint may show from the ground: from the
    side references' darkest to the top's (a ground camera sees the hood, and the roof of a car
    lower than itself), widened by the margins, and down to the shaded value as far as the ground around it shows
    shade (not up: the world shades a vehicle by where its centre stands, so sunlit paint can
    stand next to shaded ground)."""
    lo, hi = profile.value_side[0], max(profile.value_side[1], profile.value_top)
    k = 1.0 - (1.0 - SHADE_DARKENING) * shade
    return lo * k * VALUE_LOW_FACTOR, hi * VALUE_HIGH_FACTOR + 5


def _street_level(z: np.ndarray, depth_m: np.ndarray) -> float:
    near = z[(depth_m > 0.5) & (depth_m < 40.0)]
    return float(np.percentile(near, 5)) if near.size else 0.0


def _object_labels(standing: np.ndarray, depth_m: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected standing pixels, cut where the depth jumps between neighbours (the far side of
    each jump is dropped, so the near object keeps its outline)."""
    d = depth_m.astype(np.float32)
    tol = DEPTH_JUMP * d + 0.25
    jump = np.zeros_like(standing)
    dx = np.abs(np.diff(d, axis=1)) > np.minimum(tol[:, 1:], tol[:, :-1])
    right_far = d[:, 1:] > d[:, :-1]
    jump[:, 1:] |= dx & right_far
    jump[:, :-1] |= dx & ~right_far
    dy = np.abs(np.diff(d, axis=0)) > np.minimum(tol[1:], tol[:-1])
    lower_far = d[1:] > d[:-1]
    jump[1:] |= dy & lower_far
    jump[:-1] |= dy & ~lower_far
    return cv2.connectedComponents((standing & ~jump).astype(np.uint8), connectivity=4)


def _parts(view: GroundView, profile: TargetProfile, min_pixels: int, paint_only: bool) -> list[_Part]:
    """Standing objects of one view with at least ``min_pixels`` // 4 paint-hued pixels."""
    depth = view.depth_m.astype(np.float32)
    h, w = depth.shape
    xyz = depth_to_world(depth, view.intrinsics, view.world_from_camera)
    pose = np.asarray(view.world_from_camera, dtype=np.float32).reshape(4, 4)
    height = xyz[:, :, 2] - _street_level(xyz[:, :, 2], depth)
    distance = np.hypot(xyz[:, :, 0] - pose[0, 3], xyz[:, :, 1] - pose[1, 3])
    body = PAINT_ONLY_TOP_M if paint_only else profile.body_height_m or profile.paint_top_m
    standing = (height >= MIN_HEIGHT_M) & (height <= body + HEADROOM_M) & (distance <= MAX_DISTANCE_M)
    n, labels = _object_labels(standing, depth)
    hsv = cv2.cvtColor(np.ascontiguousarray(view.rgb[:, :, :3]), cv2.COLOR_RGB2HSV)
    bright = hsv[:, :, 2] >= MIN_PAINT_VALUE
    paint = hue_match(hsv, profile, dark_below=0.75 * min(profile.value_side[0], profile.value_top)) & bright & standing
    wide = near_hue(hsv, profile) & bright & standing
    counts = np.bincount(labels[paint], minlength=n)
    parts = []
    for k in np.nonzero(counts >= max(1, min_pixels // 4))[0]:
        if k == 0:
            continue
        obj = labels == k
        oy, ox = np.nonzero(obj)
        dist = float(np.median(distance[oy, ox]))
        parts.append(_Part(
            [view.name], xyz[oy, ox, :2], height[oy, ox], hsv[:, :, 2][obj & paint].astype(np.float32),
            hsv[:, :, 0][obj & wide], shade_score(obj, view.rgb, height, xyz), dist, dist / view.intrinsics.fy_px,
            cut=bool(ox.min() == 0 or ox.max() == w - 1) and len(ox) < CUT_MEASURED_SHARE * h * w,
            top_cut=bool(oy.min() == 0)))
    return parts


def _near(a: np.ndarray, b: np.ndarray, gap_m: float) -> bool:
    """Whether two point sets come within ``gap_m`` (on at most 400 points of each)."""
    if np.any(a.min(0) > b.max(0) + gap_m) or np.any(b.min(0) > a.max(0) + gap_m):
        return False  # boxes apart
    a = a[:: max(1, len(a) // 400)]
    b = b[:: max(1, len(b) // 400)]
    d2 = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
    return bool(d2.min() <= gap_m ** 2)


def _join_parts(parts: list[_Part]) -> list[_Part]:
    """Parts that touch (within ``JOIN_GAP_M``) are one object: the pieces of a vehicle seen in two
    views, or split within one view where its side is seen at a grazing angle (a depth jump).
    Judged as a whole, a taller look-alike cannot pass on a low piece of it. The union stays
    ``cut`` only when a piece is cut and no second view shows the rest."""
    out: list[_Part] = []
    for p in sorted(parts, key=lambda q: -len(q.xy_m)):
        for q in out:
            if _near(p.xy_m, q.xy_m, JOIN_GAP_M):
                q.cut = (q.cut or p.cut) and set(q.views) == set(p.views)
                q.views = sorted(set(q.views) | set(p.views))
                q.xy_m = np.concatenate([q.xy_m, p.xy_m])
                q.top_m = np.concatenate([q.top_m, p.top_m])
                q.paint_value = np.concatenate([q.paint_value, p.paint_value])
                q.hues = np.concatenate([q.hues, p.hues])
                q.shade = max(q.shade, p.shade)
                q.distance_m, q.px_m = min(q.distance_m, p.distance_m), max(q.px_m, p.px_m)
                q.top_cut = q.top_cut or p.top_cut
                break
        else:
            out.append(p)
    return out


def _judge(p: _Part, profile: TargetProfile, min_pixels: int, paint_only: bool) -> GroundObject | None:
    """The object as a target match, or None when its paint, top or length disagree (``paint_only``:
    when its paint disagrees)."""
    # Near paints differ in hue by 6 (blue, navy) to 12 (yellow, orange) units: the mean over
    # many pixels tells them apart where single pixels (JPEG) do not. Shade keeps the hue.
    if mean_hue_error(p.hues, profile) > MEAN_HUE_TOLERANCE:
        return None
    # Paint brightness tells near paints apart (navy is a dark blue), in the light the object
    # stands in: a blue car in a shadow is as dark as a navy one in the sun.
    lo, hi = expected_value_range(profile, p.shade)
    value = float(np.median(p.paint_value))
    n_paint = int(((p.paint_value >= lo) & (p.paint_value <= hi)).sum())
    if not lo <= value <= hi or n_paint < min_pixels:
        return None
    body = profile.body_height_m or profile.paint_top_m
    top = float(np.percentile(p.top_m, 98))
    x, y = np.median(p.xy_m, axis=0)
    if paint_only:
        return GroundObject(tuple(p.views), n_paint, p.distance_m, top, 0.0, float(x), float(y), value, p.shade, 1.0)
    if top - body > TOP_TOLERANCE_M + p.px_m or (body - top > TOP_TOLERANCE_M + p.px_m and not p.top_cut):
        return None
    (_, _), (a, b), _ = cv2.minAreaRect(p.xy_m.astype(np.float32))
    length = float(max(a, b))
    if not profile.body_cut and length > (profile.body_length_m or profile.length_m) + LENGTH_TOLERANCE_M:
        return None
    score = max(0.05, 1.0 - abs(top - body) / max(body, 0.5))
    return GroundObject(tuple(p.views), n_paint, p.distance_m, top, length, float(x), float(y), value, p.shade, score)


def find_target(views: list[GroundView], profile: TargetProfile, *, min_pixels: int = 40,
                paint_only: bool = False) -> list[GroundObject]:
    """Objects of the views (a STOP_OBSERVE's six, or one) that match the target, best first.

    Standing objects with the paint's hue are gathered from every view and joined where they
    touch. An object cut by a view's edge and not found whole across two views is not judged:
    its top and length are only bounds there (the front of a van passes for a car). ``paint_only``:
    any standing object with the paint matches (the cue floor of the ``paint-only`` policy)."""
    parts = [p for v in views for p in _parts(v, profile, min_pixels, paint_only)]
    found = []
    for p in _join_parts(parts):
        if p.cut:
            continue
        match = _judge(p, profile, min_pixels, paint_only)
        if match is not None:
            found.append(match)
    return sorted(found, key=lambda d: -d.score)
