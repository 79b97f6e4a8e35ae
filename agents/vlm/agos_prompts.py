"""AGOS-Agent prompts: one system prompt per role, and a user prompt rebuilt at every decision
from the role's observation, its coordination view and its memory, conditioned on the task stage.

UAV stages: ``search`` (no active candidate), ``candidate_active`` (its candidate is being verified:
annotation is off, the UAV holds or moves, a guidance message allowed; every decision meanwhile when
the run's UAV is ``active``, only after ``max_freeze_s`` when it is ``frozen``), ``post_rejection``
(search again, rejected regions listed). UGV stages: ``free_exploration``, ``candidate_reminder``,
``arrival``, ``six_view``, ``post_rejection``. The UAV's images include its teammate's top view; the
UGV's prompt states the remaining confirmation budget the world sends. The wording is ours; the
structure follows the paper's Appendix C.
"""

from __future__ import annotations

import math
from typing import Any

from agos.agents.vlm import protocol
from agos.agents.vlm.request import (
    PANEL_NOTES,
    REPLY_FORMAT,
    Memory,
    Prompt,
    PromptBuilder,
    budget,
    camera_facts,
    candidate_facts,
    confirmation_text,
    confirmations,
    frame,
    messages,
    options,
    panel_cameras,
    reference_cameras,
    reference_scale,
    teammate_scale,
    unvisited_nearest,
    xy,
)
from agos.runtime.schemas import Observation
from agos.runtime.settings import DEFAULTS

ARRIVAL_RADIUS_M = 12.0
"""Without road-graph planning (no_rgpp), the UGV counts as arrived this close to the centre."""

UAV_SYSTEM = """You are the aerial member of a two-robot search team. You fly a drone at a fixed height of \
about 80 m with a camera pointing straight down. Your teammate is a ground vehicle (UGV) that can drive the \
roads and look at cars up close. Together you must find one specific parked car, the target, shown in the \
reference pictures.

Your image of the ground carries a 5 x 5 grid: rows A (top) to E (bottom), columns 1 (left) to 5 (right), \
so A1 is the top-left cell and E5 the bottom-right one. Compare the cars you see with the reference: paint \
colour first, then body type, length and shape. One picture shows your teammate, the UGV, from above, so \
that you do not take it for another car. The target always stands on a street where cars drive, so a \
match on a road or at a junction is far more likely than one on a pavement, a lawn or a roof.

What you can do:
- MOVE_TO_UAV_WAYPOINT: fly to one of the listed neighbouring waypoints to see another part of the region.
- ANNOTATE_CANDIDATE: name the single grid cell holding a car that matches the target. A tool turns the \
cell into a region on the ground and the UGV drives there to check it. Annotations are limited, so only \
annotate with concrete evidence: matching colour AND matching body type or size.
- NO_RELIABLE_CANDIDATE: say that nothing here is convincing (you then stay and decide again shortly).
- WAIT: hold position until something changes.
While the UGV verifies your candidate you cannot annotate another one; keep searching nearby or wait, and \
you may send short guidance messages. If the UGV rejects your candidate, that region was wrong: do not \
annotate it again and continue the search elsewhere."""

UGV_SYSTEM = """You are the ground member of a two-robot search team: a car-sized robot (UGV) driving on \
the road network. Your teammate is a drone (UAV) searching from above. Together you must find one \
specific parked car, the target, shown in the reference pictures. Only you can finish the task: stop near \
the target, look around, and CONFIRM it.

While driving you only see a forward camera image, so you can miss things. STOP_OBSERVE halts you and gives \
six camera views around you, in this order: front-left, front, front-right, back-left, back, back-right.

What you can do:
- MOVE_TO_ROAD_WAYPOINT: drive to one of the listed road waypoints (forward ~10 m, forward ~30 m, a junction \
exit, or back).
- GO_TO_CANDIDATE: drive along the road network to a region the UAV reported (give its candidate_id).
- STOP_OBSERVE: stop and take the six views.
- CONFIRM: declare that the target is found. Only after STOP_OBSERVE, and only when one of the six views \
clearly shows the target (same colour, same body type, and a roof in another colour, a roof rack or a \
stripe only if the reference has one) nearby, not hidden. A wrong CONFIRM ends the task as \
a failure.
- REJECT: declare that the candidate region does not contain the target; the UAV then searches again.
- WAIT: hold still until something changes (for example a new candidate).
Keep messages to the UAV short and factual."""


