"""The stand-in's "model": answers an agos VLM request by looking at its images with OpenCV.

It sees exactly what a model sees: the labelled images and the state block of the request
(:mod:`agos.agents.vlm.protocol`), never ground truth. Perception is the heuristic's robust
detection fed with what the request carries (:mod:`agos.agents.vlm.standin.perception`): from
above, the reference top view's paint layout and world-metre silhouette at the scale the altitude
and intrinsics give, paint matched across shade; on the ground, the heuristic's
:func:`~agos.agents.heuristic.ground.find_target` on a depth image estimated from where paint-hued
regions meet the road. Never colour alone. Decisions follow the prompt's instructions for each
protocol and stage, deterministically: the same request always gets the same reply.
"""

from __future__ import annotations

import hashlib
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from agos.agents.heuristic.colour_match import TargetProfile, profile_from_references
from agos.agents.vlm import protocol
from agos.agents.vlm.protocol import SplitRequest
from agos.agents.vlm.standin.perception import (
    BOTTOM_SLACK_M,
    DEFAULT_PAINT_BOTTOM_M,
    Cap,
    PaintBottom,
    TopTemplate,
    aerial_metres_per_px,
    detect_from_above_rgb,
    find_target_rgb,
    ground_view_from_rgb,
    paint_bottom,
    reference_cap,
    top_template,
)
from agos.runtime.camera import cell_of_pixel, pixel_to_ground
from agos.runtime.codec import decode_image
from agos.runtime.schemas import CameraIntrinsics, ImageFrame

CLEAR_MATCH = 0.45
"""Aerial score (:func:`~agos.agents.vlm.standin.perception.detect_from_above_rgb`) of a match worth
reporting while parts of the region are still unseen; once every waypoint has been covered, any
detection (``MIN_SCORE``, 0.3, and up) is."""
REJECTED_RADIUS_M = 12.0
"""A detection this close to a rejected region is not reported again."""
CENTRED_FRACTION = 0.15
"""Baseline: a match within this fraction of the image size from the centre counts as centred."""
REVISIT_PENALTY_M = 25.0
MIN_GROUND_PIXELS = 80
"""Paint pixels an object needs in the six views (the heuristic UGV's ``MIN_PIXELS``)."""
CONFIRM_WITHIN_M = 45.0
EXPLORE_STOP_WITHIN_M = 25.0
ANCHOR_STOP_WITHIN_M = 15.0
CACHED_REFERENCES = 256


@dataclass(frozen=True)
class Reference:
    """What the request's reference views say about the target, read once per set of references."""

    profile: TargetProfile
    top_rgba: np.ndarray
    """The top view (RGBA, background transparent, nose up)."""
    top_metres_per_px: float
    bottom: PaintBottom
    """Where the paint begins above the road (the side view): where a vehicle's paint-hued region
    meets the road in a ground view."""
    cap: Cap
    """What the side view shows standing on the paint (a roof box, a contrasting roof), if anything."""
    templates: dict[float, TopTemplate] = field(default_factory=dict, compare=False)
    """Top templates by aerial metres per pixel (filled on first use, under the cache lock)."""


_references: OrderedDict[str, Reference | None] = OrderedDict()
_references_lock = threading.Lock()


def respond(request: SplitRequest) -> dict[str, Any]:
    """The reply object for one request (``{"action": ..., ...}``)."""
    state = request.state
    if not state or "legal_actions" not in state:
        return {"action": "WAIT", "reason": "the request has no state block I can read"}
    ref = _reference(request)
    if ref is None:
        return _first_legal(state, ["NO_RELIABLE_CANDIDATE", "WAIT"], "no usable target reference")
    if state.get("role") == "uav":
        return (_baseline_uav if state.get("protocol") == "baseline" else _agos_uav)(request, state, ref)
    return (_baseline_ugv if state.get("protocol") == "baseline" else _agos_ugv)(request, state, ref)


