"""Can a viewer tell a target from its look-alikes? A separability floor for hard episodes (issue 22, item 8).

For every kind of look-alike pair hard episodes use (world/episodes/lookalikes.py: same paint on
another body type; same type in a near paint; same type and paint with one attribute more or less),
both vehicles are rendered many times in a real town and cropped as an agent's camera sees them;
a linear classifier (scikit-learn ``LinearSVC``) on HOG features (scikit-image ``hog``) plus a 4 x 4
grid of mean colours is trained and tested on the crops, and the share of test crops it labels
right is printed, one line per pair and view::

    cue <look> <view> <A> vs <B>: NN.N%

It is a floor on what the pixels carry (a simple model sees at least this much), never a realism
score. Goal for the rich look: every pair the sampler uses at least 90 % from the ground; the
lines of the rich look's ground view end with the table ``CUE_GROUND_PCT`` to paste into
world/episodes/lookalikes.py (the sampler uses a pair only at 90 % or more).

Its noise. ``--repeats N`` runs N times at seeds ``--seed``, ``--seed`` + 1, ... (new poses each
time), prints every pair's mean, the sd of one run and the range, and ends with three tables to
paste: ``CUE_GROUND_PCT`` (the means), ``CUE_GROUND_SD`` (the sd of one run) and ``CUE_CHECK_PCT``
(mean and sd of the figure measured on ``CUE_CHECK_CROPS`` crops a class, over the disjoint blocks
of consecutive poses the runs hold: five a run of 300 crops in blocks of 60). Re-measure whenever
the look, the meshes, the ground camera or the town's traffic changes.

``--check`` measures the rich look's ground pairs once on ``CUE_CHECK_CROPS`` crops a class at a
fixed seed (``CHECK_SEED``, never one of the pinned runs) and compares each figure with its
``CUE_CHECK_PCT`` reference: a pair further than ``CHECK_Z`` sd from it (the sd taken as at least
``CHECK_MIN_SD``) is named and the exit status is 1. A smaller classifier is trained on fewer
crops, so the check compares with the reference measured at its own size, never with the table
itself. ``make bench`` runs it (bench/run_all.py), and a failure there fails ``make bench``.

How a crop is made. A *pose* is drawn per index from the seed: a free, uncovered parking slot
whose neighbours are free (a bus fits), a heading along the slot or reversed (the world has one
sun: the light comes from any side of the vehicle, and buildings' drawn shadows darken some), a
paint, a body type and a car type (the attribute pairs: only cars carry attributes); a ground
camera at a road decision anchor 10 to 25 m away (``--distance-m``: where a UGV that comes to
check a parked car stops) with a line of sight to it; and a UAV camera 80 m up, the vehicle
anywhere in its nadir view. Every class of a kind is rendered at the same poses (paired design),
with the town, its parked traffic and trees around it; a white roof and a stripe in the paint's
contrast colour, as the sampler paints them. The view is rendered as a window of the agent's
camera centred on the vehicle (same focal length in pixels as ``CameraConfig``: 256 px over 70
deg on the ground, 512 px over 60 deg from the air), JPEG-encoded at the quality agents receive,
decoded, and cropped by the instance mask: from the ground a square around the mask's box,
scaled to 64 px; from the air the mask's box turned so its long axis is horizontal, scaled to
64 x 32 px, with the mask's length and width in pixels as two more features (the UAV knows its
scale). Partial occlusion is controlled: the vehicle's unoccluded silhouette is projected
from its mesh, and crops with less than ``--min-visible`` of it in view are left out (the mean
visible share is printed). Crops are split by pose into three folds (poses of the test fold are
never seen in training); each crop is tested once.

    .venv/bin/python bench/bench_cues.py                        # both looks, both views, 300 crops a class
    .venv/bin/python bench/bench_cues.py --looks rich --views ground --repeats 3   # the tables to paste
    .venv/bin/python bench/bench_cues.py --check                # the pinned tables still true?
    .venv/bin/python bench/bench_cues.py --looks rich --views ground --ground-px 384
    .venv/bin/python bench/bench_cues.py --quick                # smoke test, a few seconds
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from figures import Figures

from agos.runtime.codec import decode_image, encode_jpeg
from agos.runtime.episode_config import CameraConfig
from agos.runtime.process import interruptible_imap
from agos.world.episodes.lookalikes import (
    ATTRIBUTES,
    CUE_CHECK_CROPS,
    CUE_CHECK_PCT,
    CUE_GROUND_PCT,
    MIN_CUE_PCT,
    PLAIN,
    pair_key,
    pairs,
)
from agos.world.episodes.sampling import long_slots
from agos.world.sim import sensors
from agos.world.sim.evidence import target_points
from agos.world.sim.scene import Scene
from agos.world.towns.asset import Town, open_town
from agos.world.towns.catalog import BODY_TYPES, VIVID_COLOURS, body_type
from agos.world.towns.look.vehicles import (
    ATTRIBUTE_BODY_TYPES,
    RICH_BODY_TYPES,
    ROOF_COLOUR,
    VehicleAttributes,
    contrast_colour,
    vehicle_mesh,
)

VIEWS = ("ground", "air")
LOOKS = ("flat", "rich")
GROUND_CROP_PX = 64
AIR_CROP_PX = (64, 32)
"""Air crops, width along the vehicle's axis."""
AIR_WINDOW_PX = 96
FOLDS = 3
QUICK_CLASSES = {"type": ("sedan", "suv"), "paint": ("red", "maroon"), "attribute": (PLAIN, "roof")}
CHECK_SEED = 101
"""``--check``'s poses: a seed the pinned runs did not use (they start at 1)."""
CHECK_Z = 3.5
"""``--check`` fails a pair further than this many sd from its reference (29 pairs: about one false
alarm in 70 checks of an unchanged world, were the figures normal)."""
CHECK_MIN_SD = 1.5
"""The least sd ``--check`` assumes, in points: pairs near 100 % show almost none over the blocks."""


