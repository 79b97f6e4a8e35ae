"""Unit tests of AGOS-Dataset's pieces: the 10 m marks along a move, and a decision as a chat example."""

from __future__ import annotations

import base64
import json

import pytest

from agos.agents.dataset.example import IMAGE_TOKEN, chat_example, reply_json
from agos.agents.vlm.request import Prompt
from agos.runtime.schemas import Action
from agos.world.sim.capture import _points_every


def test_marks_fall_every_ten_metres_strictly_inside_a_bent_line() -> None:
    marks = _points_every([(0.0, 0.0), (25.0, 0.0), (25.0, 20.0)], 10.0)  # 45 m with a corner at 25 m
    assert [d for d, _, _ in marks] == [10.0, 20.0, 30.0, 40.0]
    assert marks[2][1] == pytest.approx((25.0, 5.0)) and marks[2][2] == pytest.approx(1.5707963)
    assert marks[1][1] == pytest.approx((20.0, 0.0)) and marks[1][2] == pytest.approx(0.0)


def test_no_mark_at_the_end_or_on_a_move_shorter_than_the_spacing() -> None:
    assert [d for d, _, _ in _points_every([(0.0, 0.0), (20.5, 0.0)], 10.0)] == [10.0]  # 20 is under 1 m from the end
    assert _points_every([(0.0, 0.0), (9.0, 0.0)], 10.0) == []
    assert _points_every([(3.0, 3.0)], 10.0) == []


def _url(data: bytes, mime: str) -> dict:
    return {"type": "image_url", "image_url": {"url": f"data:{mime};base64,{base64.b64encode(data).decode()}"}}


def test_a_request_becomes_messages_with_image_tokens_in_order() -> None:
    prompt = Prompt(system="You fly.", stage="search", actions=["WAIT", "ANNOTATE_CANDIDATE"], parts=[
        {"type": "text", "text": "Your view\n[image: aerial_grid]"}, _url(b"JPEGBYTES", "image/jpeg"),
        {"type": "text", "text": "[image: topdown_map]"}, _url(b"PNGBYTES", "image/png"),
        {"type": "text", "text": "STATE (JSON):\n{}"}])
    seen: list[tuple[str, bytes, str]] = []

    def store(label: str, data: bytes, encoding: str) -> str:
        seen.append((label, data, encoding))
        return f"d001/{label}.{encoding}"

    action = Action(run_id="r", episode_id="e", role="uav", decision_index=1, action="ANNOTATE_CANDIDATE",
                    cell="C3", message="Possible target in cell C3")
    ex = chat_example(prompt, action, store)
    assert seen == [("aerial_grid", b"JPEGBYTES", "jpeg"), ("topdown_map", b"PNGBYTES", "png")]
    assert ex["images"] == ["d001/aerial_grid.jpeg", "d001/topdown_map.png"]
    system, user, assistant = ex["messages"]
    assert system == {"role": "system", "content": "You fly."}
    assert user["content"] == "\n".join(["Your view", "[image: aerial_grid]", IMAGE_TOKEN, "[image: topdown_map]",
                                         IMAGE_TOKEN, "STATE (JSON):", "{}"])
    assert json.loads(assistant["content"]) == {"action": "ANNOTATE_CANDIDATE", "cell": "C3",
                                                "message": "Possible target in cell C3"}


def test_a_reply_names_only_the_fields_the_action_sets() -> None:
    wait = Action(run_id="r", episode_id="e", role="ugv", decision_index=2, action="WAIT")
    assert reply_json(wait) == '{"action":"WAIT"}'