# ----- UAV ------------------------------------------------------------------------------------
def _agos_uav(req: SplitRequest, state: dict[str, Any], ref: Reference) -> dict[str, Any]:
    legal = state["legal_actions"]
    if "ANNOTATE_CANDIDATE" in legal:
        avoid = [tuple(p) for p in state.get("rejected_regions_m", [])]
        for u, v, _ in _aerial_matches(req, state, ref, avoid):
            cam = state["camera"]
            cell = cell_of_pixel(u, v, cam["width_px"], cam["height_px"])
            return {"action": "ANNOTATE_CANDIDATE", "cell": cell, "message": f"Possible target in cell {cell}.",
                    "reason": "paint layout, silhouette and paint colour match the reference"}
    if state.get("stage") == "candidate_active":
        return _first_legal(state, ["WAIT"], "my candidate is being checked by the UGV")
    move = _coverage_move(state)
    if move is not None and "MOVE_TO_UAV_WAYPOINT" in legal:
        return {"action": "MOVE_TO_UAV_WAYPOINT", "waypoint_id": move, "reason": "no match here; covering the region"}
    return _first_legal(state, ["NO_RELIABLE_CANDIDATE", "WAIT"], "nothing convincing in view")


def _baseline_uav(req: SplitRequest, state: dict[str, Any], ref: Reference) -> dict[str, Any]:
    legal = state["legal_actions"]
    checked = [p for m in state.get("messages", []) if m.get("from") == "ugv" for p in protocol.coordinates(m.get("text", ""))]
    matches = _aerial_matches(req, state, ref, checked, radius_m=ANCHOR_STOP_WITHIN_M + REJECTED_RADIUS_M)
    cam = state.get("camera") or {}
    if matches and not state.get("stall_reminder"):
        u, v, ground = matches[0]
        off = max(abs(u - cam["cx_px"]) / cam["width_px"], abs(v - cam["cy_px"]) / cam["height_px"])
        x, y = state["position_m"]
        if off <= CENTRED_FRACTION or "MOVE_TO_UAV_WAYPOINT" not in legal:
            return {"action": "WAIT", "message": f"CLEAR_MATCH below me: search around ({x:.0f}, {y:.0f}).",
                    "reason": "CLEAR_MATCH near the image centre"}
        best = min(state["waypoint_options"], key=lambda w: (math.dist(w["position_m"], ground), w["id"]))
        if math.dist(best["position_m"], ground) < math.dist(state["position_m"], ground):
            return {"action": "MOVE_TO_UAV_WAYPOINT", "waypoint_id": best["id"],
                    "reason": "CLEAR_MATCH off-centre; moving over it"}
        return {"action": "WAIT", "message": f"CLEAR_MATCH near me: search around ({x:.0f}, {y:.0f}).",
                "reason": "CLEAR_MATCH; no waypoint is closer to it"}
    move = _coverage_move(state)
    if move is not None and "MOVE_TO_UAV_WAYPOINT" in legal:
        return {"action": "MOVE_TO_UAV_WAYPOINT", "waypoint_id": move, "reason": "NONE; covering the region"}
    return _first_legal(state, ["NO_RELIABLE_CANDIDATE", "WAIT"], "NONE")


def _aerial_matches(req: SplitRequest, state: dict[str, Any], ref: Reference, avoid: list,
                    radius_m: float = REJECTED_RADIUS_M) -> list[tuple[float, float, tuple[float, float]]]:
    """Detections in the aerial image as (u, v, ground point), best first, away from ``avoid``: clear
    matches (``CLEAR_MATCH``) while the state lists unvisited waypoints, any detection after."""
    data = req.images.get(protocol.AERIAL)
    cam = state.get("camera")
    if data is None or not cam or "world_from_camera" not in cam:
        return []
    intr = _intrinsics(cam)
    pose = np.asarray(cam["world_from_camera"], dtype=float).reshape(4, 4)
    template = _template(ref, aerial_metres_per_px(float(state.get("altitude_m", pose[2, 3])), intr, ref.profile))
    if template is None:
        return []
    floor = CLEAR_MATCH if state.get("unvisited_waypoints") else 0.0
    out = []
    for det in detect_from_above_rgb(_rgb(data), ref.profile, template, intrinsics=intr, world_from_camera=pose):
        if det.score < floor:
            continue
        ground = pixel_to_ground(det.u_px, det.v_px, pose, intr)
        if any(math.dist(ground, p) <= radius_m for p in avoid):
            continue
        out.append((det.u_px, det.v_px, (float(ground[0]), float(ground[1]))))
    return out


def _coverage_move(state: dict[str, Any]) -> str | None:
    options = state.get("waypoint_options") or []
    if not options:
        return None
    todo = state.get("unvisited_waypoints") or []
    if todo:
        goal = todo[0]["position_m"]
        return min(options, key=lambda w: (math.dist(w["position_m"], goal), w["id"]))["id"]
    return min(options, key=lambda w: (w.get("visited", False), w["id"]))["id"]