@dataclass(frozen=True)
class Settings:
    town: str
    crops: int
    seed: int
    ground_px: int
    nadir_px: int
    ground_fov_deg: float
    nadir_fov_deg: float
    altitude_m: float
    distance_m: tuple[float, float]
    min_visible: float
    views: tuple[str, ...]
    keep_images: int = 8
    """Crops kept as images per class and view (for the contact sheet)."""


@dataclass(frozen=True)
class Pose:
    index: int
    slot_xy: tuple[float, float]
    yaw_rad: float
    ground_eye_xy: tuple[float, float]
    air_eye_xy: tuple[float, float]
    paint: str
    model: str
    """Body type of the paint kind's classes."""
    car: str
    """Body type of the attribute kind's classes (a car: the types that carry attributes)."""


@dataclass(frozen=True)
class Job:
    settings: Settings
    look: str
    kind: str
    classes: tuple[str, ...]
    indices: tuple[int, ...]


@dataclass
class Crops:
    """Crops of one class in one view: features, pose indices, visible shares, a few images."""

    features: list[np.ndarray] = field(default_factory=list)
    poses: list[int] = field(default_factory=list)
    visible: list[float] = field(default_factory=list)
    distance_m: list[float] = field(default_factory=list)
    """Ground: from the camera to the vehicle; air: the vehicle's horizontal offset from the camera."""
    images: list[np.ndarray] = field(default_factory=list)
    image_poses: list[int] = field(default_factory=list)

    def add(self, other: Crops) -> None:
        self.features += other.features
        self.poses += other.poses
        self.visible += other.visible
        self.distance_m += other.distance_m
        self.images += other.images
        self.image_poses += other.image_poses

    def in_pose_order(self, keep_images: int) -> Crops:
        """The crops by pose index, and the first ``keep_images`` images (workers finish in any order;
        nothing the bench prints or draws may depend on it)."""
        order = sorted(range(len(self.poses)), key=self.poses.__getitem__)
        shown = sorted(range(len(self.image_poses)), key=self.image_poses.__getitem__)[:keep_images]
        return Crops([self.features[i] for i in order], [self.poses[i] for i in order],
                     [self.visible[i] for i in order], [self.distance_m[i] for i in order],
                     [self.images[i] for i in shown], [self.image_poses[i] for i in shown])


# ----- vocabulary ---------------------------------------------------------------------------------
def classes_of(look: str, kind: str, quick: bool = False) -> tuple[str, ...]:
    """The classes a kind's pairs are made of (every pair of a kind is among them)."""
    names = sorted({name for pair in pairs(look)[kind] for name in pair})
    if quick:
        names = [n for n in names if n in QUICK_CLASSES[kind]]
    return tuple(names)


def vehicle_of(kind: str, cls: str, pose: Pose) -> tuple[str, str, VehicleAttributes]:
    """(body type, paint, attributes) of class ``cls`` at a pose: only the kind's cue varies."""
    if kind == "type":
        return cls, pose.paint, VehicleAttributes()
    if kind == "paint":
        return pose.model, cls, VehicleAttributes()
    attrs = {PLAIN: VehicleAttributes(), "roof": VehicleAttributes(roof=ROOF_COLOUR),  # as the sampler paints them
             "rack": VehicleAttributes(rack=True), "stripe": VehicleAttributes(stripe=contrast_colour(pose.paint))}
    return pose.car, pose.paint, attrs[cls]


# ----- poses --------------------------------------------------------------------------------------
def open_slots(town: Town) -> list[tuple[float, float, float]]:
    """Uncovered, off-plaza slots a bus fits in (sampling.long_slots): (x, y, yaw)."""
    fits = long_slots(town.layout)
    return [(*s.position_world_m, s.yaw_rad) for s in town.layout.slots
            if s.slot_id in fits and not s.covered and not s.plaza]


