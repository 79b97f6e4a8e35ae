"""What the console shows a person for one observation: the page's model of it (pure).

Contract: :func:`shown` turns an :class:`~agos.runtime.schemas.Observation` into the images and
the facts the page draws, and nothing the agent did not receive: the images AGOS-Agent's prompt
carries (the UAV's nadir view with its A1-E5 grid, or the UGV's forward view or six views; the
top-down map M; the target references, agents/vlm/request.py), the role's pose, its own view of
the coordination state (candidates, delivered messages, the teammate's last reported pose, the
shared budget) and the legal choices: one per legal action and argument (a waypoint option, an
active candidate; ANNOTATE_CANDIDATE takes a cell the person clicks). Depth and semantic images
are not shown, as the VLM policies do not send them. Map positions are given in map pixels
(north up, the map's own scale) so that the page can draw options and candidates on M.
:attr:`Shown.sha256` hashes everything shown (facts and image bytes): the ``prompt_sha256`` of
the person's decision trace.
"""

from __future__ import annotations

import hashlib
import json
import math
import struct
from dataclasses import dataclass
from typing import Any

from agos.agents.vlm import protocol
from agos.agents.vlm.agos_prompts import ugv_stage
from agos.agents.vlm.request import PANEL_NOTES, REFERENCE_NOTES, budget, candidate_facts, frame, xy
from agos.runtime.schemas import ImageFrame, Observation, Waypoint

OPTION_KEYS = "123456789"
"""Keyboard keys of the waypoint options, in order."""
ACTION_KEYS = {"ANNOTATE_CANDIDATE": "a", "NO_RELIABLE_CANDIDATE": "n", "GO_TO_CANDIDATE": "g", "STOP_OBSERVE": "s",
               "CONFIRM": "c", "REJECT": "r", "WAIT": "w"}
"""Keyboard keys of the other actions (the page lists them on each button)."""
MIME = {"png": "image/png", "jpeg": "image/jpeg"}


@dataclass(frozen=True)
class ShownImage:
    label: str
    """The VLM prompt's label of the image (``aerial_grid``, ``topdown_map``, ``forward``, a panel
    name, ``target_ref_top`` ...)."""
    caption: str
    data: bytes
    mime: str
    digest: str
    """16 hex digits of the bytes' sha256: the image's address on the page."""


@dataclass(frozen=True)
class Shown:
    state: dict[str, Any]
    """The facts, JSON-ready."""
    images: list[ShownImage]
    choices: list[dict[str, Any]]
    """The legal choices: ``action`` plus its argument (``waypoint_id``, ``candidate_id``, or
    ``needs: "cell"``), a ``label`` and a keyboard ``key``."""
    sha256: str


