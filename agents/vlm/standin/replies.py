"""What the stand-in says: the message content each outcome gives, the token cap, the completion object."""

from __future__ import annotations

import json
import random
import time
from typing import Any

from agos.agents.vlm.standin.requests import text_tokens

LEADS = ("Here is my decision:", "Based on the images, this is the best action now.", "Sure! I will act as follows:")
TRAILS = ("I chose this because it is what the current views support.", "Let me know if you need anything else.",
          "Note: the target may be partly occluded.")
PROSE = ("I am not able to decide from these images; the target is not clearly visible.",
         "The best action is to wait and look again")


def _prefix(text: str, rng: random.Random) -> str:
    """A proper prefix of ``text`` (never valid JSON when ``text`` is a JSON object)."""
    return text[:rng.randint(1, max(1, len(text) - 2))]


def render_content(outcome: str, reply: dict[str, Any], *, structured: bool, wrap_p: float,
                   rng: random.Random) -> tuple[str | None, str]:
    """The message content and finish_reason a model would give for this outcome."""
    text = json.dumps(reply, ensure_ascii=False)
    if outcome == "malformed":
        return (_prefix(text, rng) if rng.random() < 0.7 else rng.choice(PROSE)), "stop"
    if outcome == "fenced":
        return f"```json\n{text}\n```\n{rng.choice(TRAILS)}", "stop"
    if outcome == "empty":
        return rng.choice(("", None)), "stop"
    if outcome == "length":
        return _prefix(text, rng), "length"
    if structured or rng.random() >= wrap_p:
        return text, "stop"
    style = rng.randrange(3)
    fenced = f"```json\n{text}\n```"
    return (fenced if style == 0 else f"{rng.choice(LEADS)}\n{text if style == 1 else fenced}"), "stop"


def cap_tokens(content: str | None, finish: str, max_tokens: int | None) -> tuple[str | None, str]:
    """Cut a reply longer than ``max_tokens`` (4 characters a token) and mark it ``length``."""
    if content is None or max_tokens is None or text_tokens(content) <= max_tokens:
        return content, finish
    return content[:max_tokens * 4], "length"


def completion_body(index: int, model: str, choices: list[tuple[str | None, str]], prompt_tokens: int) -> dict[str, Any]:
    """An OpenAI ``chat.completion`` object with one choice per ``(content, finish_reason)``;
    ``completion_tokens`` counts every choice's content. Its id and time stamp have a fixed width, so
    the body's size (a decision's ``reply_bytes`` on the link to the model) depends on the answer alone,
    not on how many requests the server answered before."""
    completion = sum(text_tokens(content or "") for content, _ in choices)
    return {
        "id": f"chatcmpl-standin-{index:08d}", "object": "chat.completion", "created": int(time.time()), "model": model,
        "system_fingerprint": "agos-vlm-standin",
        "choices": [{"index": i, "message": {"role": "assistant", "content": content}, "logprobs": None, "finish_reason": finish}
                    for i, (content, finish) in enumerate(choices)],
        "usage": {"prompt_tokens": prompt_tokens, "completion_tokens": completion, "total_tokens": prompt_tokens + completion},
    }
