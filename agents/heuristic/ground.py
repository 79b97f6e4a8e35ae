"""The target in a UGV's six views, by shape and context as well as by paint colour.

Each pixel of a ground view is placed in the world by its depth, intrinsics and pose. Pixels
standing above the street (not the road, its markings or the shadows drawn on it) are split
into objects where the depth jumps (a car in front of a shop front is another object than the
shop front). Objects with the target's hue are kept; one cut by the edge of a view is joined
with its other part in the neighbouring view. For :func:`find_target` (the ``paint-only`` policy
and the VLM stand-in) an object is the target when

- its paint has the references' brightness in the light it stands in (a vehicle in a building's
  shadow is darker; shade is read from the ground around it),
- its top stands at the reference's body height (a sedan, a hatchback, an SUV and a van differ
  by 0.2-0.5 m), and
- it is no longer than the target.

The heuristic UGV's :func:`judge_views` is stricter: it measures the target in the side
references as it measures objects (:class:`SideReference`: the tops of the outline and of the
paint, the outline along the body, the paint's share per height band) and tells matches (seen
whole and near) from leads (worth a closer look).

Uses only the agent's images, intrinsics, poses and the reference-derived
:class:`~agos.agents.heuristic.colour_match.TargetProfile`; no ground truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from agos.agents.heuristic.colour_match import TargetProfile
from agos.agents.heuristic.paint import MEAN_HUE_TOLERANCE, PAINT_ONLY_TOP_M, hue_match, mean_hue_error, near_hue, shade_score
from agos.runtime.camera import depth_to_world
from agos.runtime.codec import decode_image
from agos.runtime.schemas import CameraIntrinsics, ImageFrame

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
    is_paint: np.ndarray
    """(N,) whether each pixel shows the paint's hue (any brightness)."""
    column_top_m: np.ndarray
    """Height of the highest pixel of each image column the object spans (its upper outline)."""
    paint_column_top_m: np.ndarray
    """The same over its paint-hued pixels (the painted outline)."""
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
        column_top = np.full(w, -np.inf, np.float32)
        np.maximum.at(column_top, ox, height[oy, ox])
        painted = paint[oy, ox]
        paint_column_top = np.full(w, -np.inf, np.float32)
        np.maximum.at(paint_column_top, ox[painted], height[oy, ox][painted])
        parts.append(_Part(
            [view.name], xyz[oy, ox, :2], height[oy, ox], painted, column_top[np.isfinite(column_top)],
            paint_column_top[np.isfinite(paint_column_top)],
            hsv[:, :, 2][obj & paint].astype(np.float32),
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
                q.is_paint = np.concatenate([q.is_paint, p.is_paint])
                q.column_top_m = np.concatenate([q.column_top_m, p.column_top_m])
                q.paint_column_top_m = np.concatenate([q.paint_column_top_m, p.paint_column_top_m])
                q.paint_value = np.concatenate([q.paint_value, p.paint_value])
                q.hues = np.concatenate([q.hues, p.hues])
                q.shade = max(q.shade, p.shade)
                q.distance_m, q.px_m = min(q.distance_m, p.distance_m), max(q.px_m, p.px_m)
                q.top_cut = q.top_cut or p.top_cut
                break
        else:
            out.append(p)
    return out


def _paint_agrees(p: _Part, profile: TargetProfile, min_pixels: int) -> tuple[int, float] | None:
    """(paint pixels in the expected brightness, median paint value) when the object's mean hue and
    brightness are the paint's, else None."""
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
    return n_paint, value


def _length_m(p: _Part) -> float:
    (_, _), (a, b), _ = cv2.minAreaRect(p.xy_m.astype(np.float32))
    return float(max(a, b))


def _judge(p: _Part, profile: TargetProfile, min_pixels: int, paint_only: bool) -> GroundObject | None:
    """The object as a target match, or None when its paint, top or length disagree (``paint_only``:
    when its paint disagrees)."""
    paint = _paint_agrees(p, profile, min_pixels)
    if paint is None:
        return None
    n_paint, value = paint
    body = profile.body_height_m or profile.paint_top_m
    top = float(np.percentile(p.top_m, 98))
    x, y = np.median(p.xy_m, axis=0)
    if paint_only:
        return GroundObject(tuple(p.views), n_paint, p.distance_m, top, 0.0, float(x), float(y), value, p.shade, 1.0)
    if top - body > TOP_TOLERANCE_M + p.px_m or (body - top > TOP_TOLERANCE_M + p.px_m and not p.top_cut):
        return None
    length = _length_m(p)
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


# ----- the heuristic UGV's judge: the target's outline and paint from the side references --------

BAND_EDGES_M = tuple(round(0.3 + 0.3 * k, 2) for k in range(14))
"""Height bands (metres above the road, 0.3-4.2 m) in which the paint's share of a vehicle's
outline is compared with the side references: a bus shows glass from 1.3 to 2.7 m all round, a box
truck paint; a two-tone roof or a stripe takes the paint out of its bands."""
BAND_MIN_PX = 8
"""Pixels of an object in a band for its share to count."""
REFERENCE_BAND_MIN_PX = 5
PAINT_TOP_PERCENTILE = 98
"""The paint pixels' top: this percentile of their heights (the side reference's is the 97th of its
paint pixels placed on the vehicle's near side, :func:`~agos.agents.heuristic.colour_match.profile_from_references`)."""
OUTLINE_PERCENTILE = 90
"""An outline's top: this percentile of the heights of the highest pixel of each image column it
spans. A roof box or a bus's roof unit spans a large share of the columns from any side, a lamp
post or a branch touching the outline a few."""
SIDE_TOLERANCE_M = 0.10
"""How far an object's top (and its paint's top) may be from the side reference's at zero distance;
half a pixel's height at the object's distance is added (the sampling of its upper edge). Body
types and roof boxes differ by 0.17 m (sedan, hatchback) to 0.6 m."""
PROFILE_STEP_M = 0.25
PROFILE_MIN_SHARE = 0.6
"""An object's outline is compared along the body when it shows this share of the target's length
along its axis (and this share of its bins meets the reference's)."""
PROFILE_TOLERANCE_M = 0.15
"""Largest mean difference of the outline along the body from the broadside reference's (a roof
box over part of the roof, a cab in front of a load bed or a cargo box change it by 0.2 m and more)."""
BAND_TOLERANCE = 0.35
"""Largest mean difference of the paint's share per band from the closest side reference (the
target scores 0.02-0.17 from any side, a box truck against a bus 0.55)."""
CONFIRM_RANGE_M = 22.0
"""An object further than this is a lead, never a match: a pixel there is 0.12 m high, as much as
a roof box's rails or the step from a sedan to a hatchback."""
TOO_CLOSE_M = 3.0
"""An object of the paint nearer than this (the UGV stopped beside it) shows too little of itself
to be judged: a lead, to be looked at from further."""
LEAD_FACTOR = 2.0
"""A lead may miss the tolerances by this factor (seen from far or cut, it is to be looked at
again from closer, not taken)."""
BOX_HEIGHT_M = 10.0
"""Height of the box that rays of a side reference are met with (above any vehicle)."""


@dataclass(frozen=True)
class SideReference:
    """What the target's ground-level references show, measured as :func:`judge_views` measures an
    object of a UGV's views: its outline's top, its paint's top and the paint's share per band."""

    top_m: float
    """Top of the outline in the broadside reference (``OUTLINE_PERCENTILE`` of its columns' tops)."""
    top_low_m: float
    """The lowest top a ground camera may see: what stands set back on a roof higher than the
    camera (a bus's roof unit) hides behind the roof's edge from close by, so for such a body the
    top of the side reference's pixels (most of them below the roof unit) counts too."""
    paint_top_m: float
    bands: tuple[tuple[float, ...], ...]
    """Per ground-level reference view, the paint's share of the silhouette in each band of
    ``BAND_EDGES_M`` (NaN where the view shows fewer than ``REFERENCE_BAND_MIN_PX`` pixels)."""
    profile_m: tuple[float, ...] = ()
    """The broadside reference's upper outline along the body: its highest point in each
    ``PROFILE_STEP_M`` from the rear to the front (NaN where the view shows none)."""
    length_m: float = 0.0
    """The body's length the profile spans."""


def band_shares(heights_m: np.ndarray, paint: np.ndarray, min_px: int) -> tuple[np.ndarray, np.ndarray]:
    """(share of paint, pixel count) per band of ``BAND_EDGES_M``; NaN share below ``min_px`` pixels."""
    edges = np.asarray(BAND_EDGES_M)
    idx = np.digitize(heights_m, edges) - 1
    inside = (idx >= 0) & (idx < len(edges) - 1)
    n = np.bincount(idx[inside], minlength=len(edges) - 1).astype(np.float64)
    k = np.bincount(idx[inside & paint], minlength=len(edges) - 1).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n >= min_px, k / n, np.nan), n


def outline_top_m(columns: np.ndarray, heights_m: np.ndarray) -> float:
    """``OUTLINE_PERCENTILE`` of the highest ``heights_m`` per value of ``columns`` (0 for none)."""
    if len(columns) == 0:
        return 0.0
    order = np.argsort(columns, kind="stable")
    cols, h = columns[order], heights_m[order]
    starts = np.flatnonzero(np.r_[True, cols[1:] != cols[:-1]])
    return float(np.percentile(np.maximum.reduceat(h, starts), OUTLINE_PERCENTILE))


def _column_tops(us: np.ndarray, vs: np.ndarray) -> np.ndarray:
    """Indices of the topmost pixel of each image column among pixels (``us``, ``vs``)."""
    order = np.lexsort((vs, us))  # by column, then from the top of the image down
    cols = us[order]
    return order[np.flatnonzero(np.r_[True, cols[1:] != cols[:-1]])]


def _column_top_m(us: np.ndarray, vs: np.ndarray, heights_m: np.ndarray) -> float:
    """``OUTLINE_PERCENTILE`` over the image columns of the height of each column's topmost pixel
    (0 for none)."""
    if len(us) == 0:
        return 0.0
    return float(np.percentile(heights_m[_column_tops(us, vs)], OUTLINE_PERCENTILE))


def _binned_max(along_m: np.ndarray, heights_m: np.ndarray, start_m: float, length_m: float,
                min_count: int = 1) -> np.ndarray:
    """Highest ``heights_m`` in each ``PROFILE_STEP_M`` of ``along_m`` from ``start_m`` over
    ``length_m`` (NaN where fewer than ``min_count`` points)."""
    n = max(1, math.floor(length_m / PROFILE_STEP_M) + 1)
    k = np.floor((along_m - start_m) / PROFILE_STEP_M).astype(int)
    ok = (k >= 0) & (k < n)
    top = np.full(n, -np.inf)
    np.maximum.at(top, k[ok], heights_m[ok])
    count = np.bincount(k[ok], minlength=n)
    return np.where((count >= min_count) & np.isfinite(top), top, np.nan)


def profile_error(xy_m: np.ndarray, heights_m: np.ndarray, side: SideReference) -> float | None:
    """Mean difference (metres) between an object's upper outline along its long axis and the
    broadside reference's, at the best shift and direction along the body; None when the object
    shows less than ``PROFILE_MIN_SHARE`` of the target's length along its axis (seen end-on, or
    mostly hidden) or the reference has no profile."""
    ref = np.asarray(side.profile_m)
    if len(ref) == 0 or len(xy_m) < 10:
        return None
    corners = cv2.boxPoints(cv2.minAreaRect(xy_m.astype(np.float32)))
    edge_a, edge_b = corners[1] - corners[0], corners[2] - corners[1]
    axis = edge_a if np.hypot(*edge_a) >= np.hypot(*edge_b) else edge_b
    axis = axis / max(float(np.hypot(*axis)), 1e-9)
    s = (xy_m - xy_m.mean(axis=0)) @ axis
    extent = float(s.max() - s.min())
    if extent < PROFILE_MIN_SHARE * side.length_m:
        return None
    seen = _binned_max(s, heights_m, float(s.min()), extent, min_count=3)
    centres = float(s.min()) + (np.arange(len(seen)) + 0.5) * PROFILE_STEP_M
    keep = np.isfinite(seen)
    seen, centres = seen[keep], centres[keep]
    best: float | None = None
    for direction in (1.0, -1.0):
        pos = direction * centres
        for shift in np.arange(-side.length_m / 2 - pos.max() - PROFILE_STEP_M,
                               side.length_m / 2 - pos.min() + PROFILE_STEP_M, PROFILE_STEP_M / 2):
            k = np.floor((pos + shift + side.length_m / 2) / PROFILE_STEP_M).astype(int)
            inside = (k >= 0) & (k < len(ref))
            both = inside.copy()
            both[inside] = np.isfinite(ref[k[inside]])
            if both.sum() < PROFILE_MIN_SHARE * len(seen):
                continue
            err = float(np.mean(np.abs(seen[both] - ref[k[both]])))
            best = err if best is None else min(best, err)
    return best


def _box_heights(us: np.ndarray, vs: np.ndarray, intrinsics: CameraIntrinsics, vehicle_from_camera: np.ndarray,
                 length_m: float, width_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Heights where the rays through pixels of a reference view (a camera posed in the vehicle's
    frame) enter the vehicle's box, and where they would place an upper outline (height and
    position along the body): the surface a pixel shows, to within the body's own slopes; an
    outline lower than the camera is the far edge of a roof seen over it (where the ray leaves the
    box's sides), one higher its near edge."""
    pose = np.asarray(vehicle_from_camera, dtype=np.float64).reshape(4, 4)
    d = pose[:3, :3] @ np.stack([(us - intrinsics.cx_px) / intrinsics.fx_px,
                                 (vs - intrinsics.cy_px) / intrinsics.fy_px, np.ones(len(us))])
    eye = pose[:3, 3:4]
    lo = np.array([[-length_m / 2], [-width_m / 2], [0.0]])
    hi = np.array([[length_m / 2], [width_m / 2], [BOX_HEIGHT_M]])
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - eye) / d, (hi - eye) / d
    t_in = np.nanmax(np.minimum(t1, t2), axis=0)
    t_out = np.nanmin(np.maximum(t1, t2)[:2], axis=0)
    t_outline = np.where(d[2] < 0, t_out, t_in)
    return eye[2, 0] + t_in * d[2], eye[2, 0] + t_outline * d[2], eye[0, 0] + t_outline * d[0]


def side_reference(references: list[ImageFrame], profile: TargetProfile) -> SideReference:
    """The :class:`SideReference` of the target from its reference views (the top view's body
    length and width place the side views' pixels on the body)."""
    length = profile.body_length_m or profile.length_m
    width = profile.body_width_m or profile.width_m
    dark = 0.75 * min(profile.value_side[0], profile.value_top)
    bands: list[tuple[float, ...]] = []
    top, paint_top, eye_m = 0.0, profile.paint_top_m, math.inf
    profile_m = np.full(0, np.nan)
    for frame in references:
        if frame.name == "ref_top" or frame.intrinsics is None or frame.world_from_camera is None:
            continue
        rgba = decode_image(frame.data)
        vs, us = np.nonzero(rgba[:, :, 3] > 0)
        if len(us) == 0:
            continue
        heights, outline, along = _box_heights(us, vs, frame.intrinsics, np.asarray(frame.world_from_camera),
                                               length, width)
        hsv = cv2.cvtColor(np.ascontiguousarray(rgba[:, :, :3]), cv2.COLOR_RGB2HSV)
        paint = hue_match(hsv, profile, dark_below=dark)[vs, us]
        bands.append(tuple(float(v) for v in band_shares(heights, paint, REFERENCE_BAND_MIN_PX)[0]))
        if frame.name == "ref_side":
            eye_m = float(np.asarray(frame.world_from_camera).reshape(4, 4)[2, 3])
            top = _column_top_m(us, vs, outline)
            tops = _column_tops(us, vs)
            profile_m = _binned_max(along[tops], outline[tops], -length / 2, length)
            # the higher of the paint pixels' top (profile.paint_top_m) and the painted columns' (a
            # thin painted roof over glass is a small share of the pixels, a large one of the columns)
            paint_top = max(paint_top, _column_top_m(us[paint], vs[paint], outline[paint]))
    top = top or profile.body_height_m or profile.paint_top_m
    low = min(top, profile.body_height_m or top) if paint_top > eye_m else top
    return SideReference(top, low, paint_top, tuple(bands), tuple(float(v) for v in profile_m), length)


def band_distance(p_shares: np.ndarray, p_counts: np.ndarray, side: SideReference) -> float | None:
    """Smallest mean difference (weighted by the object's pixels, at most 300 a band) between the
    object's paint shares and those of one side reference, over the bands both show; None when no
    reference shares two bands with it."""
    best: float | None = None
    for ref in side.bands:
        r = np.asarray(ref)
        both = np.isfinite(p_shares) & np.isfinite(r)
        if both.sum() < 2:
            continue
        w = np.minimum(p_counts[both], 300.0)
        d = float((w * np.abs(p_shares[both] - r[both])).sum() / w.sum())
        best = d if best is None else min(best, d)
    return best


@dataclass(frozen=True)
class GroundJudgement:
    """The six views judged against the target: objects that are it (CONFIRM on the first) and
    objects that may be it, seen from too far or only in part (look again from closer)."""

    matches: list[GroundObject]
    leads: list[GroundObject]


def _verify(p: _Part, profile: TargetProfile, side: SideReference, min_pixels: int) -> tuple[str, GroundObject] | None:
    """("match" | "lead", the object) or None when the object is not the target."""
    paint = _paint_agrees(p, profile, min_pixels)
    if paint is None:
        return None
    n_paint, value = paint
    # A pixel's centre lies half a pixel below the upper edge it samples.
    top = outline_top_m(np.arange(len(p.column_top_m)), p.column_top_m) + 0.5 * p.px_m
    paint_top = max(float(np.percentile(p.top_m[p.is_paint], PAINT_TOP_PERCENTILE)) if p.is_paint.any() else 0.0,
                    outline_top_m(np.arange(len(p.paint_column_top_m)), p.paint_column_top_m)) + 0.5 * p.px_m
    length = _length_m(p)
    shares, counts = band_shares(p.top_m, p.is_paint, BAND_MIN_PX)
    bands = band_distance(shares, counts, side)
    tol = SIDE_TOLERANCE_M + 0.5 * p.px_m
    top_err = max(0.0, top - side.top_m) - max(0.0, side.top_low_m - top)
    paint_err = paint_top - side.paint_top_m
    # Cut by the top of the view, the tops measured are lower bounds: too low is no reason to
    # refuse (a lead, to be seen from further), only reaching the reference's makes a match.
    low_ok = LEAD_FACTOR * tol if not p.top_cut else math.inf
    outline = None if p.top_cut else profile_error(p.xy_m, p.top_m, side)
    too_long = not profile.body_cut and length > (profile.body_length_m or profile.length_m) + LENGTH_TOLERANCE_M
    x, y = np.median(p.xy_m, axis=0)
    if (too_long or max(top_err, paint_err) > LEAD_FACTOR * tol or min(top_err, paint_err) < -low_ok
            or (bands is not None and bands > BAND_TOLERANCE)
            or (outline is not None and outline > LEAD_FACTOR * PROFILE_TOLERANCE_M)):
        if p.distance_m < TOO_CLOSE_M and not too_long:  # seen in part from beside it: look from further
            return "lead", GroundObject(tuple(p.views), n_paint, p.distance_m, top, length, float(x), float(y), value,
                                        p.shade, 0.05)
        return None
    score = max(0.05, 1.0 - min(abs(top_err) + abs(paint_err), 4 * tol) / (4 * tol) - (bands or 0.0))
    obj = GroundObject(tuple(p.views), n_paint, p.distance_m, top, length, float(x), float(y), value, p.shade, score)
    sure = (max(abs(top_err), abs(paint_err)) <= tol and bands is not None
            and (outline is None or outline <= PROFILE_TOLERANCE_M)
            and p.distance_m <= CONFIRM_RANGE_M)
    return ("match" if sure else "lead"), obj


def judge_views(views: list[GroundView], profile: TargetProfile, side: SideReference, *,
                min_pixels: int = 40) -> GroundJudgement:
    """The heuristic UGV's judgement of its six views, stricter than :func:`find_target`.

    Objects are gathered as :func:`find_target` gathers them and checked for the paint's hue and
    brightness; then against the side references: the top of the object's outline and of its
    paint (a roof box raises the first only, a taller body both), each within ``SIDE_TOLERANCE_M``
    and half a pixel; the paint's share per height band (``BAND_TOLERANCE``); and no more than the
    target's length. A match is seen whole within ``CONFIRM_RANGE_M``; a lead misses no check by
    more than ``LEAD_FACTOR`` and is worth a closer look. Best first."""
    parts = [p for v in views for p in _parts(v, profile, min_pixels, False)]
    matches: list[GroundObject] = []
    leads: list[GroundObject] = []
    for p in _join_parts(parts):
        if p.cut:
            continue
        verdict = _verify(p, profile, side, min_pixels)
        if verdict is not None:
            (matches if verdict[0] == "match" else leads).append(verdict[1])
    return GroundJudgement(sorted(matches, key=lambda d: -d.score), sorted(leads, key=lambda d: -d.score))