def shown(obs: Observation) -> Shown:
    """The page's model of ``obs`` (see the module docstring)."""
    map_frame = next((f for f in obs.images if f.kind == "map"), None)
    images = _images(obs, map_frame)
    to_px = _MapPixels(obs.region_world_m, _png_side(map_frame.data) if map_frame is not None else None)
    here = obs.pose.position_world_m[:2]
    c = obs.coordination
    mate_role = "ugv" if obs.role == "uav" else "uav"
    mate = c.poses.get(mate_role)
    options = [_option(n, w, here, to_px) for n, w in enumerate(obs.waypoint_options)]
    active, candidates, rejected = candidate_facts(obs)
    for row, k in zip(candidates, c.candidates, strict=True):  # the prompt's facts, and where to draw them
        row.update(created_s=round(k.created_sim_time_s, 1), approach=k.approach_waypoint_id, map_px=to_px(k.center_world_m),
                   polygon_px=[p for v in k.polygon_world_m if (p := to_px(v)) is not None])
    state: dict[str, Any] = {
        "run_id": obs.run_id, "episode_id": obs.episode_id, "role": obs.role, "attempt": obs.attempt,
        "decision_index": obs.decision_index, "sim_time_s": round(obs.sim_time_s, 1), "mode": obs.mode,
        "fresh_stop_observe": obs.fresh_stop_observe, "decision_timeout_s": obs.decision_timeout_s,
        "pose": {"position_m": xy(here), "altitude_m": round(obs.pose.position_world_m[2], 1),
                 "heading_deg": round(math.degrees(obs.pose.yaw_rad) % 360.0, 1), "map_px": to_px(here)},
        "teammate": None if mate is None else {"role": mate_role, "position_m": xy(mate.position_world_m[:2]),
                                               "heading_deg": round(math.degrees(mate.yaw_rad) % 360.0, 1),
                                               "map_px": to_px(mate.position_world_m[:2])},
        "budget": budget(obs),
        "annotations": {"used": c.annotations_used, "max": c.max_annotations},
        "legal_actions": list(obs.legal_actions),
        "options": options,
        "candidates": candidates,
        "messages": [{"from": m.sender, "to": m.receiver, "text": m.text, "sent_s": round(m.sent_sim_time_s, 1),
                      "delivered_s": round(m.delivered_sim_time_s, 1)} for m in c.messages],
        "region_m": [round(v, 1) for v in obs.region_world_m],
        "grid": {"rows": obs.grid_rows, "cols": obs.grid_cols},
        "map": None if to_px.side_px is None else {"side_px": to_px.side_px},
        "searchable_px": [p for w in obs.active_uav_waypoints if (p := to_px(w.position_world_m[:2])) is not None],
        "hint": _hint(obs, active, rejected),
    }
    digest = hashlib.sha256(json.dumps(state, sort_keys=True).encode())
    for image in images:
        digest.update(image.label.encode() + b"\0" + image.data)
    return Shown(state=state, images=images, choices=_choices(obs, options), sha256=digest.hexdigest())


def _images(obs: Observation, map_frame: ImageFrame | None) -> list[ShownImage]:
    """The images the role's AGOS-Agent prompt carries, under its labels and notes (agents/vlm/request.py)."""
    out: list[ShownImage] = []

    def add(label: str, caption: str, f: ImageFrame | None) -> None:
        if f is not None:
            out.append(ShownImage(label, caption, f.data, MIME.get(f.encoding, "application/octet-stream"),
                                  hashlib.sha256(f.data).hexdigest()[:16]))

    if obs.role == "uav":
        add(protocol.AERIAL, "Your downward camera with the A1-E5 grid", frame(obs, "nadir", "rgb_grid") or frame(obs, "nadir"))
    elif obs.mode == "stop_6view":
        for name, note in PANEL_NOTES.items():
            add(name, note, frame(obs, name))
    else:
        add(protocol.FORWARD, "Your forward camera", frame(obs, "forward"))
    add(protocol.MAP, "Map M of the search region, north up", map_frame)
    for ref in obs.references:
        note = REFERENCE_NOTES.get(ref.name, "Target reference")
        if ref.metres_per_px:
            note += f" ({ref.metres_per_px * 100:.1f} cm per pixel)"
        add(protocol.REFERENCE_PREFIX + ref.name.removeprefix("ref_"), note, ref)
    return out


class _MapPixels:
    """World metres -> pixels of the map M (world/towns/topdown.py's ``MapCanvas``: the region's
    longer side spans the map, north up), or None without a map."""

    def __init__(self, region: tuple[float, float, float, float], side_px: int | None) -> None:
        self.x0, self.y0, x1, y1 = region
        self.side_px = side_px
        self.scale = None if side_px is None else side_px / max(x1 - self.x0, y1 - self.y0, 1e-6)

    def __call__(self, xy: Any) -> list[float] | None:
        if self.scale is None or self.side_px is None:
            return None
        return [round((float(xy[0]) - self.x0) * self.scale, 1), round(self.side_px - (float(xy[1]) - self.y0) * self.scale, 1)]


def _png_side(data: bytes) -> int | None:
    """The width of a PNG from its header (the map is square), or None for anything else."""
    if data[:8] != b"\x89PNG\r\n\x1a\n" or len(data) < 24:
        return None
    return int(struct.unpack(">I", data[16:20])[0])