def uav_prompt(obs: Observation, memory: Memory, *, images: str = DEFAULTS.vlm.images) -> Prompt:
    active, candidates, rejected = candidate_facts(obs)
    stage = "candidate_active" if active else ("post_rejection" if rejected else "search")
    c = obs.coordination
    b = PromptBuilder(images)
    nadir = frame(obs, "nadir", "rgb_grid") or frame(obs, "nadir")
    b.text(f"Decision {obs.decision_index}. Team budget: {budget(obs)['left']} of {c.decision_budget} decisions left. "
           f"You are at ({obs.pose.position_world_m[0]:.0f}, {obs.pose.position_world_m[1]:.0f}) m, "
           f"{obs.pose.position_world_m[2]:.0f} m up. Annotations used: {c.annotations_used} of {c.max_annotations}.")
    if nadir is not None:
        b.image(protocol.AERIAL, nadir, "Your downward camera image with the A1-E5 grid")
    b.map(obs)
    b.references(obs, top_only=b.images != "all")
    b.teammate(obs)
    if active is not None:  # stage == "candidate_active"
        only = "" if "NO_RELIABLE_CANDIDATE" in obs.legal_actions else " Until it is resolved you may only move or wait."
        b.text(f"STAGE: candidate {active['id']} (cell {active['cell']}) is with the UGV for checking "
               f"(status {active['status']}). You cannot annotate now.{only} Hold position with WAIT, or move on to "
               "cover unvisited waypoints; a short guidance message to the UGV (where the car stands, how to "
               "recognise it) is allowed.")
    elif stage == "post_rejection":
        regions = "; ".join(f"({x:.0f}, {y:.0f})" for x, y in rejected)
        b.text(f"STAGE: search again. The UGV rejected the region(s) around {regions} m: do not annotate "
               "those cars again. Look for another match or fly to unvisited waypoints.")
    else:
        b.text("STAGE: aerial search. If a car in your image matches the target in colour and body type, "
               "annotate its cell. Otherwise fly towards unvisited waypoints, covering the region systematically.")
    if memory.recent:
        b.text("Your recent decisions: " + " | ".join(memory.recent))
    if c.messages:
        b.text("Messages from the UGV: " + " | ".join(f"{m['text']}" for m in messages(obs)))
    b.text(f"Legal actions now: {', '.join(obs.legal_actions)}. " + REPLY_FORMAT)
    b.state({
        "protocol": "agos-agent", "role": "uav", "stage": stage, "step": obs.decision_index, "budget": budget(obs),
        "position_m": xy(obs.pose.position_world_m), "altitude_m": round(obs.pose.position_world_m[2], 1),
        "yaw_deg": round(math.degrees(obs.pose.yaw_rad), 1), "camera": camera_facts(nadir),
        "annotations": {"used": c.annotations_used, "max": c.max_annotations},
        "active_candidate": active, "candidates": candidates, "rejected_regions_m": rejected,
        "messages": messages(obs), "waypoint_options": options(obs, memory),
        "unvisited_waypoints": unvisited_nearest(obs, memory),
        "coverage": {"visited": len(set(memory.visited)), "total": len(obs.active_uav_waypoints)},
        "memory": list(memory.recent), "legal_actions": list(obs.legal_actions),
        "reference_m_per_px": reference_scale(obs), "teammate_m_per_px": teammate_scale(obs),
        "reference_cameras": reference_cameras(obs)})
    return Prompt(UAV_SYSTEM, b.parts, stage, list(obs.legal_actions), b.image_bytes)


def ugv_stage(obs: Observation, active: dict[str, Any] | None, rejected: list[list[float]], *, rgpp: bool) -> str:
    if obs.mode == "stop_6view":
        return "six_view"
    if active is not None:
        arrived = active["status"] == "arrived" or (not rgpp and active["distance_m"] <= ARRIVAL_RADIUS_M)
        return "arrival" if arrived else "candidate_reminder"
    return "post_rejection" if rejected else "free_exploration"


