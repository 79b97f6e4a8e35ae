"""How agos lays out a VLM request, so that a model and the offline stand-in read the same thing.

A request is one system message and one user message. The user message is a list of content
parts: text parts and images. Two conventions make the request self-describing:

* Every image is preceded by a text part whose last line is ``[image: LABEL]`` (the labels are
  listed below). A model reads the label as a caption; :func:`split_request` uses it to know which
  picture is which.
* The task state is a single-line JSON object after the line ``STATE (JSON):`` in a text part:
  the same facts the prose of the prompt gives, in a form a model can quote ids from. Its keys
  are documented in ``docs/AGENTS.md`` (section "The VLM request").

The reply is one JSON object ``{"action": ..., "waypoint_id"|"cell"|"candidate_id": ...,
"message": ..., "reason": ...}`` (schema: :func:`action_schema`).
"""

from __future__ import annotations

import base64
import json
import re
from dataclasses import dataclass, field
from typing import Any

STATE_MARKER = "STATE (JSON):"
IMAGE_LABEL = re.compile(r"\[image: ([a-z0-9_]+)\]\s*$")

AERIAL = "aerial_grid"
"""The UAV's nadir RGB with the 5x5 grid drawn on it (cells A1 top-left .. E5 bottom-right)."""
MAP = "topdown_map"
FORWARD = "forward"
SIX_VIEWS = ("front_left", "front", "front_right", "back_left", "back", "back_right")
REFERENCE_PREFIX = "target_ref_"
"""``target_ref_top`` (with a metric scale in the state), ``target_ref_front`` ..."""
TEAMMATE_REFERENCE = "teammate_ref_top"
"""UAV requests: the UGV seen from straight above (not a target reference: no ``target_ref_`` prefix)."""


COORDINATE = re.compile(r"\(\s*(-?\d+(?:\.\d+)?)\s*,\s*(-?\d+(?:\.\d+)?)\s*\)")
"""How positions are written in messages between the roles: ``(x, y)`` in metres."""


def coordinates(text: str) -> list[tuple[float, float]]:
    """Every ``(x, y)`` position written in a message, in order."""
    return [(float(x), float(y)) for x, y in COORDINATE.findall(text)]


def image_caption(label: str, note: str = "") -> str:
    """The text part that goes right before an image."""
    return (f"{note}\n" if note else "") + f"[image: {label}]"


def state_text(state: dict[str, Any]) -> str:
    return f"{STATE_MARKER}\n{json.dumps(state, separators=(',', ':'), sort_keys=True)}"


def action_schema(actions: list[str]) -> dict[str, Any]:
    """JSON schema of a reply: ``action`` restricted to the legal ones, other fields optional."""
    return {
        "type": "object",
        "properties": {
            "action": {"type": "string", "enum": list(actions)},
            "waypoint_id": {"type": "string"},
            "cell": {"type": "string", "pattern": "^[A-E][1-5]$"},
            "candidate_id": {"type": "string"},
            "message": {"type": "string", "maxLength": 200},
            "reason": {"type": "string", "maxLength": 300},
        },
        "required": ["action"],
        "additionalProperties": False,
    }


@dataclass
class SplitRequest:
    """A chat request taken apart: system text, user text, the state object, labelled images."""

    system: str
    text: str
    state: dict[str, Any] | None
    images: dict[str, bytes] = field(default_factory=dict)
    """Label -> encoded image bytes (JPEG or PNG), decoded from the data URLs."""
    unlabelled: int = 0


def _data_url_bytes(url: str) -> bytes:
    if not url.startswith("data:") or "," not in url:
        raise ValueError("image_url is not a base64 data URL")
    return base64.b64decode(url.split(",", 1)[1])


def split_request(messages: list[dict[str, Any]]) -> SplitRequest:
    """Take apart the ``messages`` of a chat completion laid out by agos (raises ValueError)."""
    system_parts: list[str] = []
    texts: list[str] = []
    images: dict[str, bytes] = {}
    unlabelled = 0
    for message in messages:
        content = message.get("content")
        parts: list[dict[str, Any]] = (
            [{"type": "text", "text": content}] if isinstance(content, str) else (content or [])
        )
        label = None
        for part in parts:
            if part.get("type") == "text":
                text = str(part.get("text", ""))
                (system_parts if message.get("role") == "system" else texts).append(text)
                match = IMAGE_LABEL.search(text)
                label = match.group(1) if match else None
            elif part.get("type") == "image_url":
                data = _data_url_bytes(str((part.get("image_url") or {}).get("url", "")))
                if label is None:
                    unlabelled += 1
                else:
                    images[label] = data
                label = None
    text = "\n".join(texts)
    state = None
    at = text.rfind(STATE_MARKER)
    if at != -1:
        line = text[at + len(STATE_MARKER):].strip().splitlines()
        if line:
            state = json.loads(line[0])
    return SplitRequest(system="\n".join(system_parts), text=text, state=state, images=images, unlabelled=unlabelled)
