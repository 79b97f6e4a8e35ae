"""The reply parser-validator: well-formed and repairable replies become the intended action;
anything else (fuzzed: more than 1,000 malformed replies) becomes a legal, logged fallback."""

from __future__ import annotations

import json
import random

import pytest

from agos.agents.vlm.parse import extract_json, to_action
from agos.runtime.schemas import Candidate, CoordinationState, Observation, Pose, Waypoint


def observation(role: str = "ugv") -> Observation:
    cand = Candidate(candidate_id="C001", cell="B2", polygon_world_m=[(0, 0), (1, 0), (1, 1)], center_world_m=(0.5, 0.5),
                     status="pending", created_sim_time_s=0.0)
    legal = (["MOVE_TO_ROAD_WAYPOINT", "GO_TO_CANDIDATE", "STOP_OBSERVE", "CONFIRM", "REJECT", "WAIT"] if role == "ugv"
             else ["MOVE_TO_UAV_WAYPOINT", "ANNOTATE_CANDIDATE", "NO_RELIABLE_CANDIDATE", "WAIT"])
    options = [Waypoint(waypoint_id=w, position_world_m=(0, 0, 0), kind="cruise") for w in
               (["R10", "R22"] if role == "ugv" else ["U1_2", "U2_2"])]
    return Observation(
        run_id="r", episode_id="e", role=role, decision_index=3, sim_time_s=1.0,
        pose=Pose(position_world_m=(0, 0, 0), yaw_rad=0.0), mode="driving" if role == "ugv" else "aerial", images=[],
        references=[], legal_actions=legal, waypoint_options=options, region_world_m=(0, 0, 1, 1),
        coordination=CoordinationState(run_id="r", episode_id="e", sim_time_s=1.0, candidates=[cand]))


@pytest.mark.parametrize(("reply", "expected"), [
    ('{"action": "GO_TO_CANDIDATE", "candidate_id": "C001"}', ("GO_TO_CANDIDATE", "C001")),
    ('```json\n{"action": "MOVE_TO_ROAD_WAYPOINT", "waypoint_id": "R22"}\n```', ("MOVE_TO_ROAD_WAYPOINT", "R22")),
    ("<think>the car is red</think>Sure! {'action': 'STOP_OBSERVE', 'reason': 'close',} thanks", ("STOP_OBSERVE", None)),
    ('I choose {"action": "reject"} because no match.', ("REJECT", "C001")),
])
def test_wellformed_and_repairable_replies(reply: str, expected: tuple[str, str | None]) -> None:
    parsed = to_action(reply, observation())
    assert not parsed.fallback, parsed.reason
    assert parsed.action.action == expected[0]
    assert expected[1] in (parsed.action.waypoint_id, parsed.action.candidate_id)


def test_uav_annotation_cell_is_checked() -> None:
    obs = observation("uav")
    assert to_action('{"action": "ANNOTATE_CANDIDATE", "cell": "c4"}', obs).action.cell == "C4"
    assert to_action('{"action": "ANNOTATE_CANDIDATE", "cell": "F9"}', obs).fallback


@pytest.mark.parametrize("reply", [None, "", "no json here", '{"action": "FLY_AWAY"}', '{"action": "CONFIRM"',
                                   '{"action": "MOVE_TO_ROAD_WAYPOINT", "waypoint_id": "R999"}',
                                   '{"action": "GO_TO_CANDIDATE", "candidate_id": "C777"}', "[1, 2, 3]"])
def test_unusable_replies_fall_back_to_wait_with_a_reason(reply) -> None:
    parsed = to_action(reply, observation())
    assert parsed.fallback and parsed.action.action == "WAIT" and parsed.reason


def test_truncated_reply_is_never_repaired() -> None:
    parsed = to_action('{"action": "CONFIRM"}', observation(), truncated=True)
    assert parsed.fallback and "truncated" in parsed.reason


def _mutations(rng: random.Random, base: str) -> str:
    ops = [
        lambda s: s[: rng.randrange(len(s) + 1)],
        lambda s: s.replace('"', "'"),
        lambda s: s.replace("}", ",}"),
        lambda s: "```json\n" + s + "\n```" + rng.choice(["", " done", "\n```"]),
        lambda s: "<think>" + "x" * rng.randrange(50) + "</think>" + s,
        lambda s: s.replace("action", rng.choice(["act", "Action", "", "action"])),
        lambda s: s[::-1],
        lambda s: "".join(ch for ch in s if rng.random() > 0.05),
        lambda s: s + rng.choice(["{", "}", "]", "\\", "\u0000", "null"]),
        lambda s: "{" * rng.randrange(1, 50) + s,
        lambda s: s.replace("R22", rng.choice(["R22", "R10", "r22", "", "22", "R-1"])),
        lambda s: json.dumps({"action": rng.choice(["WAIT", "CONFIRM", 3, None, [], "MOVE_TO_ROAD_WAYPOINT"]),
                              "waypoint_id": rng.choice([None, 5, "R10", {"a": 1}])}),
    ]
    for _ in range(rng.randrange(1, 4)):
        base = rng.choice(ops)(base)
    return base


def test_fuzz_malformed_replies_never_crash_and_always_yield_a_legal_action() -> None:
    rng = random.Random(1234)
    bases = ['{"action": "MOVE_TO_ROAD_WAYPOINT", "waypoint_id": "R22", "message": "on my way"}',
             '{"action": "GO_TO_CANDIDATE", "candidate_id": "C001"}', '{"action": "CONFIRM", "reason": "red sedan"}']
    obs = observation()
    fallbacks = 0
    for _ in range(1500):
        parsed = to_action(_mutations(rng, rng.choice(bases)), obs)
        assert parsed.action.action in obs.legal_actions
        if parsed.action.waypoint_id is not None:
            assert parsed.action.waypoint_id in {"R10", "R22"}
        if parsed.fallback:
            fallbacks += 1
            assert parsed.reason and parsed.action.action == "WAIT" and parsed.action.rationale.startswith("fallback")
    assert 0 < fallbacks < 1500


def test_extract_json_reports_repairs() -> None:
    assert extract_json('{"a": 1}') == ({"a": 1}, False)
    assert extract_json("{'a': 1,}") == ({"a": 1}, True)