def draw_pose(index: int, s: Settings, look: str, town: Town, scene: Scene, slots: list) -> Pose:
    """The pose of one index: the same for every class and kind of a look (paired design)."""
    rng = np.random.default_rng(np.random.SeedSequence([s.seed, index]))
    types = RICH_BODY_TYPES if look == "rich" else tuple(sorted(BODY_TYPES))
    _ids, xy = town.roads.anchor_array()
    half_air_m = 0.9 * s.altitude_m * math.tan(math.radians(s.nadir_fov_deg / 2))
    while True:
        x, y, yaw = slots[int(rng.integers(len(slots)))]
        yaw = float(yaw + (math.pi if rng.random() < 0.5 else 0.0))
        paint, model, car = str(rng.choice(VIVID_COLOURS)), str(rng.choice(types)), str(rng.choice(ATTRIBUTE_BODY_TYPES))
        air = (float(x + rng.uniform(-half_air_m, half_air_m)), float(y + rng.uniform(-half_air_m, half_air_m)))
        d = np.hypot(xy[:, 0] - x, xy[:, 1] - y)
        near = [int(k) for k in np.flatnonzero((d >= s.distance_m[0]) & (d <= s.distance_m[1]))]
        rng.shuffle(near)
        uid = scene.add_vehicle("sedan", "red", (x, y, 0.0), yaw)
        try:
            points = target_points((x, y, 0.0), yaw)
            for k in near:
                eye = np.array([xy[k, 0], xy[k, 1], sensors.UGV_CAMERA_HEIGHT_M])
                if scene.line_of_sight(eye, uid, points):
                    return Pose(index, (x, y), yaw, (float(xy[k, 0]), float(xy[k, 1])), air, paint, model, car)
        finally:
            scene.remove(uid)