# ----- UGV ------------------------------------------------------------------------------------
def _agos_ugv(req: SplitRequest, state: dict[str, Any], ref: Reference) -> dict[str, Any]:
    stage, active = state.get("stage"), state.get("active_candidate")
    legal = state["legal_actions"]
    if stage == "six_view":
        cid = {"candidate_id": active["id"]} if active else {}
        if _six_view_match(req, state, ref):
            return {"action": "CONFIRM", **cid, "message": "Target confirmed.", "reason": "a nearby car matches"}
        return {"action": "REJECT", **cid, "message": f"{active['id'] if active else 'This area'}: not the target.",
                "reason": "no matching car nearby in the six views"}
    if stage in ("arrival", "candidate_reminder"):
        if active is None:
            raise ValueError(f"stage {stage!r} without an active_candidate in the state block")
        if stage == "arrival":
            return {"action": "STOP_OBSERVE", "message": f"Arrived at {active['id']}; looking around.",
                    "reason": "arrived at the candidate"}
        if "GO_TO_CANDIDATE" in legal:
            return {"action": "GO_TO_CANDIDATE", "candidate_id": active["id"], "message": f"On my way to {active['id']}.",
                    "reason": "the UAV's candidate comes first"}
        step = _towards(state, "distance_to_candidate_m")
        if step is not None:
            return {"action": "MOVE_TO_ROAD_WAYPOINT", "waypoint_id": step, "reason": "closer to the candidate"}
    return _explore(req, state, ref)


def _baseline_ugv(req: SplitRequest, state: dict[str, Any], ref: Reference) -> dict[str, Any]:
    anchor = state.get("anchor")
    where = f"({anchor['position_m'][0]:.0f}, {anchor['position_m'][1]:.0f})" if anchor else "here"
    if state.get("mode") == "stop_6view":
        if _six_view_match(req, state, ref):
            return {"action": "CONFIRM", "message": "Target confirmed.", "reason": "a nearby car matches"}
        return {"action": "REJECT", "message": f"Checked the area at {where}: no match.", "reason": "no nearby match"}
    if anchor is not None:
        if anchor["distance_m"] <= ANCHOR_STOP_WITHIN_M:
            return {"action": "STOP_OBSERVE", "reason": "at the UAV's search anchor"}
        step = _towards(state, "distance_to_anchor_m")
        if step is not None:
            return {"action": "MOVE_TO_ROAD_WAYPOINT", "waypoint_id": step, "reason": "towards the UAV's anchor"}
    return _explore(req, state, ref)


def _explore(req: SplitRequest, state: dict[str, Any], ref: Reference) -> dict[str, Any]:
    """No candidate to chase: stop for a car like the target ahead (unless just rejected), else wait."""
    recent = state.get("memory") or []
    just_rejected = any("REJECT" in line for line in recent[-3:])
    data = req.images.get(protocol.FORWARD)
    cam = state.get("camera")
    if (data is not None and cam and not just_rejected and "STOP_OBSERVE" in state["legal_actions"]
            and _ground_matches(ref, [(protocol.FORWARD, data, cam)], within_m=EXPLORE_STOP_WITHIN_M)):
        return {"action": "STOP_OBSERVE", "reason": "a car like the target is ahead"}
    return _first_legal(state, ["WAIT"], "waiting for the UAV")


def _towards(state: dict[str, Any], key: str) -> str | None:
    options = [w for w in state.get("waypoint_options") or [] if key in w]
    if not options:
        return None
    return min(options, key=lambda w: (w[key] + REVISIT_PENALTY_M * w.get("visited", False), w["id"]))["id"]


def _six_view_match(req: SplitRequest, state: dict[str, Any], ref: Reference) -> bool:
    cameras = state.get("panel_cameras") or {}
    views = [(name, req.images[name], cameras[name]) for name in protocol.SIX_VIEWS
             if name in req.images and cameras.get(name)]
    return _ground_matches(ref, views, within_m=CONFIRM_WITHIN_M)


