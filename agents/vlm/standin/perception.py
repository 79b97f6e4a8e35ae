"""What the stand-in sees: the heuristic's robust detectors, fed only with what a VLM request carries.

The heuristic policies place every pixel in the world with a depth image
(:mod:`agos.agents.heuristic.aerial`, :mod:`agos.agents.heuristic.ground`). A VLM request carries
no depth: RGB images, each camera's intrinsics and pose and the UAV's altitude in the state block,
and the target's reference views with their scale. This module recovers what the detectors need
from those, the way a careful viewer reads a picture, and never decides by colour alone:

* **From above** (:func:`detect_from_above_rgb`): the street is a plane 80 m below a nadir camera,
  so the altitude and the intrinsics give metres per pixel. The reference top view, scaled to that,
  is a template of the target's paint layout (hood, glass, roof, a rack, a stripe, an open bed)
  matched over 24 orientations against the shade-tolerant paint mask of
  :func:`~agos.agents.heuristic.aerial.shade_tolerant_paint`, with a ring around the body where
  paint must not be (a longer or wider vehicle of the same paint spills into it). The match's
  paint silhouette is then measured in world metres along and across the vehicle's axis and
  compared with the reference, allowing for the side a standing vehicle shows away from the image
  centre (its painted height times the ground offset over the altitude: what depth would have
  removed). The mean hue must be the paint's (blue is not navy) and paint darker than the
  reference needs shade around it (:func:`~agos.agents.heuristic.paint.shade_score`).
* **From the ground** (:func:`ground_view_from_rgb`, :func:`find_target_rgb`): a vehicle stands on
  the road, so where a paint-hued region's lowest pixels meet the road fixes its distance along
  the camera rays. The lowest painted point is not the road but the sill, at the height the side
  reference shows (:func:`paint_bottom`); the region's bottom edge is taken as its lower convex
  hull (wheel arches do not pull it up), and the region stands on one vertical face at the median
  of its columns' distances, the rest of the view on the road plane: a depth image a monocular
  viewer would draw. :func:`~agos.agents.heuristic.ground.find_target` judges it as it judges a
  real one (hue mean, brightness in the light the object stands in, top height, length), against
  the reference's *painted* top, since only paint-hued pixels are raised. What stands on the
  paint in the side reference (:func:`reference_cap`: a roof box, a two-tone roof) is looked for
  above each match, against the background beside it (:func:`cap_share`).

What it costs against depth (docs/AGENTS.md, "What the stand-in sees, and what that costs"): from
above a sedan and an SUV of one paint differ by a few pixels, nothing tells a car's height, and a
flat patch of the paint with a car's layout would pass; from the ground the silhouette is the
paint's, a stripe is not checked, a roof box is judged against whatever stands behind it, and an
occluded sill pushes an object back (it is then judged too tall and rejected, never accepted).
Deterministic: the same images and state give the same detections.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import cv2
import numpy as np

from agos.agents.heuristic.aerial import SHADE_PENALTY, SHADE_RELATIVE_VALUE, shade_tolerant_paint
from agos.agents.heuristic.colour_match import HUE_TOLERANCE, SAT_MIN, AerialDetection, TargetProfile, hue_distance
from agos.agents.heuristic.ground import MIN_PAINT_VALUE, GroundObject, GroundView, find_target
from agos.agents.heuristic.paint import MEAN_HUE_TOLERANCE, hue_match, mean_hue_error, near_hue, shade_score
from agos.runtime.schemas import CameraIntrinsics

ORIENTATIONS = 24
"""Template orientations tried from above (15 degree steps; vehicles park along curved roads too)."""
RING_M = 0.6
"""Width of the ring around the template's body where the paint must not continue."""
MIN_MATCH = 0.45
"""Lowest normalised correlation of the paint mask with the template worth measuring."""
MIN_SCORE = 0.3
"""Lowest score (correlation minus the silhouette's weighted size errors) reported as a detection."""
LENGTH_WEIGHT, WIDTH_WEIGHT = 1.0, 0.5
"""Weights of the silhouette's relative length and width errors in a detection's score (the width,
a few pixels, is the less certain)."""
NMS_M = 3.0
NMS_LENGTH_SHARE = 0.75
"""Two detections closer than this share of the target's length (or ``NMS_M``, if more) are one
vehicle: the better scored is kept."""
GLASS_BRIDGE_M = 1.2
"""Gap across glass that paint regions of one vehicle are joined over to measure its silhouette."""
LEAN_MIN_HEIGHT_M = 1.0
"""Painted height assumed at least when estimating how much side a vehicle shows off-centre."""
GROUND_CLOSE_PX = (13, 3)
"""Rows x columns of the closing that joins a ground view's paint regions across the glass band."""
MIN_REGION_PX = 20
FAR_M = 500.0
"""Depth given to pixels whose rays do not meet the road (sky, facades above the horizon)."""
DEFAULT_PAINT_BOTTOM_M = 0.35
"""A car's sill, when the side reference does not show the paint's lowest point."""
BOTTOM_SLACK_M = 0.05
"""Added either side of the side reference's spread of paint bottoms: the sampling of its lowest pixel."""
CAP_GAP_M, CAP_BAND_M = 0.08, 0.40
"""The band above an object's painted top where a cap (a roof box, a contrasting roof) shows."""
CAP_MIN_PX = 40
CAP_SAT_TOLERANCE, CAP_VALUE_TOLERANCE = 50, 50
CAP_MIN_SHARE = 0.15
BOX_SATURATION = 40
BOX_VALUE = (70, 200)
BOX_MAX_SHARE = 0.4
REGION_MATCH_M = 2.0
"""A region belongs to an object of :func:`~agos.agents.heuristic.ground.find_target` this close."""


