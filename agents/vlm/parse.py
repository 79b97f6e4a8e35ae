"""Parser-validator: any model reply -> one legal action, or a logged fallback.

Models answer with JSON, often wrapped: markdown fences, reasoning in ``<think>`` blocks, text
before or after, single quotes, trailing commas, Python literals. :func:`extract_json` finds the
first JSON object and repairs only such syntax, never content. :func:`to_action` then checks the
object against the observation: the action must be legal now, a waypoint one of the options, a
cell A1-E5, a candidate one the role knows. Anything else becomes the fallback (WAIT, always
legal) with the reason recorded. A truncated reply (``finish_reason == "length"``) is never
repaired into an action: a plausible but wrong action is worse than a WAIT.
"""

from __future__ import annotations

import ast
import json
import re
from dataclasses import dataclass
from typing import Any

from agos.agents.contract import action_for
from agos.runtime.schemas import Action, Observation

FENCE = re.compile(r"```(?:json|JSON)?\s*(.*?)```", re.DOTALL)
THINK = re.compile(r"<think>.*?</think>", re.DOTALL | re.IGNORECASE)
TRAILING_COMMA = re.compile(r",\s*([}\]])")
CELL = re.compile(r"^[A-Ea-e][1-5]$")


@dataclass(frozen=True)
class Parsed:
    action: Action
    fallback: bool
    reason: str | None
    """Why the reply was not used (None when it was)."""
    repaired: bool = False


def extract_json(text: str | None) -> tuple[dict[str, Any] | None, bool]:
    """The first JSON object in a reply and whether syntax had to be repaired."""
    if not text:
        return None, False
    body = THINK.sub("", text)
    candidates = [m.group(1) for m in FENCE.finditer(body)] + [body]
    for chunk in candidates:
        start = chunk.find("{")
        while start != -1:
            obj, repaired = _object_at(chunk, start)
            if obj is not None:
                return obj, repaired or chunk is not body or start > 0
            start = chunk.find("{", start + 1)
    return None, False


def _object_at(text: str, start: int) -> tuple[dict[str, Any] | None, bool]:
    depth, in_str, quote, end, escaped = 0, False, "", None, False
    for i in range(start, len(text)):
        ch = text[i]
        if in_str:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == quote:
                in_str = False
        elif ch in "\"'":
            in_str, quote = True, ch
        elif ch == "{":
            depth += 1
        elif ch == "}":
            depth -= 1
            if depth == 0:
                end = i + 1
                break
    if end is None:
        return None, False
    raw = text[start:end]
    try:
        obj = json.loads(raw)
        return (obj, False) if isinstance(obj, dict) else (None, False)
    except (json.JSONDecodeError, RecursionError):
        pass
    fixed = TRAILING_COMMA.sub(r"\1", raw)
    try:
        obj = json.loads(fixed)
        return (obj, True) if isinstance(obj, dict) else (None, False)
    except (json.JSONDecodeError, RecursionError):
        pass
    try:  # single quotes, True/False/None: a Python literal, evaluated safely
        obj = ast.literal_eval(fixed)
        return (obj, True) if isinstance(obj, dict) else (None, False)
    except (ValueError, SyntaxError, MemoryError, RecursionError, TypeError):
        return None, False


def _text(value: Any, limit: int = 300) -> str | None:
    return None if value is None else str(value)[:limit]


def to_action(reply: str | None, obs: Observation, *, truncated: bool = False) -> Parsed:
    def fallback(reason: str) -> Parsed:
        return Parsed(action_for(obs, "WAIT", rationale=f"fallback: {reason}"), True, reason)

    if truncated:
        return fallback("reply truncated (finish_reason=length); not repaired into an action")
    obj, repaired = extract_json(reply)
    if obj is None:
        return fallback("no JSON object in the reply")
    name = str(obj.get("action", "")).strip().upper()
    if name not in obs.legal_actions:
        return fallback(f"action {name or '<missing>'!r} is not legal now")
    fields: dict[str, Any] = {"message": _text(obj.get("message")), "rationale": _text(obj.get("reason") or obj.get("rationale"))}
    if name in ("MOVE_TO_UAV_WAYPOINT", "MOVE_TO_ROAD_WAYPOINT"):
        wp = str(obj.get("waypoint_id", obj.get("waypoint", ""))).strip()
        if wp not in {w.waypoint_id for w in obs.waypoint_options}:
            return fallback(f"waypoint {wp!r} is not an option")
        fields["waypoint_id"] = wp
    elif name == "ANNOTATE_CANDIDATE":
        cell = str(obj.get("cell", obj.get("grid_cell", ""))).strip()
        if not CELL.match(cell):
            return fallback(f"cell {cell!r} is not one of A1..E5")
        fields["cell"] = cell.upper()
    elif name in ("GO_TO_CANDIDATE", "REJECT"):
        known = {c.candidate_id for c in obs.coordination.candidates if c.status in ("pending", "arrived")}
        cid = obj.get("candidate_id")
        if cid is None and len(known) == 1:
            cid = next(iter(known))
        if str(cid) not in known:
            if name == "GO_TO_CANDIDATE" or known:
                return fallback(f"candidate {cid!r} is not an active candidate")
            cid = None
        fields["candidate_id"] = None if cid is None else str(cid)
    return Parsed(action_for(obs, name, **fields), False, None, repaired)