def _ground_matches(ref: Reference, views: list[tuple[str, bytes, dict[str, Any]]], *, within_m: float) -> bool:
    """Whether the views (name, image bytes, camera facts) show the target within ``within_m``: the
    heuristic's ground judgement (paint hue and brightness in its light, painted top, length) on
    depth estimated from where paint-hued regions meet the road
    (:func:`~agos.agents.vlm.standin.perception.ground_view_from_rgb`)."""
    ground = [ground_view_from_rgb(name, _rgb(data), ref.profile, intrinsics=_intrinsics(cam),
                                   world_from_camera=np.asarray(cam["world_from_camera"], dtype=float).reshape(4, 4),
                                   bottom=ref.bottom)
              for name, data, cam in views if "world_from_camera" in cam]
    found = find_target_rgb(ground, ref.profile, min_pixels=MIN_GROUND_PIXELS, cap=ref.cap)
    return any(obj.distance_m <= within_m for obj in found)


# ----- helpers --------------------------------------------------------------------------------
def _first_legal(state: dict[str, Any], preferred: list[str], reason: str) -> dict[str, Any]:
    legal = state["legal_actions"]
    return {"action": next((a for a in preferred if a in legal), "WAIT"), "reason": reason}


def _rgb(data: bytes) -> np.ndarray:
    image = decode_image(data)
    return image[:, :, :3] if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)


def _intrinsics(cam: dict[str, Any]) -> CameraIntrinsics:
    return CameraIntrinsics(width_px=int(cam["width_px"]), height_px=int(cam["height_px"]), fx_px=float(cam["fx_px"]),
                            fy_px=float(cam["fy_px"]), cx_px=float(cam["cx_px"]), cy_px=float(cam["cy_px"]))


def _reference(req: SplitRequest) -> Reference | None:
    """What the request's reference images say about the target (cached by their bytes); None when
    they have no scaled top view with paint."""
    refs = {label: data for label, data in req.images.items() if label.startswith(protocol.REFERENCE_PREFIX)}
    if "target_ref_top" not in refs:
        return None
    key = hashlib.sha256(b"".join(refs[k] for k in sorted(refs))).hexdigest()
    with _references_lock:
        if key in _references:
            return _references[key]
    state = req.state or {}
    cameras = state.get("reference_cameras") or {}
    frames = []
    for label, data in sorted(refs.items()):
        name = "ref_" + label.removeprefix(protocol.REFERENCE_PREFIX)
        cam = cameras.get(name) or {}
        frames.append(ImageFrame(
            name=name, kind="rgb", encoding="png", data=data,
            intrinsics=_intrinsics(cam) if "fx_px" in cam else None, world_from_camera=cam.get("world_from_camera"),
            metres_per_px=cam.get("m_per_px") or (state.get("reference_m_per_px") if name == "ref_top" else None)))
    ref: Reference | None
    try:
        profile = profile_from_references(frames)
        top = next(f for f in frames if f.name == "ref_top")
        top_rgba = decode_image(top.data)
        side, side_cam = refs.get(protocol.REFERENCE_PREFIX + "side"), cameras.get("ref_side") or {}
        bottom = PaintBottom(DEFAULT_PAINT_BOTTOM_M, DEFAULT_PAINT_BOTTOM_M - BOTTOM_SLACK_M,
                             DEFAULT_PAINT_BOTTOM_M + BOTTOM_SLACK_M)
        cap = Cap(False, 0.0, 0.0)
        if side is not None and "fx_px" in side_cam and side_cam.get("world_from_camera"):
            side_rgba = decode_image(side)
            if side_rgba.ndim == 3 and side_rgba.shape[2] == 4:
                side_pose = np.asarray(side_cam["world_from_camera"], dtype=float).reshape(4, 4)
                bottom = paint_bottom(side_rgba, _intrinsics(side_cam), side_pose, profile)
                cap = reference_cap(side_rgba, _intrinsics(side_cam), side_pose, profile)
        assert top.metres_per_px is not None, "profile_from_references refuses an unscaled top view"
        ref = Reference(profile, top_rgba, float(top.metres_per_px), bottom, cap) \
            if top_rgba.ndim == 3 and top_rgba.shape[2] == 4 else None
    except (ValueError, TypeError):
        ref = None
    with _references_lock:
        _references[key] = ref
        while len(_references) > CACHED_REFERENCES:
            _references.popitem(last=False)
    return ref


def _template(ref: Reference, metres_per_px: float) -> TopTemplate | None:
    """The reference's top template at an aerial scale (cached on the reference, 1 mm steps)."""
    key = round(metres_per_px, 3)
    with _references_lock:
        if key in ref.templates:
            return ref.templates[key]
    template = top_template(ref.top_rgba, ref.top_metres_per_px, key, ref.profile)
    with _references_lock:
        if template is not None:
            ref.templates[key] = template
    return template
