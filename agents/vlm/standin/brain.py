"""The stand-in's "model": answers an agos VLM request by looking at its images with OpenCV.

It sees exactly what a model sees: the labelled images and the state block of the request
(:mod:`agos.agents.vlm.protocol`), never ground truth. Perception is the heuristic's colour-and-size
matching (:mod:`agos.agents.heuristic.perception`), except that ground views are RGB only: distance
and painted height come from where a region meets the road and the camera pose in the state,
not from a depth image. Decisions follow the prompt's instructions for each protocol and stage,
deterministically: the same request always gets the same reply.
"""

from __future__ import annotations

import hashlib
import math
import threading
from collections import OrderedDict
from typing import Any

import cv2
import numpy as np

from agos.agents.heuristic.perception import TargetProfile, detect_from_above, paint_mask, profile_from_references
from agos.agents.vlm import protocol
from agos.agents.vlm.protocol import SplitRequest
from agos.runtime.camera import cell_of_pixel, pixel_to_ground
from agos.runtime.codec import decode_image
from agos.runtime.schemas import CameraIntrinsics, ImageFrame

REJECTED_RADIUS_M = 12.0
"""A detection this close to a rejected region is not reported again."""
CENTRED_FRACTION = 0.15
"""Baseline: a match within this fraction of the image size from the centre counts as centred."""
REVISIT_PENALTY_M = 25.0
MIN_GROUND_PIXELS = 80
MIN_FILL = 0.35
"""A vehicle fills much of its bounding box; a diagonal road marking does not."""
CONFIRM_WITHIN_M = 45.0
EXPLORE_STOP_WITHIN_M = 25.0
ANCHOR_STOP_WITHIN_M = 15.0

_profiles: OrderedDict[str, TargetProfile | None] = OrderedDict()
_profiles_lock = threading.Lock()


def respond(request: SplitRequest) -> dict[str, Any]:
    """The reply object for one request (``{"action": ..., ...}``)."""
    state = request.state
    if not state or "legal_actions" not in state:
        return {"action": "WAIT", "reason": "the request has no state block I can read"}
    profile = _profile(request)
    if profile is None:
        return _first_legal(state, ["NO_RELIABLE_CANDIDATE", "WAIT"], "no usable target reference")
    if state.get("role") == "uav":
        return (_baseline_uav if state.get("protocol") == "baseline" else _agos_uav)(request, state, profile)
    return (_baseline_ugv if state.get("protocol") == "baseline" else _agos_ugv)(request, state, profile)


# ----- UAV ------------------------------------------------------------------------------------
def _agos_uav(req: SplitRequest, state: dict[str, Any], profile: TargetProfile) -> dict[str, Any]:
    legal = state["legal_actions"]
    if "ANNOTATE_CANDIDATE" in legal:
        avoid = [tuple(p) for p in state.get("rejected_regions_m", [])]
        for u, v, _ in _aerial_matches(req, state, profile, avoid):
            cam = state["camera"]
            cell = cell_of_pixel(u, v, cam["width_px"], cam["height_px"])
            return {"action": "ANNOTATE_CANDIDATE", "cell": cell, "message": f"Possible target in cell {cell}.",
                    "reason": "paint colour and footprint match the reference"}
    if state.get("stage") == "candidate_active":
        return _first_legal(state, ["WAIT"], "my candidate is being checked by the UGV")
    move = _coverage_move(state)
    if move is not None and "MOVE_TO_UAV_WAYPOINT" in legal:
        return {"action": "MOVE_TO_UAV_WAYPOINT", "waypoint_id": move, "reason": "no match here; covering the region"}
    return _first_legal(state, ["NO_RELIABLE_CANDIDATE", "WAIT"], "nothing convincing in view")


def _baseline_uav(req: SplitRequest, state: dict[str, Any], profile: TargetProfile) -> dict[str, Any]:
    legal = state["legal_actions"]
    checked = [p for m in state.get("messages", []) if m.get("from") == "ugv" for p in protocol.coordinates(m.get("text", ""))]
    matches = _aerial_matches(req, state, profile, checked, radius_m=ANCHOR_STOP_WITHIN_M + REJECTED_RADIUS_M)
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


def _aerial_matches(req: SplitRequest, state: dict[str, Any], profile: TargetProfile, avoid: list,
                    radius_m: float = REJECTED_RADIUS_M) -> list[tuple[float, float, tuple[float, float]]]:
    """Detections in the aerial image as (u, v, ground point), best first, away from ``avoid``."""
    data = req.images.get(protocol.AERIAL)
    cam = state.get("camera")
    if data is None or not cam or "world_from_camera" not in cam:
        return []
    intr = _intrinsics(cam)
    pose = np.asarray(cam["world_from_camera"], dtype=float).reshape(4, 4)
    out = []
    for det in detect_from_above(_rgb(data), profile, altitude_m=float(state["altitude_m"]), fy_px=intr.fy_px):
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
def _agos_ugv(req: SplitRequest, state: dict[str, Any], profile: TargetProfile) -> dict[str, Any]:
    stage, active = state.get("stage"), state.get("active_candidate")
    legal = state["legal_actions"]
    if stage == "six_view":
        cid = {"candidate_id": active["id"]} if active else {}
        if _six_view_match(req, state, profile):
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
    return _explore(req, state, profile)


