"""One decision as a fine-tuning example: AGOS-Agent's request with the expert's answer.

Format (one JSON object per line; read directly by LLaMA-Factory's ``sharegpt`` loader with
``messages`` and ``images`` columns, and by ms-swift):

    {"id": "<episode>/<role>/<decision>", "episode_id": ..., "role": ..., "decision_index": ...,
     "stage": ..., "messages": [{"role": "system", "content": "..."},
                                {"role": "user", "content": "...<image>...<image>..."},
                                {"role": "assistant", "content": "{\\"action\\": ...}"}],
     "images": ["episodes/<ep>/<role>/d001/nadir_grid.jpg", ...]}

The user turn is the text parts of the request joined by newlines, with ``<image>`` where each image
goes; ``images`` lists the image files in that order (paths relative to the dataset directory), whose
bytes are exactly those the agent sends. The assistant turn is the expert's action as the reply JSON
the agent parses (agents/vlm/protocol.py).
"""

from __future__ import annotations

import base64
import json
from collections.abc import Callable
from typing import Any

from agos.agents.vlm.protocol import IMAGE_LABEL
from agos.agents.vlm.request import Prompt
from agos.runtime.schemas import Action

IMAGE_TOKEN = "<image>"
REPLY_FIELDS = ("waypoint_id", "cell", "candidate_id", "message")


def reply_json(action: Action) -> str:
    """The reply a model would give for ``action``: ``action`` and the fields it sets."""
    reply: dict[str, Any] = {"action": action.action}
    for name in REPLY_FIELDS:
        value = getattr(action, name)
        if value:
            reply[name] = value
    return json.dumps(reply, separators=(",", ":"))


def chat_example(prompt: Prompt, action: Action, image_path: Callable[[str, bytes, str], str]) -> dict[str, Any]:
    """``prompt`` answered with ``action``. ``image_path(label, data, encoding)`` stores (or finds) the
    file holding an image of the request and returns its path for the example."""
    texts: list[str] = []
    images: list[str] = []
    label = "image"
    for part in prompt.parts:
        if part["type"] == "text":
            texts.append(part["text"])
            found = IMAGE_LABEL.search(part["text"])
            label = found.group(1) if found else "image"
        else:
            header, b64 = part["image_url"]["url"].split(",", 1)
            encoding = "jpeg" if "jpeg" in header else "png"
            images.append(image_path(label, base64.b64decode(b64), encoding))
            texts.append(IMAGE_TOKEN)
    return {"messages": [{"role": "system", "content": prompt.system},
                         {"role": "user", "content": "\n".join(texts)},
                         {"role": "assistant", "content": reply_json(action)}],
            "images": images}
