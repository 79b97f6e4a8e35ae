"""VLM policies against the real stand-in HTTP server on loopback: prompt layout and stages,
re-asks, logged fallbacks, traces, and the API key kept out of everything recorded."""

from __future__ import annotations

import asyncio
import copy
import json
import logging
import time

import msgspec
import pytest

from agos.agents.registry import make_policy
from agos.agents.vlm import protocol
from agos.agents.vlm.agos_prompts import ugv_prompt, ugv_stage
from agos.agents.vlm.baseline_prompts import anchor_from_messages
from agos.agents.vlm.request import Memory
from agos.agents.vlm.standin.server import StandinServer
from agos.runtime.codec import to_json
from agos.runtime.schemas import MessageRecord
from agos.runtime.settings import VlmOptions

pytestmark = pytest.mark.loopback  # the stand-in server listens on loopback in this process


def _agent(url: str, role: str = "uav", name: str = "agos-agent", **kw):
    return make_policy(name, role, vlm=VlmOptions(base_url=url, model="agos-standin", **kw))


def test_prompts_label_every_image_and_carry_the_state(observations) -> None:
    from agos.agents.vlm.agos_prompts import uav_prompt

    uav = next(o for o in observations if o.role == "uav")
    prompt = uav_prompt(uav, Memory())
    req = protocol.split_request(prompt.messages())
    assert req.unlabelled == 0
    assert {"aerial_grid", "topdown_map", "target_ref_top", "target_ref_side"} <= set(req.images)
    assert req.state["legal_actions"] == uav.legal_actions and req.state["stage"] == "search"
    assert req.state["camera"]["world_from_camera"] and req.state["unvisited_waypoints"]
    assert prompt.image_bytes["aerial_grid"] == len(req.images["aerial_grid"])
    six = next(o for o in observations if o.role == "ugv" and o.mode == "stop_6view")
    prompt = ugv_prompt(six, Memory())
    req = protocol.split_request(prompt.messages())
    assert prompt.stage == "six_view" and set(protocol.SIX_VIEWS) <= set(req.images)
    assert set(req.state["panel_cameras"]) == set(protocol.SIX_VIEWS)
    assert "CONFIRM" in req.state["legal_actions"]


def test_ugv_stages() -> None:
    cand = {"id": "C001", "status": "pending", "distance_m": 40.0}

    class Obs:
        mode = "driving"

    assert ugv_stage(Obs, None, [], rgpp=True) == "free_exploration"
    assert ugv_stage(Obs, None, [[1.0, 2.0]], rgpp=True) == "post_rejection"
    assert ugv_stage(Obs, cand, [], rgpp=True) == "candidate_reminder"
    assert ugv_stage(Obs, {**cand, "status": "arrived"}, [], rgpp=True) == "arrival"
    assert ugv_stage(Obs, {**cand, "distance_m": 8.0}, [], rgpp=False) == "arrival"  # no_rgpp: arrival by distance
    Obs.mode = "stop_6view"
    assert ugv_stage(Obs, cand, [], rgpp=True) == "six_view"


def test_baseline_anchor_is_the_latest_uninspected_uav_coordinate(observations) -> None:
    obs = copy.deepcopy(next(o for o in observations if o.role == "ugv"))
    obs.coordination.messages = [
        MessageRecord(sender="uav", receiver="ugv", text="CLEAR_MATCH: search around (126, -116).", sent_sim_time_s=1,
                      delivered_sim_time_s=1),
        MessageRecord(sender="uav", receiver="ugv", text="thanks", sent_sim_time_s=2, delivered_sim_time_s=2)]
    memory = Memory()
    assert anchor_from_messages(obs, memory) == (126.0, -116.0)
    memory.inspected_anchors.append((120.0, -110.0))
    assert anchor_from_messages(obs, memory) is None