def _baseline_ugv(req: SplitRequest, state: dict[str, Any], profile: TargetProfile) -> dict[str, Any]:
    anchor = state.get("anchor")
    where = f"({anchor['position_m'][0]:.0f}, {anchor['position_m'][1]:.0f})" if anchor else "here"
    if state.get("mode") == "stop_6view":
        if _six_view_match(req, state, profile):
            return {"action": "CONFIRM", "message": "Target confirmed.", "reason": "a nearby car matches"}
        return {"action": "REJECT", "message": f"Checked the area at {where}: no match.", "reason": "no nearby match"}
    if anchor is not None:
        if anchor["distance_m"] <= ANCHOR_STOP_WITHIN_M:
            return {"action": "STOP_OBSERVE", "reason": "at the UAV's search anchor"}
        step = _towards(state, "distance_to_anchor_m")
        if step is not None:
            return {"action": "MOVE_TO_ROAD_WAYPOINT", "waypoint_id": step, "reason": "towards the UAV's anchor"}
    return _explore(req, state, profile)


def _explore(req: SplitRequest, state: dict[str, Any], profile: TargetProfile) -> dict[str, Any]:
    """No candidate to chase: stop for a car like the target ahead (unless just rejected), else wait."""
    recent = state.get("memory") or []
    just_rejected = any("REJECT" in line for line in recent[-3:])
    data = req.images.get(protocol.FORWARD)
    cam = state.get("camera")
    if (data is not None and cam and not just_rejected and "STOP_OBSERVE" in state["legal_actions"]
            and _ground_matches(_rgb(data), cam, profile, within_m=EXPLORE_STOP_WITHIN_M)):
        return {"action": "STOP_OBSERVE", "reason": "a car like the target is ahead"}
    return _first_legal(state, ["WAIT"], "waiting for the UAV")


def _towards(state: dict[str, Any], key: str) -> str | None:
    options = [w for w in state.get("waypoint_options") or [] if key in w]
    if not options:
        return None
    return min(options, key=lambda w: (w[key] + REVISIT_PENALTY_M * w.get("visited", False), w["id"]))["id"]


def _six_view_match(req: SplitRequest, state: dict[str, Any], profile: TargetProfile) -> bool:
    cameras = state.get("panel_cameras") or {}
    for name in protocol.SIX_VIEWS:
        data, cam = req.images.get(name), cameras.get(name)
        if data is not None and cam and _ground_matches(_rgb(data), cam, profile, within_m=CONFIRM_WITHIN_M):
            return True
    return False


def _ground_matches(rgb: np.ndarray, cam: dict[str, Any], profile: TargetProfile, *, within_m: float) -> bool:
    """A paint-coloured region standing on the road within ``within_m`` with the reference's painted
    height. Without depth: the region's lowest pixels meet the road (z = 0), which fixes its distance
    along the camera rays; its highest pixels at that distance give the painted height."""
    intr = _intrinsics(cam)
    pose = np.asarray(cam["world_from_camera"], dtype=float).reshape(4, 4)
    lo, hi = profile.value_side
    mask = paint_mask(rgb, profile, (lo * 0.8, min(255.0, max(hi, profile.value_top) * 1.25 + 5)))
    joined = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((13, 3), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(joined, connectivity=8)
    eye = pose[:3, 3]
    for k in range(1, n):
        _, y0, w, h, area = (int(v) for v in stats[k])
        if area < MIN_GROUND_PIXELS or y0 + h >= rgb.shape[0] - 1 or area < MIN_FILL * w * h:
            continue  # small, cut off by the image's lower edge (no visible road contact), or a thin line
        vs, us = np.nonzero((labels == k) & mask)
        if len(vs) < MIN_GROUND_PIXELS // 2:
            continue
        rays = pose[:3, :3] @ np.stack([(us - intr.cx_px) / intr.fx_px, (vs - intr.cy_px) / intr.fy_px, np.ones(len(us))])
        bottom = np.argmax(vs)
        if rays[2, bottom] >= -1e-6:
            continue  # the region does not reach below the horizon: no road contact
        t = -eye[2] / rays[2, bottom]
        distance = float(t * math.hypot(rays[0, bottom], rays[1, bottom]))
        heights = eye[2] + distance / np.hypot(rays[0], rays[1]) * rays[2]
        top, middle = float(np.percentile(heights, 97)), float(np.percentile(heights, 50))
        if middle < 0.25 or distance > within_m:
            continue
        if top - profile.paint_top_m > 0.35 or profile.paint_top_m - top > 0.75:
            continue
        return True
    return False


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


def _profile(req: SplitRequest) -> TargetProfile | None:
    """The target profile from the request's reference images (cached by their bytes)."""
    refs = {label: data for label, data in req.images.items() if label.startswith(protocol.REFERENCE_PREFIX)}
    if "target_ref_top" not in refs:
        return None
    key = hashlib.sha256(b"".join(refs[k] for k in sorted(refs))).hexdigest()
    with _profiles_lock:
        if key in _profiles:
            return _profiles[key]
    cameras = (req.state or {}).get("reference_cameras") or {}
    frames = []
    for label, data in sorted(refs.items()):
        name = "ref_" + label.removeprefix(protocol.REFERENCE_PREFIX)
        cam = cameras.get(name) or {}
        frames.append(ImageFrame(
            name=name, kind="rgb", encoding="png", data=data,
            intrinsics=_intrinsics(cam) if "fx_px" in cam else None, world_from_camera=cam.get("world_from_camera"),
            metres_per_px=cam.get("m_per_px") or ((req.state or {}).get("reference_m_per_px") if name == "ref_top" else None)))
    try:
        profile: TargetProfile | None = profile_from_references(frames)
    except (ValueError, TypeError):
        profile = None
    with _profiles_lock:
        _profiles[key] = profile
        while len(_profiles) > 256:
            _profiles.popitem(last=False)
    return profile