# ----- from above -----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TopTemplate:
    """The reference top view at the aerial image's scale, rotated to each of ``ORIENTATIONS``."""

    paint: tuple[np.ndarray, ...]
    """Per orientation, float32 1 where the reference shows paint, 0 elsewhere."""
    window: tuple[np.ndarray, ...]
    """Per orientation, float32 1 over the body and the ring around it: where the correlation looks."""
    body: tuple[np.ndarray, ...]
    """Per orientation, the body's pixels (bool)."""
    length_m: float
    """Extent of the reference's paint along the vehicle (nose up in the reference)."""
    width_m: float
    metres_per_px: float


def _hsv(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(rgb[:, :, :3]), cv2.COLOR_RGB2HSV)


def _extents(mask: np.ndarray, angle_deg: float, metres_per_px: float) -> tuple[float, float]:
    """(along, across) extent in metres of a mask's pixels for a vehicle axis rotated ``angle_deg``
    counter-clockwise from image up (the reference's nose); one pixel is added to each."""
    vs, us = np.nonzero(mask)
    if len(us) == 0:
        return 0.0, 0.0
    t = math.radians(angle_deg)
    ax, ay = -math.sin(t), -math.cos(t)
    along = us * ax + vs * ay
    across = -us * ay + vs * ax
    return (float(along.max() - along.min() + 1) * metres_per_px, float(across.max() - across.min() + 1) * metres_per_px)


