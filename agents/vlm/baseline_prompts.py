"""Baseline prompts: the same roles and images, but no candidate tools and no stages.

The UAV sorts what it sees into CLEAR_MATCH, AMBIGUOUS or NONE; for a centred clear match it
waits and sends its own position as a rough search anchor in a text message. The UGV reads the
latest anchor from the UAV's messages, sees its distance to it and each road option's distance to
it, drives there by ordinary road waypoints, stops to look, then confirms or rejects. Neither role
may use candidate ids, grid cells or target coordinates (the world does not even offer
ANNOTATE_CANDIDATE or GO_TO_CANDIDATE in a Baseline run).
"""

from __future__ import annotations

import math

from agos.agents.vlm import protocol
from agos.agents.vlm.request import (
    PANEL_NOTES,
    REPLY_FORMAT,
    Memory,
    Prompt,
    PromptBuilder,
    budget,
    camera_facts,
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

STALL_WAITS = 3
"""After this many WAITs in one place the UAV prompt tells it to move on."""
INSPECTED_RADIUS_M = 15.0

UAV_SYSTEM = """You are a drone flying about 80 m above a town with a downward camera, searching for one \
parked car (the target, see the reference pictures) together with a ground robot (UGV). You cannot mark \
anything on a map for the UGV; you can only fly and talk to it in short messages. One picture shows the \
UGV from above, so that you do not take it for another car.

At every decision, first classify what your image shows:
- CLEAR_MATCH: a car with the target's paint colour and body type.
- AMBIGUOUS: something similar, but colour or shape is uncertain.
- NONE: no plausible target.
Then act:
- CLEAR_MATCH near the centre of your image: WAIT, and send the UGV a message with your current position, \
written as (x, y) in metres, as the place to search.
- CLEAR_MATCH away from the centre: move to the waypoint that brings it under you.
- AMBIGUOUS or NONE: move to a waypoint you have not visited, covering the area systematically.
Never output grid cells, candidate ids, boxes or target coordinates; only your own position."""

UGV_SYSTEM = """You are a ground robot (UGV) on the road network of a town, searching for one parked car \
(the target, see the reference pictures) together with a drone (UAV). The UAV may send you messages with a \
position (x, y) in metres: treat the latest one as an approximate place to search, not an exact location.

While driving you see only a forward camera. Drive towards the UAV's position by choosing road waypoints \
that bring you closer to it. Stop with STOP_OBSERVE when you are near that position or when a car like the \
target appears ahead. After STOP_OBSERVE you get six views (front-left, front, front-right, back-left, back, \
back-right). Say CONFIRM only when one of them shows, close by, a car that is without doubt the target; if \
none does, REJECT and carry on. A \
wrong CONFIRM ends the task as a failure. Never use candidate ids, grid cells, boxes or target coordinates."""


def uav_prompt(obs: Observation, memory: Memory, *, images: str = DEFAULTS.vlm.images) -> Prompt:
    b = PromptBuilder(images)
    p = obs.pose.position_world_m
    nadir = frame(obs, "nadir")
    b.text(f"Decision {obs.decision_index}; {budget(obs)['left']} team decisions left. You are at "
           f"({p[0]:.0f}, {p[1]:.0f}) m, {p[2]:.0f} m up.")
    if nadir is not None:
        b.image(protocol.AERIAL, nadir, "Your downward camera image")
    b.map(obs)
    b.references(obs, top_only=b.images != "all")
    b.teammate(obs)
    if obs.coordination.messages:
        b.text("Messages from the UGV: " + " | ".join(m["text"] for m in messages(obs)))
    stalled = memory.waits_here >= STALL_WAITS
    if stalled:
        b.text(f"Reminder: you have waited {memory.waits_here} times here. Unless the UGV is on its way, move on.")
    b.text("Classify the evidence (CLEAR_MATCH, AMBIGUOUS, NONE), then act by the rules. "
           f"Valid waypoint ids: {', '.join(w.waypoint_id for w in obs.waypoint_options)}. "
           f"Legal actions now: {', '.join(obs.legal_actions)}. " + REPLY_FORMAT)
    b.state({
        "protocol": "baseline", "role": "uav", "step": obs.decision_index, "budget": budget(obs),
        "position_m": xy(p), "altitude_m": round(p[2], 1), "camera": camera_facts(nadir),
        "messages": messages(obs), "waypoint_options": options(obs, memory),
        "unvisited_waypoints": unvisited_nearest(obs, memory), "waits_here": memory.waits_here,
        "stall_reminder": stalled, "legal_actions": list(obs.legal_actions),
        "reference_m_per_px": reference_scale(obs), "teammate_m_per_px": teammate_scale(obs),
        "reference_cameras": reference_cameras(obs)})
    return Prompt(UAV_SYSTEM, b.parts, "baseline", list(obs.legal_actions), b.image_bytes)


def anchor_from_messages(obs: Observation, memory: Memory) -> tuple[float, float] | None:
    """The position in the latest UAV message that the UGV has not already inspected."""
    for m in reversed(obs.coordination.messages):
        if m.sender != "uav":
            continue
        found = protocol.coordinates(m.text)
        if not found:
            continue
        point = found[-1]
        if any(math.dist(point, done) <= INSPECTED_RADIUS_M for done in memory.inspected_anchors):
            return None
        return point
    return None


def ugv_prompt(obs: Observation, memory: Memory, *, images: str = DEFAULTS.vlm.images) -> Prompt:
    b = PromptBuilder(images)
    p = obs.pose.position_world_m
    anchor = anchor_from_messages(obs, memory)
    b.text(f"Decision {obs.decision_index}; {budget(obs)['left']} team decisions left. You are at "
           f"({p[0]:.0f}, {p[1]:.0f}) m. Mode: {'stopped, six views' if obs.mode == 'stop_6view' else 'driving'}. "
           + confirmation_text(obs))
    cam = b.ground_views(obs)
    if obs.coordination.messages:
        b.text("Messages from the UAV: " + " | ".join(m["text"] for m in messages(obs)))
    anchor_row = None
    if anchor is not None:
        d = math.dist(p[:2], anchor)
        anchor_row = {"position_m": [anchor[0], anchor[1]], "distance_m": round(d, 1)}
        b.text(f"Search anchor from the UAV: ({anchor[0]:.0f}, {anchor[1]:.0f}) m, {d:.0f} m from you. Each road "
               "option below shows its distance to the anchor.")
    elif obs.mode != "stop_6view":
        b.text("No search anchor from the UAV yet: wait for one or explore; stop if a target-like car appears ahead.")
    b.text(f"Legal actions now: {', '.join(obs.legal_actions)}. " + REPLY_FORMAT)
    extra = {} if anchor is None else {"distance_to_anchor_m": lambda w: round(math.dist(w.position_world_m[:2], anchor), 1)}
    b.state({
        "protocol": "baseline", "role": "ugv", "step": obs.decision_index, "budget": budget(obs),
        "confirmations": confirmations(obs), "position_m": xy(p),
        "heading_deg": round(math.degrees(obs.pose.yaw_rad), 1), "mode": obs.mode, "fresh_stop": obs.fresh_stop_observe,
        "camera": camera_facts(cam), "anchor": anchor_row, "messages": messages(obs),
        "waypoint_options": options(obs, memory, **extra), "legal_actions": list(obs.legal_actions),
        "panels": list(PANEL_NOTES) if obs.mode == "stop_6view" else [], "panel_cameras": panel_cameras(obs),
        "reference_m_per_px": reference_scale(obs),
        "reference_cameras": reference_cameras(obs)})
    return Prompt(UGV_SYSTEM, b.parts, "six_view" if obs.mode == "stop_6view" else "baseline",
                  list(obs.legal_actions), b.image_bytes)