def test_a_malformed_reply_is_re_asked_and_counted_apart_from_the_decision(observations) -> None:
    uav = next(o for o in observations if o.role == "uav")
    with StandinServer(script=("malformed", "ok")) as server:
        action = _agent(server.url).act(uav)
    assert action.trace.reasks == 1 and action.trace.http_attempts == 2 and not action.trace.fallback
    assert action.action in uav.legal_actions and action.trace.parsed_action == action.action
    assert action.trace.stage == "search" and action.trace.prompt_tokens


def test_unusable_replies_become_a_logged_legal_fallback(observations, caplog) -> None:
    uav = next(o for o in observations if o.role == "uav")
    with StandinServer(script=("empty", "length", "malformed")) as server, caplog.at_level(logging.WARNING):
        action = _agent(server.url, reasks=2, max_retries=0).act(uav)
    assert action.action == "WAIT" and "WAIT" in uav.legal_actions
    assert action.trace.fallback and action.trace.fallback_reason and action.trace.reasks == 2
    assert any("fallback WAIT" in r.getMessage() for r in caplog.records)


def test_an_unreachable_endpoint_is_an_outage_not_a_decision(observations) -> None:
    """No answer after the retries is no decision of the model: EndpointOutage, which the agent service
    turns into Action.outage (the world pauses the episode), never a fallback WAIT."""
    from agos.agents.contract import EndpointOutage

    ugv = next(o for o in observations if o.role == "ugv")
    agent = _agent("http://127.0.0.1:9/v1", "ugv", max_retries=1, timeout_s=2)
    with pytest.raises(EndpointOutage, match=r"127\.0\.0\.1:9/v1: no answer after 2 attempts \(ConnectError\)"):
        agent.act(ugv)
    with StandinServer(faults={"500": 1.0}) as server:  # a 5xx past the retry budget, likewise
        with pytest.raises(EndpointOutage, match=r"no answer after 2 attempts \(HTTP 500\)"):
            _agent(server.url, "ugv", max_retries=1).act(ugv)
        assert server.stats()["chat_completions"] == 2
    hung = msgspec.structs.replace(ugv, decision_timeout_s=2.0)  # the world waits 2 s for this decision
    hang_bound_s = 30.0  # a hang, not a speed: the decision's 2 s (less a margin) apply, not the client's 60 s
    with StandinServer(faults={"timeout": 1.0}, hang_s=90) as server:  # accepts, never answers (until closed)
        started = time.monotonic()
        with pytest.raises(EndpointOutage, match=r"no answer after 1 attempt within the decision's time \(ReadTimeout\)"):
            _agent(server.url, "ugv", timeout_s=60).act(hung)  # at the world's deadline, not after 60 s
        assert time.monotonic() - started < hang_bound_s


def test_the_api_key_never_reaches_traces_or_logs(observations, caplog, monkeypatch, tmp_path) -> None:
    secret = "sk-test-0123456789abcdef"
    monkeypatch.setenv("AGOS_TEST_KEY", secret)
    uav = next(o for o in observations if o.role == "uav")
    trace_file = tmp_path / "traces.jsonl"
    with StandinServer(script=("429", "malformed", "ok")) as server, caplog.at_level(logging.DEBUG):
        action = _agent(server.url, api_key_env="AGOS_TEST_KEY", trace_file=trace_file).act(uav)
        sent = [dict(r.headers) for r in server.recorded]
    assert any(h.get("authorization") == f"Bearer {secret}" or h.get("Authorization") == f"Bearer {secret}" for h in sent)
    assert secret not in to_json(action).decode()
    assert secret not in trace_file.read_text() and json.loads(trace_file.read_text())["decision_index"] == 1
    assert secret not in caplog.text


def test_the_async_path_shares_one_client_across_concurrent_decisions(observations) -> None:
    uavs = [o for o in observations if o.role == "uav"][:6]
    with StandinServer(latency_ms=100) as server:
        agent = _agent(server.url)

        async def all_at_once():
            try:
                return await asyncio.gather(*(agent.act_async(o) for o in uavs))
            finally:
                await agent.aclose()

        actions = asyncio.run(all_at_once())
        assert server.stats()["max_in_flight"] > 1  # overlapped, not serialised
    assert [a.decision_index for a in actions] == [o.decision_index for o in uavs]


