"""Pieces every VLM prompt is built from: the images a role sends, per-episode memory, and the
facts of the state block that AGOS-Agent and the Baseline share.

A :class:`Prompt` is what a prompt builder returns: the system text, the user content parts
(captioned images and text, laid out as :mod:`agos.agents.vlm.protocol` says), the task stage and
the legal actions the reply schema allows.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from agos.agents.vlm import protocol
from agos.agents.vlm.client import image_part
from agos.runtime.codec import decode_image, encode_jpeg
from agos.runtime.schemas import ImageFrame, Observation, Waypoint

MEMORY_LINES = 6
"""Recent own decisions kept for the prompt ("task memory")."""

REFERENCE_NOTES = {
    "ref_top": "Target reference, seen from straight above",
    "ref_front": "Target reference, front view",
    "ref_front_left": "Target reference, front-left view",
    "ref_side": "Target reference, side view",
    "ref_rear": "Target reference, rear view",
}
PANEL_NOTES = {
    "front_left": "Six-view panel 1 of 6: front-left (60 deg left of the heading)",
    "front": "Six-view panel 2 of 6: front (along the heading)",
    "front_right": "Six-view panel 3 of 6: front-right",
    "back_left": "Six-view panel 4 of 6: back-left",
    "back": "Six-view panel 5 of 6: back",
    "back_right": "Six-view panel 6 of 6: back-right",
}


@dataclass
class Prompt:
    system: str
    parts: list[dict[str, Any]]
    stage: str
    actions: list[str]
    image_bytes: dict[str, int] = field(default_factory=dict)

    def messages(self) -> list[dict[str, Any]]:
        return [{"role": "system", "content": self.system}, {"role": "user", "content": self.parts}]

    def sha256(self) -> str:
        """A hash of the whole request content (images included): equal prompts, equal hashes."""
        return hashlib.sha256(json.dumps(self.messages(), sort_keys=True).encode()).hexdigest()


class PromptBuilder:
    """Accumulates a user message: text, captioned images and the state block."""

    def __init__(self, images: str) -> None:
        self.parts: list[dict[str, Any]] = []
        self.image_bytes: dict[str, int] = {}
        self.images = images

    def text(self, text: str) -> None:
        self.parts.append({"type": "text", "text": text})

    def image(self, label: str, frame: ImageFrame, note: str) -> None:
        data, encoding = frame.data, frame.encoding
        if frame.kind == "map" and encoding == "png":  # a lossless map is ~5x the bytes for no gain to a model
            data, encoding = encode_jpeg(decode_image(data)[:, :, :3], quality=85), "jpeg"
        self.parts.append({"type": "text", "text": protocol.image_caption(label, note)})
        self.parts.append(image_part(data, encoding))
        self.image_bytes[label] = len(data)

    def references(self, obs: Observation, *, top_only: bool = False) -> None:
        for ref in obs.references:
            if top_only and ref.name != "ref_top":
                continue
            note = REFERENCE_NOTES.get(ref.name, "Target reference")
            if ref.metres_per_px:
                note += f" ({ref.metres_per_px:.4f} m per pixel, background blacked out)"
            self.image(protocol.REFERENCE_PREFIX + ref.name.removeprefix("ref_"), ref, note)

    def teammate(self, obs: Observation) -> None:
        """The teammate's top view, where the observation has one (the UAV's) and every image is sent."""
        ref = obs.teammate_reference
        if ref is None or self.images != "all":
            return
        note = "Your teammate, the UGV, seen from straight above with its nose up"
        if ref.metres_per_px:
            note += f" ({ref.metres_per_px:.4f} m per pixel, background blacked out)"
        self.image(protocol.TEAMMATE_REFERENCE, ref, note + ": tell it apart from the cars you search among")

    def map(self, obs: Observation) -> None:
        frame = next((f for f in obs.images if f.kind == "map"), None)
        if frame is not None and self.images == "all":
            note = "Top-down map of the search region, north up"
            if frame.metres_per_px:
                note += f" ({frame.metres_per_px:.2f} m per pixel)"
            self.image(protocol.MAP, frame, note + "; markers: cyan triangle = UAV, magenta dot with a heading line = UGV")

    def ground_views(self, obs: Observation) -> ImageFrame | None:
        """The UGV's camera image(s) (six panels after STOP_OBSERVE, else the forward view), the map
        and the references; returns the first camera frame (its intrinsics go into the state)."""
        first = None
        if obs.mode == "stop_6view":
            for name, note in PANEL_NOTES.items():
                f = frame(obs, name)
                if f is not None:
                    first = first or f
                    self.image(name, f, note)
        else:
            first = frame(obs, "forward")
            if first is not None:
                self.image(protocol.FORWARD, first, "Your forward camera while driving")
        self.map(obs)
        self.references(obs, top_only=self.images != "all")
        return first

    def state(self, state: dict[str, Any]) -> None:
        self.text(protocol.state_text(state))


def frame(obs: Observation, name: str, kind: str = "rgb") -> ImageFrame | None:
    return next((f for f in obs.images if f.name == name and f.kind == kind), None)


@dataclass
class Memory:
    """What a VLM policy keeps about one episode between its decisions."""

    visited: list[str] = field(default_factory=list)
    """Waypoints this role has been at (UAV grid nodes or road anchors), oldest first."""
    visited_xy: list[tuple[float, float]] = field(default_factory=list)
    """Where the role has decided from (UAV: the ground points its camera has covered)."""
    recent: deque[str] = field(default_factory=lambda: deque(maxlen=MEMORY_LINES))
    """One line per recent decision: step, action, argument."""
    inspected_anchors: list[tuple[float, float]] = field(default_factory=list)
    """Baseline UGV: message anchors it already stopped at and rejected."""
    waits_here: int = 0
    """Consecutive WAITs at the same position (the Baseline's anti-stall reminder)."""
    last_position: tuple[float, float] | None = None

    def at(self, waypoint_id: str | None) -> None:
        if waypoint_id and (not self.visited or self.visited[-1] != waypoint_id):
            self.visited.append(waypoint_id)

    def seen_from(self, position: tuple[float, float]) -> None:
        if not self.visited_xy or math.dist(self.visited_xy[-1], position) > 1.0:
            self.visited_xy.append(position)

    def note(self, step: int, action: str, detail: str = "") -> None:
        self.recent.append(f"step {step}: {action}{' ' + detail if detail else ''}")


def xy(v: Any) -> list[float]:
    return [round(float(v[0]), 1), round(float(v[1]), 1)]


def budget(obs: Observation) -> dict[str, int]:
    c = obs.coordination
    return {"used": c.decisions_used, "total": c.decision_budget, "left": max(0, c.decision_budget - c.decisions_used)}


def confirmations(obs: Observation) -> dict[str, int]:
    """The remaining confirmation budget as the world sends it: CONFIRMs used, allowed, left."""
    c = obs.coordination
    return {"used": c.confirmations_used, "max": c.max_confirmations,
            "left": max(0, c.max_confirmations - c.confirmations_used)}


def confirmation_text(obs: Observation) -> str:
    """The prompt's sentence on the confirmation budget."""
    left = confirmations(obs)
    return (f"Confirmations left: {left['left']} of {left['max']} (a CONFIRM, right or wrong, ends the task, "
            "so spend it only on a clear match).")


def teammate_scale(obs: Observation) -> float | None:
    ref = obs.teammate_reference
    return None if ref is None else ref.metres_per_px


def messages(obs: Observation, limit: int = 4) -> list[dict[str, Any]]:
    return [{"from": m.sender, "text": m.text, "t_s": round(m.delivered_sim_time_s, 1)}
            for m in obs.coordination.messages[-limit:]]


def candidate_facts(obs: Observation) -> tuple[dict[str, Any] | None, list[dict[str, Any]], list[list[float]]]:
    """(the active candidate, every candidate, rejected candidate centres) as prompt facts."""
    here = obs.pose.position_world_m[:2]
    rows, active, rejected = [], None, []
    for c in obs.coordination.candidates:
        row = {"id": c.candidate_id, "cell": c.cell, "center_m": xy(c.center_world_m), "status": c.status,
               "distance_m": round(math.dist(here, c.center_world_m), 1)}
        rows.append(row)
        if c.status in ("pending", "arrived") and active is None:
            active = row
        if c.status in ("rejected", "false_confirm"):
            rejected.append(xy(c.center_world_m))
    return active, rows, rejected


def options(obs: Observation, memory: Memory, **extra: Any) -> list[dict[str, Any]]:
    here = obs.pose.position_world_m[:2]
    out = []
    for w in obs.waypoint_options:
        row: dict[str, Any] = {"id": w.waypoint_id, "position_m": xy(w.position_world_m),
                               "distance_m": round(math.dist(here, w.position_world_m[:2]), 1),
                               "visited": w.waypoint_id in memory.visited}
        if w.option:
            row["option"] = w.option
        if w.path_length_m is not None:
            row["path_length_m"] = round(w.path_length_m, 1)
        if w.distance_to_candidate_m is not None:
            row["distance_to_candidate_m"] = round(w.distance_to_candidate_m, 1)
        for key, fn in extra.items():
            row[key] = fn(w)
        out.append(row)
    return out


COVERED_RADIUS_M = 41.0
"""A UAV waypoint this close to a place the UAV has looked down from counts as covered: at 80 m the
60 deg nadir view spans about 92 m, so the neighbouring waypoints' centres were in view."""


def uncovered(obs: Observation, memory: Memory) -> list[Waypoint]:
    """Active UAV waypoints not yet covered by the camera (see ``COVERED_RADIUS_M``)."""
    return [w for w in obs.active_uav_waypoints
            if not any(math.dist(w.position_world_m[:2], p) <= COVERED_RADIUS_M for p in memory.visited_xy)]


def unvisited_nearest(obs: Observation, memory: Memory, n: int = 5) -> list[dict[str, Any]]:
    """The nearest active UAV waypoints not yet covered by the camera."""
    here = obs.pose.position_world_m[:2]
    rest = sorted(uncovered(obs, memory), key=lambda w: (math.dist(here, w.position_world_m[:2]), w.waypoint_id))
    return [{"id": w.waypoint_id, "position_m": xy(w.position_world_m),
             "distance_m": round(math.dist(here, w.position_world_m[:2]), 1)} for w in rest[:n]]


def camera_facts(f: ImageFrame | None) -> dict[str, Any] | None:
    if f is None or f.intrinsics is None:
        return None
    i = f.intrinsics
    out: dict[str, Any] = {"width_px": i.width_px, "height_px": i.height_px, "fx_px": round(i.fx_px, 3),
                           "fy_px": round(i.fy_px, 3), "cx_px": round(i.cx_px, 3), "cy_px": round(i.cy_px, 3),
                           "fov_deg": round(math.degrees(2 * math.atan(i.height_px / (2 * i.fy_px))), 1)}
    if f.world_from_camera is not None:
        out["world_from_camera"] = [round(v, 4) for v in f.world_from_camera]
    if f.metres_per_px is not None:
        out["m_per_px"] = f.metres_per_px
    return out


def reference_cameras(obs: Observation) -> dict[str, Any]:
    """Camera of each reference view (so metric sizes and painted heights can be read off them)."""
    return {r.name: camera_facts(r) for r in obs.references if r.intrinsics is not None}


def panel_cameras(obs: Observation) -> dict[str, Any]:
    """Six-view mode: the camera of each panel, by panel name."""
    if obs.mode != "stop_6view":
        return {}
    return {name: camera_facts(frame(obs, name)) for name in PANEL_NOTES if frame(obs, name) is not None}


def reference_scale(obs: Observation) -> float | None:
    top = next((r for r in obs.references if r.name == "ref_top"), None)
    return None if top is None else top.metres_per_px


REPLY_FORMAT = (
    "Reply with exactly one JSON object and nothing else, for example "
    '{"action": "MOVE_TO_UAV_WAYPOINT", "waypoint_id": "<an id from the options>", '
    '"message": "<optional short note to your teammate>", "reason": "<one sentence>"}. '
    "Fields by action: waypoint_id for MOVE_TO_*; cell (A1..E5) for ANNOTATE_CANDIDATE; candidate_id for "
    "GO_TO_CANDIDATE and REJECT. Use only ids that appear in the state.")