def _option(n: int, w: Waypoint, here: Any, to_px: _MapPixels) -> dict[str, Any]:
    row: dict[str, Any] = {"n": n + 1, "id": w.waypoint_id, "kind": w.kind, "option": w.option,
                           "position_m": xy(w.position_world_m), "map_px": to_px(w.position_world_m[:2]),
                           "distance_m": round(math.dist(here, w.position_world_m[:2]), 1)}
    if w.path_length_m is not None:
        row["path_length_m"] = round(w.path_length_m, 1)
    if w.distance_to_candidate_m is not None:
        row["distance_to_candidate_m"] = round(w.distance_to_candidate_m, 1)
    return row


def active_candidates(obs: Observation) -> list[str]:
    """Candidates GO_TO_CANDIDATE and REJECT may name (the VLM parser's rule, agents/vlm/parse.py)."""
    return [c.candidate_id for c in obs.coordination.candidates if c.status in ("pending", "arrived")]


def _choices(obs: Observation, options: list[dict[str, Any]]) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    for action in obs.legal_actions:
        if action in ("MOVE_TO_UAV_WAYPOINT", "MOVE_TO_ROAD_WAYPOINT"):
            for o in options:
                what = o["option"] or o["kind"]
                far = f"{o['path_length_m']:.0f} m by road" if "path_length_m" in o else f"{o['distance_m']:.0f} m"
                hint = f", {o['distance_to_candidate_m']:.0f} m from the candidate" if "distance_to_candidate_m" in o else ""
                out.append({"action": action, "waypoint_id": o["id"], "label": f"Move to {o['id']} ({what}, {far}{hint})",
                            "key": OPTION_KEYS[o["n"] - 1] if o["n"] <= len(OPTION_KEYS) else None})
        elif action in ("GO_TO_CANDIDATE", "REJECT"):
            ids: list[str | None] = [*active_candidates(obs)] or ([None] if action == "REJECT" else [])
            for cid in ids:
                verb = "Go to candidate" if action == "GO_TO_CANDIDATE" else "Reject candidate"
                out.append({"action": action, "candidate_id": cid, "label": f"{verb} {cid}" if cid else "Reject",
                            "key": ACTION_KEYS[action] if len(ids) == 1 else None})
        elif action == "ANNOTATE_CANDIDATE":
            out.append({"action": action, "needs": "cell", "key": ACTION_KEYS[action],
                        "label": "Annotate a cell: click it on the grid, or type it (e.g. C3)"})
        else:
            label = {"NO_RELIABLE_CANDIDATE": "No reliable candidate here", "STOP_OBSERVE": "Stop and observe (six views)",
                     "CONFIRM": "Confirm: the target is here", "WAIT": "Wait"}.get(action, action)
            out.append({"action": action, "label": label, "key": ACTION_KEYS.get(action)})
    return out


UGV_HINTS = {
    "six_view": "Six views around the UGV: CONFIRM only if the target is clearly visible and near; else REJECT or move on.",
    "arrival": "You are at the candidate: STOP_OBSERVE for the six views, or drive closer.",
    "candidate_reminder": "A candidate is known: GO_TO_CANDIDATE drives there by road; then STOP_OBSERVE to look around.",
    "post_rejection": "The candidate was rejected: drive other roads, or wait for the UAV's next candidate.",
    "free_exploration": "No candidate yet: drive the roads, or wait for the UAV's candidate.",
}
"""The UGV's line for each stage of its AGOS-Agent prompt (agents/vlm/agos_prompts.py)."""


def _hint(obs: Observation, active: dict[str, Any] | None, rejected: list[list[float]]) -> str:
    """One line on where the task stands for this role: the stage AGOS-Agent's prompt is in, said to a
    person. ``active``, ``rejected``: :func:`~agos.agents.vlm.request.candidate_facts`."""
    if obs.role == "uav":
        if active is not None:
            return (f"Candidate {active['id']} is with the UGV: annotating is off until it is confirmed or rejected. "
                    "Keep searching or wait.")
        if rejected:
            return "A candidate was rejected: search on, elsewhere. Annotate one cell only when colour and body type match."
        return ("Search: fly over the searchable area (grey dots on the map) and annotate the one cell where the "
                "target is, when colour and body type match the references.")
    rgpp = "GO_TO_CANDIDATE" in obs.legal_actions or active is None  # as agos_prompts.ugv_prompt has it
    return UGV_HINTS[ugv_stage(obs, active, rejected, rgpp=rgpp)]