def test_a_re_sent_observation_is_answered_once(observations) -> None:
    """The world re-sends an unanswered observation every 5 s; a slow model must not be asked twice."""
    uav = next(o for o in observations if o.role == "uav")
    with StandinServer(latency_ms=300) as server:
        agent = _agent(server.url)

        async def twice():
            try:
                first, second = await asyncio.gather(agent.act_async(uav), agent.act_async(uav))
                third = await agent.act_async(uav)  # after the answer: the same answer again
                return first, second, third
            finally:
                await agent.aclose()

        first, second, third = asyncio.run(twice())
        assert server.stats()["chat_completions"] == 1
    assert first.action == second.action == third.action
    assert list(agent._memory[uav.episode_id].recent) == [f"step 1: {first.action} {first.waypoint_id or ''}".rstrip()]


@pytest.mark.parametrize(("body", "outage"), [
    ([1, 2], True),  # not a chat completion, after the retries: the endpoint gave no answer
    ({"choices": [None]}, True),
    ({"choices": []}, True),
    ({"choices": [{"message": {"content": 7}}], "usage": {"prompt_tokens": "many"}}, False),  # an unusable answer
])
def test_odd_reply_shapes_become_outages_or_traced_fallbacks(observations, body, outage) -> None:
    import httpx

    from agos.agents.contract import EndpointOutage
    from agos.agents.vlm.client import VlmClient

    uav = next(o for o in observations if o.role == "uav")
    agent = _agent("http://stand.in/v1", reasks=0)
    agent._client = VlmClient("http://stand.in/v1", "agos-standin", max_retries=1, backoff_base_s=0.0,
                              transport=httpx.MockTransport(lambda request: httpx.Response(200, json=body)))
    if outage:
        with pytest.raises(EndpointOutage, match="invalid reply body"):
            asyncio.run(agent.act_async(uav))
        return
    action = asyncio.run(agent.act_async(uav))
    assert action.action == "WAIT" and action.trace.fallback and action.trace.fallback_reason


def test_content_parts_and_string_counts_are_read(observations) -> None:
    import httpx

    from agos.agents.vlm.client import VlmClient

    uav = next(o for o in observations if o.role == "uav")
    body = {"choices": [{"message": {"content": [{"type": "text", "text": '{"action": "WAIT"}'}]},
                         "finish_reason": "stop"}], "usage": {"prompt_tokens": "812", "completion_tokens": 9}}
    agent = _agent("http://stand.in/v1")
    agent._client = VlmClient("http://stand.in/v1", "agos-standin",
                              transport=httpx.MockTransport(lambda request: httpx.Response(200, json=body)))
    action = asyncio.run(agent.act_async(uav))
    assert action.action == "WAIT" and not action.trace.fallback and action.trace.prompt_tokens == 812


def test_an_echoed_key_is_redacted_from_errors(observations, monkeypatch) -> None:
    import httpx

    from agos.agents.vlm.client import VlmClient

    secret = "sk-echo-987654321"
    monkeypatch.setenv("AGOS_TEST_KEY", secret)
    uav = next(o for o in observations if o.role == "uav")
    echo = httpx.MockTransport(lambda request: httpx.Response(401, text=f"bad key {request.headers['authorization']}"))
    agent = _agent("http://stand.in/v1", api_key_env="AGOS_TEST_KEY")
    agent._client = VlmClient("http://stand.in/v1", "agos-standin", api_key_env="AGOS_TEST_KEY", transport=echo)
    from agos.agents.contract import EndpointOutage

    with pytest.raises(EndpointOutage) as refused:  # a refused key is no decision of the model either
        asyncio.run(agent.act_async(uav))
    assert "401" in str(refused.value) and "AGOS_TEST_KEY" in str(refused.value) and secret not in str(refused.value)