# ----- rendering and cropping ---------------------------------------------------------------------
def body_triangles(look: str, model: str, attrs: VehicleAttributes) -> np.ndarray:
    """(T, 3, 3) triangles (or box faces as triangles) of a vehicle in its own frame."""
    if look == "rich":
        return np.concatenate(list(vehicle_mesh(model, attrs).triangles.values()))
    tris = []
    parts = body_type(model).parts
    base = np.array([parts[0].center_m[0], parts[0].center_m[1], 0.0])  # the flat look centres its first box
    for part in parts:
        c, h = np.asarray(part.center_m) - base, np.asarray(part.half_extents_m)
        corners = np.array([c + h * [sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        for a, b, d in ((0, 1, 3), (0, 3, 2), (4, 5, 7), (4, 7, 6), (0, 1, 5), (0, 5, 4), (2, 3, 7), (2, 7, 6),
                        (0, 2, 6), (0, 6, 4), (1, 3, 7), (1, 7, 5)):
            tris.append(corners[[a, b, d]])
    return np.asarray(tris)


def silhouette(tris_vehicle: np.ndarray, xy: tuple[float, float], yaw: float, shot: sensors.Shot) -> np.ndarray:
    """The vehicle's unoccluded silhouette in a shot, projected from its triangles."""
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    pts = tris_vehicle.reshape(-1, 3) @ rot.T + [xy[0], xy[1], 0.0]
    cam = (pts - shot.world_from_camera[:3, 3]) @ shot.world_from_camera[:3, :3]
    k = shot.intrinsics
    uv = np.column_stack([k.fx_px * cam[:, 0] / cam[:, 2] + k.cx_px, k.fy_px * cam[:, 1] / cam[:, 2] + k.cy_px])
    up = 4  # drawn at 4x and averaged: a pixel counts when half of it is covered, as in a render
    mask = np.zeros((k.height_px * up, k.width_px * up), np.uint8)
    for poly in np.round(uv * up - 0.5).astype(np.int32).reshape(-1, 3, 2):  # one by one: fillPoly of
        cv2.fillConvexPoly(mask, poly, 255)  # many polygons fills their overlaps even-odd
    mask = cv2.resize(mask, (k.width_px, k.height_px), interpolation=cv2.INTER_AREA) >= 128
    return mask


def window(scene: Scene, s: Settings, view: str, eye_xy: tuple[float, float], centre: np.ndarray,
           radius_m: float) -> sensors.Shot:
    """The part of the agent's camera around the vehicle, at the camera's own pixel scale."""
    if view == "ground":
        eye = np.array([eye_xy[0], eye_xy[1], sensors.UGV_CAMERA_HEIGHT_M])
        f_px = (s.ground_px / 2) / math.tan(math.radians(s.ground_fov_deg / 2))
        half = math.asin(min(radius_m / float(np.linalg.norm(centre - eye)), 0.99)) + math.radians(3.0)
        size = min(s.ground_px, math.ceil(2 * f_px * math.tan(half)) // 2 * 2)
        up = np.array([0.0, 0.0, 1.0])
    else:
        eye = np.array([eye_xy[0], eye_xy[1], s.altitude_m + 0.013])
        f_px = (s.nadir_px / 2) / math.tan(math.radians(s.nadir_fov_deg / 2))
        size = AIR_WINDOW_PX
        up = np.array([0.0, 1.0, 0.0])
    return sensors.shoot(scene, view, eye, centre - eye, up, math.degrees(2 * math.atan(size / 2 / f_px)), size)


def ground_crop(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """A square around the mask's box (15 % margin), scaled to GROUND_CROP_PX."""
    ys, xs = np.nonzero(mask)
    cx, cy = (xs.min() + xs.max() + 1) / 2, (ys.min() + ys.max() + 1) / 2
    side = max(2, round(1.15 * max(xs.max() - xs.min() + 1, ys.max() - ys.min() + 1)))
    pad = side + 2
    big = cv2.copyMakeBorder(rgb, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    x0, y0 = round(cx - side / 2) + pad, round(cy - side / 2) + pad
    n = GROUND_CROP_PX
    return cv2.resize(big[y0:y0 + side, x0:x0 + side], (n, n),
                      interpolation=cv2.INTER_AREA if side > n else cv2.INTER_LINEAR)


def air_crop(rgb: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mask's box turned so its long axis is horizontal (15 % margin, 2:1), scaled to
    AIR_CROP_PX, and the mask's length and width in pixels (the nadir scale is known: size is a cue)."""
    ys, xs = np.nonzero(mask)
    cx, cy = float(xs.mean()), float(ys.mean())
    cov = np.cov(np.vstack([xs - cx, ys - cy])) if len(xs) > 2 else np.eye(2)
    angle = 0.5 * math.degrees(math.atan2(2 * cov[0, 1], cov[0, 0] - cov[1, 1]))
    m = cv2.getRotationMatrix2D((cx, cy), angle, 1.0)
    turned = np.column_stack([xs, ys, np.ones(len(xs))]) @ m.T
    length, width = np.ptp(turned[:, 0]) + 1, np.ptp(turned[:, 1]) + 1
    w, h = AIR_CROP_PX
    scale = w / (1.15 * max(length, 2 * width))
    m = cv2.getRotationMatrix2D((cx, cy), angle, scale)
    m[:, 2] += [w / 2 - cx, h / 2 - cy]
    crop = cv2.warpAffine(rgb, m, (w, h), flags=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE)
    return crop, np.array([length, width], np.float32) / 16.0


def features(crop: np.ndarray, extra: np.ndarray | None = None) -> np.ndarray:
    """HOG of the crop (gradients of the strongest colour channel), a 4 x 4 grid of mean Lab colours
    and ``extra`` (the air crops' size)."""
    from skimage.feature import hog

    grad = hog(crop, orientations=9, pixels_per_cell=(8, 8), cells_per_block=(2, 2), channel_axis=-1,
               feature_vector=True)
    lab = cv2.resize(cv2.cvtColor(crop, cv2.COLOR_RGB2LAB), (4, 4), interpolation=cv2.INTER_AREA)
    parts = [grad, lab.astype(np.float64).ravel() / 255.0] + ([] if extra is None else [extra])
    return np.concatenate(parts).astype(np.float32)


_WORKER: dict[str, Any] = {}


def _scene(s: Settings, look: str) -> tuple[Town, Scene, list]:
    if _WORKER.get("town_name") != s.town:
        for scene in _WORKER.get("scenes", {}).values():
            scene.close()
        town = open_town(s.town)
        _WORKER.update(town_name=s.town, town=town, scenes={}, slots=open_slots(town))
    scenes = _WORKER["scenes"]
    if look not in scenes:
        scenes[look] = Scene(_WORKER["town"].layout, look=look)
    return _WORKER["town"], scenes[look], _WORKER["slots"]


def render_job(job: Job) -> tuple[Job, dict[tuple[str, str], Crops]]:
    """Crops of every class of a kind at the job's poses, per view; occluded ones left out."""
    s = job.settings
    town, scene, slots = _scene(s, job.look)
    out: dict[tuple[str, str], Crops] = defaultdict(Crops)
    for index in job.indices:
        pose = draw_pose(index, s, job.look, town, scene, slots)
        for cls in job.classes:
            model, paint, attrs = vehicle_of(job.kind, cls, pose)
            tris = body_triangles(job.look, model, attrs)
            height = float(tris[:, :, 2].max())
            centre = np.array([pose.slot_xy[0], pose.slot_xy[1], height / 2])
            radius = float(np.linalg.norm(tris.reshape(-1, 3)[:, :2], axis=1).max())
            radius = math.hypot(radius, height / 2)
            uid = scene.add_vehicle(model, paint, (*pose.slot_xy, 0.0), pose.yaw_rad,
                                    attributes=attrs if job.look == "rich" else None)
            try:
                for view in s.views:
                    eye_xy = pose.ground_eye_xy if view == "ground" else pose.air_eye_xy
                    shot = window(scene, s, view, eye_xy, centre, radius)
                    mask = shot.render.instance == uid
                    full = silhouette(tris, pose.slot_xy, pose.yaw_rad, shot)
                    visible = float(np.count_nonzero(mask & full) / max(1, np.count_nonzero(full)))
                    if visible < s.min_visible or np.count_nonzero(mask) < 4:
                        continue
                    rgb = decode_image(encode_jpeg(shot.render.rgb))
                    crop, extra = (ground_crop(rgb, mask), None) if view == "ground" else air_crop(rgb, mask)
                    c = out[(cls, view)]
                    c.features.append(features(crop, extra))
                    c.poses.append(index)
                    c.visible.append(visible)
                    c.distance_m.append(math.dist(eye_xy, pose.slot_xy))
                    if len(c.images) < s.keep_images:
                        c.images.append(crop)
                        c.image_poses.append(index)
            finally:
                scene.remove(uid)
    return job, dict(out)


# ----- classification -----------------------------------------------------------------------------
def pair_predictions(a: Crops, b: Crops, n: int, start: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Whether each crop is labelled right, each tested once by a linear SVM trained on the other
    folds of poses (fold = pose index mod 3), and its distance; ``n`` crops of each class from the
    ``start``-th (in pose order)."""
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler
    from sklearn.svm import LinearSVC

    span = slice(start, start + n)
    fa, fb = a.features[span], b.features[span]
    x = np.vstack([np.asarray(fa), np.asarray(fb)])
    y = np.concatenate([np.zeros(len(fa)), np.ones(len(fb))])
    fold = np.concatenate([np.asarray(a.poses[span]), np.asarray(b.poses[span])]) % FOLDS
    right = np.zeros(len(y), bool)
    for f in range(FOLDS):
        train, test = fold != f, fold == f
        if not test.any() or len(set(y[train])) < 2:
            continue
        model = make_pipeline(StandardScaler(), LinearSVC(C=0.001, max_iter=10000, random_state=0))
        model.fit(x[train], y[train])
        right[test] = model.predict(x[test]) == y[test]
    return right, np.concatenate([np.asarray(a.distance_m[span]), np.asarray(b.distance_m[span])])


PairId = tuple[str, str, str, str, str]
"""(look, view, kind, a, b), a < b."""


def pair_ids(looks: tuple[str, ...], views: tuple[str, ...], quick: bool) -> list[PairId]:
    """The pairs a run measures, in the order it prints them."""
    out = []
    for look in looks:
        for view in views:
            for kind, kind_pairs in pairs(look).items():
                classes = classes_of(look, kind, quick)
                out += [(look, view, kind, a, b) for a, b in kind_pairs if a in classes and b in classes]
    return out


def pair_crops(crops: dict[tuple[str, str, str, str], Crops], pid: PairId) -> tuple[Crops, Crops]:
    look, view, kind, a, b = pid
    return crops[(look, kind, a, view)], crops[(look, kind, b, view)]


def block_pcts(crops: dict[tuple[str, str, str, str], Crops], pid: PairId, total: int, block: int) -> list[float]:
    """The pair's accuracy on each of ``total // block`` disjoint blocks of ``block`` crops a class
    (consecutive poses): as many independent measurements of the ``--check`` size as the run holds."""
    a, b = pair_crops(crops, pid)
    return [100.0 * float(pair_predictions(a, b, block, k * block)[0].mean()) for k in range(total // block)]


# ----- the run ------------------------------------------------------------------------------------
def plan(s: Settings, keys: set[tuple[str, str]], quick: bool, start: dict, count: int, chunk: int) -> list[Job]:
    """Jobs for the next ``count`` poses of every (look, kind) in ``keys``, in chunks; advances ``start``."""
    jobs = []
    for look, kind in sorted(keys):
        classes = classes_of(look, kind, quick)
        first = start[(look, kind)]
        for k in range(first, first + count, chunk):
            jobs.append(Job(s, look, kind, classes, tuple(range(k, min(first + count, k + chunk)))))
        start[(look, kind)] = first + count
    return jobs


def run(s: Settings, looks: tuple[str, ...], *, quick: bool, workers: int) -> dict[tuple[str, str, str, str], Crops]:
    """Crops per (look, kind, class, view) until every class has ``s.crops`` in every view: a first
    round of 1.2 x as many poses (some crops are left out as occluded), then more if short."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    crops: dict[tuple[str, str, str, str], Crops] = defaultdict(Crops)
    start: dict[tuple[str, str], int] = defaultdict(int)
    chunk = 4 if quick else 20
    todo = {(look, kind) for look in looks for kind in pairs(look)}
    count = math.ceil(1.2 * s.crops)
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                  transient=True) as progress:
        bars = {key: progress.add_task(f"{key[0]} {key[1]}: poses", total=count) for key in sorted(todo)}
        while todo:
            jobs = plan(s, todo, quick, start, count, chunk)
            jobs.sort(key=lambda j: (j.indices[0], j.look, j.kind))  # every kind advances together
            results = interruptible_imap(render_job, jobs, workers) if workers > 1 else map(render_job, jobs)
            for job, got in results:
                for (cls, view), c in got.items():
                    crops[(job.look, job.kind, cls, view)].add(c)
                progress.advance(bars[(job.look, job.kind)], len(job.indices))
            for key in list(todo):
                have = min(len(crops[(*key, cls, view)].features) for cls in classes_of(*key, quick) for view in s.views)
                if have >= s.crops:
                    todo.discard(key)
                else:
                    progress.update(bars[key], total=start[key] + chunk)
            count = chunk
    return {key: c.in_pose_order(s.keep_images) for key, c in crops.items()}


def report(s: Settings, looks: tuple[str, ...], crops: dict, quick: bool, *, table: bool = True) -> dict[PairId, float]:
    """Prints one line per pair and view, the visible shares and (``table``) the rich look's ground
    table; the figures by pair."""
    lines, pcts = [], {}
    for look in looks:
        for view in s.views:
            for pid in pair_ids((look,), (view,), quick):
                right, dist = pair_predictions(*pair_crops(crops, pid), s.crops)
                pct = pcts[pid] = 100.0 * float(right.mean())
                line = f"cue {look} {view} {pid[3]} vs {pid[4]}: {pct:.1f}%"
                if view == "ground" and pct < MIN_CUE_PCT and not quick:
                    mid = sum(s.distance_m) / 2
                    near, far = right[dist <= mid], right[dist > mid]
                    line += (f"   ({s.distance_m[0]:.0f}-{mid:.1f} m: {100 * near.mean():.1f}%, "
                             f"{mid:.1f}-{s.distance_m[1]:.0f} m: {100 * far.mean():.1f}%)")
                lines.append(line)
            if look == "flat":
                lines.append(f"cue flat {view} plain vs {'/'.join(ATTRIBUTES)}: n/a (the flat look draws no attributes)")
    for line in lines:
        print(line)
    for look in looks:
        for view in s.views:
            vis = [v for key, c in crops.items() if key[0] == look and key[3] == view for v in c.visible]
            if vis:
                print(f"visible share of kept crops, {look} {view}: mean {np.mean(vis):.2f}, min {np.min(vis):.2f}")
    ground = {pair_key(*pid[2:]): pct for pid, pct in pcts.items() if pid[:2] == ("rich", "ground")}
    if table and ground:
        print(f"\n# rich look, ground {s.ground_px} px, {s.crops} crops a class, seed {s.seed} "
              f"(bench/bench_cues.py); pairs below {MIN_CUE_PCT:.0f} are not sampled")
        print_dict("CUE_GROUND_PCT", "float", {k: f"{v:.1f}" for k, v in ground.items()})
    return pcts


def print_dict(name: str, value_type: str, values: dict[tuple[str, str, str], str]) -> None:
    print(f"{name}: dict[tuple[LookalikeKind, str, str], {value_type}] = {{")
    for key in sorted(values):
        print(f"    {key!r}: {values[key]},")
    print("}")


def sd(values: list[float]) -> float:
    """Sample standard deviation (0 for one value)."""
    return float(np.std(values, ddof=1)) if len(values) > 1 else 0.0


def summary(s: Settings, seeds: list[int], runs: list[dict[PairId, float]], blocks: dict[PairId, list[float]]) -> None:
    """Mean and spread of every pair over the repeats; for the rich look's ground view, the three
    tables to paste into world/episodes/lookalikes.py."""
    print(f"\n{len(seeds)} runs (seeds {', '.join(map(str, seeds))}), {s.crops} crops a class each: "
          "mean, sd of one run, range")
    ground_pct, ground_sd = {}, {}
    for pid in runs[0]:
        values = [r[pid] for r in runs]
        mean = float(np.mean(values))
        print(f"cue {pid[0]} {pid[1]} {pid[3]} vs {pid[4]}: mean {mean:.1f}%, sd {sd(values):.1f} "
              f"({min(values):.1f}-{max(values):.1f}: {' / '.join(f'{v:.1f}' for v in values)})")
        if pid[:2] == ("rich", "ground"):
            ground_pct[pair_key(*pid[2:])], ground_sd[pair_key(*pid[2:])] = mean, sd(values)
    if not ground_pct:
        return
    spread = list(ground_sd.values())
    print(f"sd of one run, rich ground: median {np.median(spread):.1f}, root mean square "
          f"{math.sqrt(np.mean(np.square(spread))):.1f}, max {max(spread):.1f} points")
    print(f"\n# rich look, ground {s.ground_px} px, {s.crops} crops a class, mean of {len(seeds)} runs (seeds "
          f"{', '.join(map(str, seeds))}; bench/bench_cues.py --repeats {len(seeds)}); pairs below "
          f"{MIN_CUE_PCT:.0f} are not sampled")
    print_dict("CUE_GROUND_PCT", "float", {k: f"{v:.1f}" for k, v in ground_pct.items()})
    print(f"# sd of one run's figure over the {len(seeds)} runs (the mean's is sd / sqrt({len(seeds)}))")
    print_dict("CUE_GROUND_SD", "float", {k: f"{v:.1f}" for k, v in ground_sd.items()})
    checks = {pair_key(*pid[2:]): v for pid, v in blocks.items() if pid[:2] == ("rich", "ground")}
    if checks and min(len(v) for v in checks.values()) >= 2:
        n = min(len(v) for v in checks.values())
        print(f"# bench/bench_cues.py --check's reference: mean and sd of the figure on {CUE_CHECK_CROPS} crops a "
              f"class, over {n} disjoint blocks of the runs above")
        print_dict("CUE_CHECK_PCT", "tuple[float, float]",
                   {k: f"({np.mean(v):.1f}, {sd(v):.1f})" for k, v in checks.items()})


def judge(pct: float, reference: tuple[float, float]) -> tuple[float, bool]:
    """A ``--check`` figure against its reference (mean, sd): its z (the sd at least CHECK_MIN_SD) and
    whether it is out of tolerance (|z| > CHECK_Z)."""
    mean, spread = reference
    z = (pct - mean) / max(spread, CHECK_MIN_SD)
    return z, abs(z) > CHECK_Z


def check(s: Settings, workers: int, figures: Figures) -> int:
    """The pinned table against a fresh measurement of the ``--check`` size: 0 when every rich ground
    pair is within CHECK_Z sd of its reference (CUE_CHECK_PCT), 1 naming those that are not."""
    crops = run(s, ("rich",), quick=False, workers=workers)
    bad, worst = [], (0.0, "")
    for pid in pair_ids(("rich",), ("ground",), False):
        key = pair_key(*pid[2:])
        pct = 100.0 * float(pair_predictions(*pair_crops(crops, pid), s.crops)[0].mean())
        if key not in CUE_CHECK_PCT:
            bad.append(f"{pid[3]} vs {pid[4]} ({pid[2]}): {pct:.1f}%, not in CUE_CHECK_PCT")
            print(f"cue rich ground {pid[3]} vs {pid[4]}: {pct:.1f}%, no reference: OUT")
            continue
        mean, spread = CUE_CHECK_PCT[key]
        z, out = judge(pct, (mean, spread))
        print(f"cue rich ground {pid[3]} vs {pid[4]}: {pct:.1f}% (reference {mean:.1f} +- {spread:.1f}, "
              f"z {z:+.1f}; table {CUE_GROUND_PCT.get(key, float('nan')):.1f}){': OUT' if out else ''}")
        if abs(z) >= abs(worst[0]):
            worst = (z, f"{pid[3]} vs {pid[4]}")
        if out:
            bad.append(f"{pid[3]} vs {pid[4]} ({pid[2]}): {pct:.1f}%, reference {mean:.1f} +- {spread:.1f}")
            figures.add(f"cues: {pid[3]} vs {pid[4]}", pct, f"{pct:.1f}% (z {z:+.1f})",
                        f"{mean:.1f} +- {CHECK_Z:g} sd", False)
    total = len(pair_ids(("rich",), ("ground",), False))
    figures.add("cues: rich ground pairs within noise of the table", total - len(bad),
                f"{total - len(bad)}/{total} (worst {worst[1]}, z {worst[0]:+.1f})", f"{total}/{total}", not bad)
    if bad:
        print(f"\nCUE_GROUND_PCT disagrees with this measurement beyond its noise (|z| > {CHECK_Z:g}) for "
              f"{len(bad)} pair(s):\n  " + "\n  ".join(bad) + "\nre-measure the table: bench/bench_cues.py "
              "--looks rich --views ground --repeats 3 (docs/WORLD.md), and paste its three tables into "
              "world/episodes/lookalikes.py", file=sys.stderr)
        return 1
    print(f"\nall {total} rich ground pairs within {CHECK_Z:g} sd of CUE_CHECK_PCT (worst {worst[1]}, z {worst[0]:+.1f})")
    return 0


def contact_sheet(path: Path, crops: dict, s: Settings) -> None:
    """A few crops of every class, a row each (look, kind, class, view), to look at."""
    rows = []
    for key in sorted(crops):
        images = crops[key].images[:8]
        if not images:
            continue
        size = (GROUND_CROP_PX, GROUND_CROP_PX) if key[3] == "ground" else (GROUND_CROP_PX, GROUND_CROP_PX // 2)
        tiles = [cv2.resize(im, size, interpolation=cv2.INTER_NEAREST) for im in images]
        tiles += [np.zeros_like(tiles[0])] * (8 - len(tiles))
        row = np.concatenate(tiles, axis=1)
        label = np.full((size[1], 200, 3), 255, np.uint8)
        cv2.putText(label, " ".join(key), (3, size[1] // 2 + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1,
                    cv2.LINE_AA)
        rows.append(np.concatenate([label, cv2.resize(row, (row.shape[1], size[1]))], axis=1))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 2), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in rows]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(np.concatenate(rows), cv2.COLOR_RGB2BGR))


def main(argv: list[str] | None = None) -> int:
    cam = CameraConfig()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--town", default="grid-s7")
    parser.add_argument("--crops", type=int, default=300, help="crops a class and view (default 300)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=1,
                        help="runs at seeds seed, seed + 1, ...: each pair's mean and spread, and the tables to paste")
    parser.add_argument("--looks", default="flat,rich")
    parser.add_argument("--views", default="ground,air")
    parser.add_argument("--ground-px", type=int, default=cam.ground_px)
    parser.add_argument("--nadir-px", type=int, default=cam.nadir_px)
    parser.add_argument("--distance-m", type=float, nargs=2, default=(10.0, 25.0))
    parser.add_argument("--min-visible", type=float, default=0.7)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--sheet", type=Path, help="write a contact sheet of crops (PNG) here")
    parser.add_argument("--quick", action="store_true", help="smoke test: two classes a kind, 6 crops")
    parser.add_argument("--check", action="store_true",
                        help=f"the pinned table against a fresh measurement ({CUE_CHECK_CROPS} crops a class, rich "
                             f"ground, seed {CHECK_SEED}); exits 1 naming the pairs beyond {CHECK_Z:g} sd")
    parser.add_argument("--json", action="store_true", help="also print each figure as a BENCH-FIGURE line (--check)")
    args = parser.parse_args(argv)
    looks = tuple(x for x in args.looks.split(",") if x)
    views = tuple(x for x in args.views.split(",") if x)
    if not set(looks) <= set(LOOKS) or not set(views) <= set(VIEWS):
        parser.error(f"looks are {', '.join(LOOKS)}; views are {', '.join(VIEWS)}")
    if args.repeats < 1 or (args.check and (args.quick or args.repeats > 1)):
        parser.error("--repeats is 1 or more; --check takes neither --quick nor --repeats")
    crops_a_class = 6 if args.quick else CUE_CHECK_CROPS if args.check else args.crops
    seeds = [CHECK_SEED] if args.check else [args.seed + k for k in range(args.repeats)]
    if args.check:
        looks, views = ("rich",), ("ground",)
    started = time.perf_counter()
    runs: list[dict[PairId, float]] = []
    blocks: dict[PairId, list[float]] = defaultdict(list)
    for seed in seeds:
        s = Settings(args.town, crops_a_class, seed, args.ground_px, args.nadir_px, cam.ground_fov_deg,
                     cam.nadir_fov_deg, 80.0, tuple(args.distance_m), args.min_visible, views)
        run_started = time.perf_counter()
        print(f"town {s.town}, ground {s.ground_px} px / {s.ground_fov_deg:.0f} deg at {s.distance_m[0]:.0f}-"
              f"{s.distance_m[1]:.0f} m, air {s.nadir_px} px / {s.nadir_fov_deg:.0f} deg at {s.altitude_m:.0f} m, "
              f"{s.crops} crops a class and view, seed {s.seed}", flush=True)
        try:
            if args.check:
                code = check(s, args.workers, Figures(args.json))
                print(f"{time.perf_counter() - started:.0f} s")
                return code
            crops = run(s, looks, quick=args.quick, workers=args.workers)
        except KeyboardInterrupt:
            print("interrupted: no figures", file=sys.stderr)
            return 130
        runs.append(report(s, looks, crops, args.quick, table=args.repeats == 1))
        if not args.quick and s.crops >= 2 * CUE_CHECK_CROPS:
            for pid in runs[-1]:
                if pid[:2] == ("rich", "ground"):
                    blocks[pid] += block_pcts(crops, pid, s.crops, CUE_CHECK_CROPS)
        if args.sheet and seed == seeds[0]:
            contact_sheet(args.sheet, crops, s)
            print(f"crops: {args.sheet}")
        print(f"seed {seed}: {time.perf_counter() - run_started:.0f} s", flush=True)
    if args.repeats > 1:
        summary(s, seeds, runs, blocks)
    print(f"{time.perf_counter() - started:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