def ugv_prompt(obs: Observation, memory: Memory, *, images: str = DEFAULTS.vlm.images) -> Prompt:
    active, candidates, rejected = candidate_facts(obs)
    rgpp = "GO_TO_CANDIDATE" in obs.legal_actions or active is None
    stage = ugv_stage(obs, active, rejected, rgpp=rgpp)
    b = PromptBuilder(images)
    p = obs.pose.position_world_m
    b.text(f"Decision {obs.decision_index}. Team budget: {budget(obs)['left']} of {obs.coordination.decision_budget} "
           f"decisions left. You are at ({p[0]:.0f}, {p[1]:.0f}) m, heading "
           f"{math.degrees(obs.pose.yaw_rad):.0f} deg (0 = east, 90 = north). Mode: "
           f"{'stopped, six views' if obs.mode == 'stop_6view' else 'driving'}. " + confirmation_text(obs))
    cam = b.ground_views(obs)
    b.text(_ugv_stage_text(stage, active, rejected, rgpp=rgpp))
    if memory.recent:
        b.text("Your recent decisions: " + " | ".join(memory.recent))
    if obs.coordination.messages:
        b.text("Messages from the UAV: " + " | ".join(m["text"] for m in messages(obs)))
    b.text(f"Legal actions now: {', '.join(obs.legal_actions)}. " + REPLY_FORMAT)
    b.state({
        "protocol": "agos-agent", "role": "ugv", "stage": stage, "step": obs.decision_index, "budget": budget(obs),
        "confirmations": confirmations(obs), "position_m": xy(p),
        "heading_deg": round(math.degrees(obs.pose.yaw_rad), 1), "mode": obs.mode,
        "fresh_stop": obs.fresh_stop_observe, "camera": camera_facts(cam), "active_candidate": active,
        "candidates": candidates, "rejected_regions_m": rejected, "messages": messages(obs),
        "waypoint_options": options(obs, memory), "memory": list(memory.recent),
        "legal_actions": list(obs.legal_actions), "panels": list(PANEL_NOTES) if obs.mode == "stop_6view" else [],
        "panel_cameras": panel_cameras(obs),
        "reference_m_per_px": reference_scale(obs),
        "reference_cameras": reference_cameras(obs), "arrival_radius_m": ARRIVAL_RADIUS_M})
    return Prompt(UGV_SYSTEM, b.parts, stage, list(obs.legal_actions), b.image_bytes)


def _ugv_stage_text(stage: str, active: dict[str, Any] | None, rejected: list[list[float]], *, rgpp: bool) -> str:
    if stage == "six_view":
        who = f" for candidate {active['id']}" if active else ""
        return (f"STAGE: six-view check{who}. Look at all six panels (front-left, front, front-right, back-left, "
                "back, back-right). CONFIRM only if a car in them clearly is the target: same paint colour, same "
                "body type, a contrasting roof, roof rack or stripe exactly where the reference has one, close "
                "to you and not hidden. Otherwise REJECT" + (f" with candidate_id {active['id']}" if active
                                                                               else "") + " and tell the UAV.")
    if stage == "arrival":
        assert active is not None, "ugv_stage gives this stage only with an active candidate"
        return (f"STAGE: you have reached the area of candidate {active['id']}. Use STOP_OBSERVE now to look around, "
                "and send the UAV a short arrival message.")
    if stage == "candidate_reminder":
        assert active is not None, "ugv_stage gives this stage only with an active candidate"
        if rgpp:
            return (f"STAGE: PRIORITY. The UAV reported candidate {active['id']} (cell {active['cell']}, centre "
                    f"({active['center_m'][0]:.0f}, {active['center_m'][1]:.0f}) m, {active['distance_m']:.0f} m away). "
                    f"Nothing matters more now than checking it: answer GO_TO_CANDIDATE, candidate_id {active['id']}.")
        return (f"STAGE: PRIORITY. The UAV reported candidate {active['id']} around ({active['center_m'][0]:.0f}, "
                f"{active['center_m'][1]:.0f}) m, {active['distance_m']:.0f} m away. There is no route tool: pick the "
                "road waypoint whose distance_to_candidate_m is smallest (avoid ones you visited) and STOP_OBSERVE "
                f"once you are within about {ARRIVAL_RADIUS_M:.0f} m.")
    if stage == "post_rejection":
        regions = "; ".join(f"({x:.0f}, {y:.0f})" for x, y in rejected)
        return (f"STAGE: the candidate(s) around {regions} m were rejected; do not go back there. Explore other roads "
                "or wait for a new candidate from the UAV; stop and look if a car like the target appears ahead.")
    return ("STAGE: free exploration. No candidate yet. Explore the roads, or wait for the UAV's report. If the "
            "forward view shows a car that looks very much like the reference, STOP_OBSERVE and look around.")