def top_template(ref_top_rgba: np.ndarray, ref_metres_per_px: float, metres_per_px: float,
                 profile: TargetProfile) -> TopTemplate | None:
    """The reference top view (RGBA, background transparent, nose up) resampled to ``metres_per_px``;
    None when it shows no paint."""
    scale = ref_metres_per_px / metres_per_px
    h, w = ref_top_rgba.shape[:2]
    small = cv2.resize(ref_top_rgba, (max(3, round(w * scale)), max(3, round(h * scale))), interpolation=cv2.INTER_AREA)
    body = small[:, :, 3] > 127
    paint = shade_tolerant_paint(_hsv(small), profile) & body
    if not paint.any():
        return None
    ys, xs = np.nonzero(body)
    body, paint = body[ys.min():ys.max() + 1, xs.min():xs.max() + 1], paint[ys.min():ys.max() + 1, xs.min():xs.max() + 1]
    ring = math.ceil(RING_M / metres_per_px)
    side = math.ceil(math.hypot(*body.shape)) + 2 * ring + 3
    side += 1 - side % 2

    def centred(m: np.ndarray) -> np.ndarray:
        out = np.zeros((side, side), np.float32)
        oy, ox = (side - m.shape[0]) // 2, (side - m.shape[1]) // 2
        out[oy:oy + m.shape[0], ox:ox + m.shape[1]] = m
        return out

    b, p = centred(body), centred(paint)
    around = cv2.dilate(b.astype(np.uint8), np.ones((2 * ring + 1, 2 * ring + 1), np.uint8)).astype(np.float32)
    centre = ((side - 1) / 2.0, (side - 1) / 2.0)
    paints, windows, bodies = [], [], []
    for k in range(ORIENTATIONS):
        rot = cv2.getRotationMatrix2D(centre, 360.0 * k / ORIENTATIONS, 1.0)
        rb, rp, ra = (cv2.warpAffine(m, rot, (side, side), flags=cv2.INTER_LINEAR) for m in (b, p, around))
        paints.append((rp > 0.5).astype(np.float32))
        windows.append(((ra > 0.5) | (rb > 0.5)).astype(np.float32))
        bodies.append(rb > 0.5)
    length, width = _extents(paint, 0.0, metres_per_px)
    return TopTemplate(tuple(paints), tuple(windows), tuple(bodies), length, width, metres_per_px)


def aerial_metres_per_px(altitude_m: float, intrinsics: CameraIntrinsics, profile: TargetProfile) -> float:
    """Ground sampling of a nadir view at the height of the target's roof."""
    top = max(profile.paint_top_m, LEAN_MIN_HEIGHT_M)
    return max(altitude_m - top, 1.0) / intrinsics.fy_px


def detect_from_above_rgb(rgb: np.ndarray, profile: TargetProfile, template: TopTemplate, *,
                          intrinsics: CameraIntrinsics, world_from_camera: np.ndarray) -> list[AerialDetection]:
    """Vehicles of a nadir RGB view (no depth) with the target's paint layout, silhouette and paint,
    best first (scores in [``MIN_SCORE``, 1]).

    A candidate is a peak of the normalised correlation between the view's shade-tolerant paint
    mask and ``template`` (over its body and the ring around it), at the best of the orientations.
    Its score is the correlation minus the weighted relative errors of its paint silhouette's length
    and width (measured in world metres along the template's axis, the side a standing vehicle shows
    off-centre allowed for); the silhouette is the paint joined across glass that touches the
    template's body. Candidates whose mean hue is not the paint's are dropped; paint darker than
    ``SHADE_RELATIVE_VALUE`` of the reference loses up to ``SHADE_PENALTY`` when the ground around it is
    sunlit; of detections closer than ``NMS_LENGTH_SHARE`` of a vehicle, the best is kept. Uses the
    camera's intrinsics and pose and the reference-derived profile only.
    """
    mpp = template.metres_per_px
    hsv = _hsv(rgb)
    paint = shade_tolerant_paint(hsv, profile)
    h, w = paint.shape
    best, which = _correlation(paint, template)
    nms = max(3, int(NMS_M / mpp)) | 1
    peaks = np.argwhere((best >= cv2.dilate(best, np.ones((nms, nms), np.uint8))) & (best >= MIN_MATCH))
    if len(peaks) == 0:
        return []
    joined = cv2.morphologyEx(paint.astype(np.uint8), cv2.MORPH_CLOSE, _square(GLASS_BRIDGE_M / mpp))
    _, labels = cv2.connectedComponents(joined, connectivity=8)
    pose = np.asarray(world_from_camera, dtype=float).reshape(4, 4)
    altitude = float(pose[2, 3])
    painted_h = max(profile.paint_top_m, LEAN_MIN_HEIGHT_M)
    found = []
    street: np.ndarray | None = None
    for v, u in sorted(peaks.tolist()):
        a = int(which[v, u])
        body = _placed(template.body[a], u, v, (h, w))
        px = hsv[body]
        if mean_hue_error(px[near_hue(px, profile), 0], profile) > MEAN_HUE_TOLERANCE:
            continue
        near = cv2.dilate(body.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        ids = np.unique(labels[near & (joined > 0)])
        region = np.isin(labels, ids[ids > 0]) & paint
        angle = 360.0 * a / ORIENTATIONS
        length, width = _extents(region, angle, mpp)
        du, dv = u - intrinsics.cx_px, v - intrinsics.cy_px
        off = math.hypot(du, dv)
        lean = off * mpp * painted_h / max(altitude - painted_h, 1.0)
        t = math.radians(angle)
        along = abs(du * -math.sin(t) + dv * -math.cos(t)) / max(off, 1e-9)
        want_l = template.length_m + lean * along
        want_w = template.width_m + lean * math.sqrt(max(0.0, 1.0 - along * along))
        score = float(best[v, u]) - LENGTH_WEIGHT * abs(length - want_l) / want_l - WIDTH_WEIGHT * abs(width - want_w) / want_w
        on = body & paint
        if on.any() and float(np.median(hsv[:, :, 2][on])) < SHADE_RELATIVE_VALUE * profile.value_top:
            street = _street_points((h, w), intrinsics, pose) if street is None else street
            standing = body.astype(np.float32)  # the vehicle stands; the rest of the view is ground
            score -= SHADE_PENALTY * (1.0 - shade_score(body, rgb, standing, street))
        if score >= MIN_SCORE:
            found.append(AerialDetection(float(u), float(v), length, width, score))
    apart = max(NMS_M, NMS_LENGTH_SHARE * template.length_m) / mpp
    kept: list[AerialDetection] = []
    for det in sorted(found, key=lambda d: (-d.score, d.v_px, d.u_px)):
        if all(math.hypot(det.u_px - k.u_px, det.v_px - k.v_px) > apart for k in kept):
            kept.append(det)
    return kept


def _correlation(paint: np.ndarray, template: TopTemplate) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the best normalised correlation (over the template's window) of the paint mask
    with the template centred there, and the orientation that gives it; 0 where no paint is near.

    The correlation is OpenCV's ``TM_CCOEFF_NORMED`` with a mask, computed from two filters per
    orientation, and only in boxes around the paint (the rest of the view cannot match)."""
    h, w = paint.shape
    best = np.zeros((h, w), np.float32)
    which = np.zeros((h, w), np.int32)
    half = template.paint[0].shape[0] // 2
    near = cv2.dilate(paint.astype(np.uint8), np.ones((2 * half + 1, 2 * half + 1), np.uint8))
    n, _, stats, _ = cv2.connectedComponentsWithStats(near, connectivity=8)
    image = paint.astype(np.float32)
    for k in range(1, n):
        x, y, bw, bh = (int(c) for c in stats[k, :4])
        x0, y0, x1, y1 = max(0, x - half), max(0, y - half), min(w, x + bw + half), min(h, y + bh + half)
        crop = image[y0:y1, x0:x1]
        region = (slice(y, y + bh), slice(x, x + bw))
        inner = (slice(y - y0, y - y0 + bh), slice(x - x0, x - x0 + bw))
        for a in range(ORIENTATIONS):
            t, m = template.paint[a], template.window[a]
            n_w, n_t = float(m.sum()), float(t.sum())
            both = cv2.filter2D(crop, -1, t, borderType=cv2.BORDER_CONSTANT)[inner]
            seen = cv2.filter2D(crop, -1, m, borderType=cv2.BORDER_CONSTANT)[inner]
            spread = np.maximum(seen - seen * seen / n_w, 0.0) * max(n_t - n_t * n_t / n_w, 0.0)
            ncc = np.where(spread > 1e-6, (both - seen * n_t / n_w) / np.sqrt(np.maximum(spread, 1e-12)), 0.0)
            better = ncc > best[region]
            best[region][better] = ncc[better]
            which[region][better] = a
    return best, which


def _square(side_px: float) -> np.ndarray:
    n = max(3, math.ceil(side_px) | 1)
    return np.ones((n, n), np.uint8)


def _placed(mask: np.ndarray, u: int, v: int, shape: tuple[int, int]) -> np.ndarray:
    """A template-sized mask centred on pixel (u, v) of an image of ``shape``, clipped to it."""
    out = np.zeros(shape, bool)
    half = mask.shape[0] // 2
    ys, xs = np.nonzero(mask)
    ys, xs = ys + v - half, xs + u - half
    keep = (ys >= 0) & (xs >= 0) & (ys < shape[0]) & (xs < shape[1])
    out[ys[keep], xs[keep]] = True
    return out


def _street_points(shape: tuple[int, int], intrinsics: CameraIntrinsics, pose: np.ndarray) -> np.ndarray:
    """(H, W, 3) world points where each pixel's ray meets the street plane z = 0."""
    rays = _rays(shape, intrinsics) @ pose[:3, :3].T
    eye = pose[:3, 3]
    t = -eye[2] / np.minimum(rays[..., 2], -1e-9)
    return (eye + t[..., None] * rays).astype(np.float32)


def _rays(shape: tuple[int, int], intrinsics: CameraIntrinsics) -> np.ndarray:
    """(H, W, 3) camera-frame rays through each pixel, z = 1 (OpenCV camera)."""
    h, w = shape
    us, vs = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    return np.stack([(us - intrinsics.cx_px) / intrinsics.fx_px, (vs - intrinsics.cy_px) / intrinsics.fy_px,
                     np.ones_like(us)], -1)


# ----- from the ground ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PaintBottom:
    """Where a vehicle's paint begins above the road, read off the side reference."""

    height_m: float
    """Median over the side view's columns of the lowest painted point's height (a sill, a box's floor)."""
    low_m: float
    """Lowest plausible height: the 10th percentile over the columns, less ``BOTTOM_SLACK_M``."""
    high_m: float
    """Highest plausible height: the 90th percentile over the columns, plus ``BOTTOM_SLACK_M``."""


def paint_bottom(side_rgba: np.ndarray, intrinsics: CameraIntrinsics, world_from_camera: np.ndarray,
                 profile: TargetProfile) -> PaintBottom:
    """The paint's lower edge in the side reference: per column the lowest painted pixel's ray meets
    the vehicle's near side (a vertical plane half the paint's width from its centre line); its
    median and plausible range over the columns. ``DEFAULT_PAINT_BOTTOM_M`` when it shows no paint."""
    hsv = _hsv(side_rgba)
    mask = (side_rgba[:, :, 3] > 0) & (hue_distance(hsv[:, :, 0], profile.hue) <= HUE_TOLERANCE) & (hsv[:, :, 1] >= SAT_MIN)
    vs, us = np.nonzero(mask)
    if len(vs) == 0:
        d = DEFAULT_PAINT_BOTTOM_M
        return PaintBottom(d, max(0.0, d - BOTTOM_SLACK_M), d + BOTTOM_SLACK_M)
    cols = np.unique(us)
    lowest = np.full(mask.shape[1], -1)
    np.maximum.at(lowest, us, vs)
    vb = lowest[cols].astype(float)
    z = _near_side_heights(cols, vb, intrinsics, world_from_camera, profile.width_m)
    lo, mid, hi = (float(np.percentile(z, q)) for q in (10, 50, 90))
    return PaintBottom(max(0.0, mid), max(0.0, lo - BOTTOM_SLACK_M), hi + BOTTOM_SLACK_M)


def _lower_edge(us: np.ndarray, vs: np.ndarray) -> np.ndarray:
    """Per column of ``us`` (sorted, unique), the region's bottom edge as the lower convex hull of
    its lowest pixels (image v grows downward): wheel arches and occluded bits do not lift it."""
    hull: list[tuple[float, float]] = []
    for u, v in zip(us.tolist(), vs.tolist(), strict=True):
        while len(hull) >= 2:
            (u0, v0), (u1, v1) = hull[-2], hull[-1]
            if (u1 - u0) * (v - v0) - (v1 - v0) * (u - u0) >= 0:  # the middle point lies above the chord
                hull.pop()
            else:
                break
        hull.append((float(u), float(v)))
    hu, hv = np.array([p[0] for p in hull]), np.array([p[1] for p in hull])
    return np.interp(us, hu, hv)


@dataclass(frozen=True)
class Region:
    """A paint-hued region of a ground view placed on its vertical face (see :func:`ground_view_from_rgb`)."""

    view: str
    cols: np.ndarray
    """Its image columns, ascending."""
    reach_m: np.ndarray
    """Per column, the horizontal distance from the camera to the face it stands on."""
    x_m: float
    """Median world position of its bottom edge."""
    y_m: float


@dataclass(frozen=True)
class RgbGroundView:
    """A ground view with its estimated depth (what :func:`~agos.agents.heuristic.ground.find_target`
    reads) and the paint-hued regions that depth raised."""

    view: GroundView
    regions: tuple[Region, ...]


def ground_view_from_rgb(name: str, rgb: np.ndarray, profile: TargetProfile, *, intrinsics: CameraIntrinsics,
                         world_from_camera: np.ndarray, bottom: PaintBottom) -> RgbGroundView:
    """A :class:`~agos.agents.heuristic.ground.GroundView` of an RGB ground view with a depth image
    estimated from it: the road plane everywhere, except that each region of the paint's hue
    (joined across the glass band) stands on a vertical face at one distance from the camera.

    The region's bottom edge (the lower convex hull of its lowest pixels) is taken at
    ``bottom.height_m`` above the road, which fixes each column's distance; the region stands at
    their median. An oblique vehicle then measures its extent across the line of sight, which for
    the target stays within its length plus the heuristic's ``LENGTH_TOLERANCE_M``. Where the paint
    begins is known only within ``bottom``'s range, and a region standing taller than the camera
    is sensitive to it (its top's height scales with the distance): the region's distance is then
    scaled, within what that range allows, towards the one that puts its top at the reference's
    painted top. A car's top is near the camera's height, so its scale
    barely moves it; a box truck's top 1.6 m above the camera may move by a few decimetres.
    """
    h, w = rgb.shape[:2]
    pose = np.asarray(world_from_camera, dtype=float).reshape(4, 4)
    rot, eye = pose[:3, :3], pose[:3, 3]
    world_rays = _rays((h, w), intrinsics) @ rot.T
    down = world_rays[..., 2] < -1e-6
    depth = np.full((h, w), FAR_M)
    depth[down] = np.minimum(-eye[2] / world_rays[..., 2][down], FAR_M)  # camera rays have z = 1: t is the depth
    hsv = _hsv(rgb)
    bright = hsv[:, :, 2] >= MIN_PAINT_VALUE
    dark = 0.75 * min(profile.value_side[0], profile.value_top)
    hued = ((near_hue(hsv, profile) | hue_match(hsv, profile, dark_below=dark)) & bright).astype(np.uint8)
    hued = cv2.morphologyEx(hued, cv2.MORPH_OPEN, np.ones((2, 2), np.uint8))
    joined = cv2.morphologyEx(hued, cv2.MORPH_CLOSE, np.ones(GROUND_CLOSE_PX, np.uint8))
    n, labels = cv2.connectedComponents(joined, connectivity=8)
    horizontal = np.hypot(world_rays[..., 0], world_rays[..., 1])
    drop = eye[2] - bottom.height_m
    regions = []
    for k in range(1, n):
        vs, us = np.nonzero(labels == k)
        if len(us) < MIN_REGION_PX or drop <= 0:
            continue
        cols = np.unique(us)
        lowest = np.full(w, -1)
        np.maximum.at(lowest, us, vs)
        edge = _lower_edge(cols, lowest[cols])
        ray = np.stack([(cols - intrinsics.cx_px) / intrinsics.fx_px, (edge - intrinsics.cy_px) / intrinsics.fy_px,
                        np.ones(len(cols))], -1) @ rot.T
        meets = ray[:, 2] < -1e-6
        if not meets.any():
            continue  # its lowest pixels look above the horizon: it does not stand on the road in view
        # One distance for the whole region, the median of its columns': a column's distance is
        # sensitive to a pixel of its edge (0.4 m a pixel at 10 m), and per-column distances
        # stretch an oblique vehicle along the line of sight past its length.
        reach = np.full(len(cols), float(np.median(drop / -ray[meets, 2] * np.hypot(ray[meets, 0], ray[meets, 1]))))
        t = reach[0] / np.maximum(horizontal[vs, us], 1e-9)
        rise = world_rays[vs, us, 2] * t  # height above the camera at scale 1
        top = float(np.percentile(rise, 98))
        want = profile.paint_top_m - eye[2]
        if abs(top) > 1e-3 and want * top > 0:
            lo, hi = (eye[2] - bottom.high_m) / drop, (eye[2] - bottom.low_m) / drop
            scale = min(max(want / top, lo), hi)
            t *= scale
            reach *= scale
        depth[vs, us] = np.minimum(t, FAR_M)
        ground = eye[:2] + ray[:, :2] / np.maximum(np.hypot(ray[:, 0], ray[:, 1]), 1e-9)[:, None] * reach[:, None]
        x, y = np.median(ground, axis=0)
        regions.append(Region(name, cols, reach, float(x), float(y)))
    return RgbGroundView(GroundView(name, rgb, depth.astype(np.float32), intrinsics, pose), tuple(regions))


@dataclass(frozen=True)
class Cap:
    """What the side reference shows on top of the paint: a roof box, a roof in a contrasting colour."""

    present: bool
    saturation: float
    """Median HSV saturation of its pixels (0 when absent)."""
    value: float


def reference_cap(side_rgba: np.ndarray, intrinsics: CameraIntrinsics, world_from_camera: np.ndarray,
                  profile: TargetProfile) -> Cap:
    """The part of the side reference's silhouette standing ``CAP_GAP_M`` or more above its painted
    top (heights where the rays meet the vehicle's near side) that is not paint, when it has
    ``CAP_MIN_PX`` pixels."""
    body = side_rgba[:, :, 3] > 0
    vs, us = np.nonzero(body)
    if len(vs) == 0:
        return Cap(False, 0.0, 0.0)
    z = _near_side_heights(us, vs, intrinsics, world_from_camera, profile.width_m)
    hsv = _hsv(side_rgba)[vs, us]
    paint = (hue_distance(hsv[:, 0], profile.hue) <= HUE_TOLERANCE) & (hsv[:, 1] >= SAT_MIN)
    above = (z >= profile.paint_top_m + CAP_GAP_M) & ~paint
    if int(above.sum()) < CAP_MIN_PX:
        return Cap(False, 0.0, 0.0)
    px = hsv[above]
    return Cap(True, float(np.median(px[:, 1])), float(np.median(px[:, 2])))


def cap_share(view: GroundView, region: Region, top_m: float, cap: Cap) -> float:
    """How much more of the band just above an object's painted top (``CAP_GAP_M`` to ``CAP_BAND_M``
    higher, on the face the region stands on) looks like ``cap`` (or, with no cap, like a roof box:
    grey, ``BOX_SATURATION`` or less) over the middle half of the region's columns than beside the
    region, in as many columns either side: something standing on the roof, not the background
    behind it. 0 when none of the band is in view."""
    hsv = _hsv(view.rgb)
    h, w = hsv.shape[:2]
    rays = _rays((h, w), view.intrinsics) @ view.world_from_camera[:3, :3].T
    eye_z = float(view.world_from_camera[2, 3])
    n = len(region.cols)
    quarter = max(1, n // 4)
    reach = float(np.median(region.reach_m))
    lo, hi = int(region.cols[0]), int(region.cols[-1])
    middle = region.cols[quarter:max(quarter + 1, n - quarter)]
    beside = np.concatenate([np.arange(lo - quarter, lo), np.arange(hi + 1, hi + 1 + quarter)])
    beside = beside[(beside >= 0) & (beside < w)]

    def share(cols: np.ndarray) -> float | None:
        hits = total = 0
        for c in cols.tolist():
            col = rays[:, c]
            z = eye_z + reach * col[:, 2] / np.maximum(np.hypot(col[:, 0], col[:, 1]), 1e-9)
            px = hsv[(z >= top_m + CAP_GAP_M) & (z <= top_m + CAP_BAND_M), c].astype(np.float32)
            if cap.present:
                like = ((np.abs(px[:, 1] - cap.saturation) <= CAP_SAT_TOLERANCE)
                        & (np.abs(px[:, 2] - cap.value) <= CAP_VALUE_TOLERANCE))
            else:
                like = (px[:, 1] <= BOX_SATURATION) & (px[:, 2] >= BOX_VALUE[0]) & (px[:, 2] <= BOX_VALUE[1])
            hits += int(like.sum())
            total += len(px)
        return hits / total if total else None

    above, aside = share(middle), share(beside)
    if above is None:
        return 0.0
    return max(0.0, above - (aside or 0.0))


def find_target_rgb(views: list[RgbGroundView], profile: TargetProfile, *, min_pixels: int,
                    cap: Cap | None = None) -> list[GroundObject]:
    """:func:`~agos.agents.heuristic.ground.find_target` over views from :func:`ground_view_from_rgb`,
    against the reference's painted top (the estimated depth raises only paint-hued pixels, so an
    object's top is its paint's top), best first. With ``cap`` (the side reference's
    :func:`reference_cap`), what stands on the paint is checked too: a target with a cap needs at
    least ``CAP_MIN_SHARE`` of the band above an object's paint to look like it, a target without
    one refuses an object whose band is ``BOX_MAX_SHARE`` or more a grey box."""
    painted = dataclasses.replace(profile, body_height_m=profile.paint_top_m)
    found = find_target([v.view for v in views], painted, min_pixels=min_pixels)
    if cap is None:
        return found
    by_name = {v.view.name: v for v in views}
    kept = []
    for obj in found:
        shares = [cap_share(by_name[name].view, region, obj.top_m, cap)
                  for name in obj.views for region in by_name[name].regions
                  if math.hypot(region.x_m - obj.x_m, region.y_m - obj.y_m) <= REGION_MATCH_M]
        if not shares:
            continue
        share = max(shares) if cap.present else min(shares)
        if (share >= CAP_MIN_SHARE) if cap.present else (share < BOX_MAX_SHARE):
            kept.append(obj)
    return kept


def _near_side_heights(us: np.ndarray, vs: np.ndarray, intrinsics: CameraIntrinsics,
                       world_from_camera: np.ndarray | list[float], width_m: float) -> np.ndarray:
    """Heights above the road where the rays through pixels (``us``, ``vs``) of a side reference meet
    the vehicle's near side (a vertical plane ``width_m`` / 2 from its centre line)."""
    pose = np.asarray(world_from_camera, dtype=float).reshape(4, 4)
    rays = pose[:3, :3] @ np.stack([(us - intrinsics.cx_px) / intrinsics.fx_px, (vs - intrinsics.cy_px) / intrinsics.fy_px,
                                    np.ones(len(us))])
    eye = pose[:3, 3]
    near = math.hypot(eye[0], eye[1]) - width_m / 2
    return eye[2] + near / np.maximum(np.hypot(rays[0], rays[1]), 1e-9) * rays[2]
