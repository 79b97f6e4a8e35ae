"""``agos vlm-standin``'s transport: the real server on loopback, queried with httpx and with the real
VlmClient. Timing assertions are lower bounds only."""

from __future__ import annotations

import asyncio
import json
import math
import os
import random
import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from agos.agents.vlm.client import VlmClient, VlmError, image_part
from agos.agents.vlm.protocol import AERIAL, SIX_VIEWS, SplitRequest, action_schema, image_caption, state_text
from agos.agents.vlm.standin.faults import FAULT_KINDS, FaultSpecError, draw_outcome, fault_sequence, parse_faults
from agos.agents.vlm.standin.requests import image_size, image_tokens
from agos.agents.vlm.standin.schema import check_schema, violation
from agos.agents.vlm.standin.server import StandinServer, default_responder, wait_responder

pytestmark = pytest.mark.loopback  # the server listens on loopback in this process

ROOT = Path(__file__).resolve().parents[1]
MODEL = "agos-standin"
REPLY = {"action": "WAIT", "reason": "nothing visible yet"}


def jpeg(width: int, height: int) -> bytes:
    return cv2.imencode(".jpg", np.full((height, width, 3), 90, np.uint8))[1].tobytes()


def png(width: int, height: int) -> bytes:
    return cv2.imencode(".png", np.zeros((height, width), np.uint8))[1].tobytes()


def agos_messages(views: int = 6, state: dict | None = None) -> list[dict]:
    """A request laid out as agos lays it out: a 512x512 aerial view, ``views`` 256x256 views, STATE."""
    content: list[dict] = [{"type": "text", "text": image_caption(AERIAL, "Your nadir view with the grid.")},
                           image_part(jpeg(512, 512), "jpeg")]
    for label in SIX_VIEWS[:views]:
        content += [{"type": "text", "text": image_caption(label)}, image_part(jpeg(256, 256), "jpeg")]
    content.append({"type": "text", "text": state_text(state or {"step": 3, "legal_actions": ["WAIT"]})})
    return [{"role": "system", "content": "You are the UGV."}, {"role": "user", "content": content}]


def fixed(request: SplitRequest) -> dict:
    return dict(REPLY)


@pytest.fixture
def standin() -> Iterator:
    """A factory: ``standin(**kwargs)`` starts a server that is closed after the test."""
    servers: list[StandinServer] = []

    def make(responder=fixed, **kwargs) -> StandinServer:
        server = StandinServer(responder, **kwargs).start()
        servers.append(server)
        return server

    yield make
    for server in servers:
        server.close()


def chat(server: StandinServer, messages: list[dict] | None = None, *, model: str = MODEL, timeout: float = 10.0,
         headers: dict[str, str] | None = None, **extra) -> httpx.Response:
    body = {"model": model, "messages": messages or agos_messages(views=0), **extra}
    return httpx.post(f"{server.url}/chat/completions", json=body, timeout=timeout, headers=headers)


def content(response: httpx.Response) -> str | None:
    return response.json()["choices"][0]["message"]["content"]


def client(server: StandinServer, **kwargs) -> VlmClient:
    kwargs.setdefault("backoff_base_s", 0.01)
    return VlmClient(server.url, MODEL, rng=random.Random(0), **kwargs)


async def complete(c: VlmClient, messages: list[dict] | None = None, **kwargs):
    try:
        return await c.complete(messages or agos_messages(views=0), **kwargs)
    finally:
        await c.close()


# --- endpoints and request handling -------------------------------------------------------------------


def test_models_list_and_client_preflight(standin) -> None:
    server = standin(models=("qwen-vl", MODEL))
    listing = httpx.get(f"{server.url}/models").json()
    assert listing["object"] == "list"
    assert [(m["id"], m["object"]) for m in listing["data"]] == [("qwen-vl", "model"), (MODEL, "model")]

    async def preflight(model: str) -> list[str]:
        c = VlmClient(server.url, model)
        try:
            return await c.preflight()
        finally:
            await c.close()

    assert asyncio.run(preflight(MODEL)) == ["qwen-vl", MODEL]
    with pytest.raises(VlmError, match="its /models lists: qwen-vl, agos-standin"):
        asyncio.run(preflight("gpt-99"))


def test_reply_is_openai_shaped_with_usage(standin) -> None:
    server = standin()
    fmt = {"type": "json_schema", "json_schema": {"name": "a", "schema": {}}}
    response = chat(server, agos_messages(views=6), response_format=fmt)
    assert response.status_code == 200
    body = response.json()
    assert body["object"] == "chat.completion" and body["model"] == MODEL and body["id"] and body["created"] > 0
    choice = body["choices"][0]
    assert choice["finish_reason"] == "stop" and choice["message"]["role"] == "assistant"
    assert json.loads(choice["message"]["content"]) == REPLY
    usage = body["usage"]
    # 512x512 -> 18x18 = 324 tokens, six 256x256 -> 9x9 = 81 each; text adds chars/4
    assert usage["prompt_tokens"] > 324 + 6 * 81
    assert usage["completion_tokens"] >= len(json.dumps(REPLY)) // 4
    assert usage["total_tokens"] == usage["prompt_tokens"] + usage["completion_tokens"]


def test_responder_gets_the_split_request(standin) -> None:
    seen: list[SplitRequest] = []

    def record(request: SplitRequest) -> dict:
        seen.append(request)
        return {"action": "WAIT", "reason": f"{len(request.images)} images"}

    server = standin(record)
    state = {"step": 7, "legal_actions": ["WAIT", "CONFIRM"]}
    reply = asyncio.run(complete(client(server), agos_messages(views=6, state=state), schema={"type": "object"}))
    assert json.loads(reply.text) == {"action": "WAIT", "reason": "7 images"}
    (request,) = seen
    assert set(request.images) == {AERIAL, *SIX_VIEWS} and request.state == state
    assert request.system == "You are the UGV." and image_size(request.images[AERIAL]) == (512, 512)
    assert reply.prompt_tokens is not None and reply.prompt_tokens >= 324 + 6 * 81 and reply.completion_tokens


def test_unknown_model_is_a_404_naming_it(standin) -> None:
    server = standin()
    response = chat(server, model="gpt-99")
    assert response.status_code == 404
    error = response.json()["error"]
    assert "gpt-99" in error["message"] and MODEL in error["message"] and error["param"] == "model"
    with pytest.raises(VlmError, match=r"HTTP 404.*gpt-99"):
        asyncio.run(complete(VlmClient(server.url, "gpt-99")))
    assert server.stats()["errors"] == {"404": 2} and server.sequence() == []  # refused requests draw nothing


def _body(content=None, **fields) -> bytes:
    """A request body with one user message holding ``content`` (a string or a list of parts)."""
    return json.dumps({"model": MODEL, "messages": [{"role": "user", "content": content or "x"}], **fields}).encode()


def _image(url: str) -> list[dict]:
    return [{"type": "image_url", "image_url": {"url": url}}]


@pytest.mark.parametrize(("body", "expected"), [
    (b"{not json", "not valid JSON"),
    (b"[1, 2]", "must be a JSON object"),
    (json.dumps({"model": MODEL}).encode(), "'messages' must be a non-empty list"),
    (json.dumps({"messages": [{"role": "user", "content": "x"}]}).encode(), "'model' is required"),
    (_body(_image("https://example.com/a.jpg")), "only base64 data URLs"),
    (_body(_image("data:image/jpeg;base64,/9hqcGVn")), "not a JPEG or PNG"),
    (_body([{"type": "audio"}]), "unsupported content part"),
    (_body("STATE (JSON):\n{oops"), "request layout"),
    (_body(max_tokens=0), "'max_tokens'"),
    (_body(stream=True), "streaming"),
])
def test_malformed_requests_get_a_clear_400(standin, body: bytes, expected: str) -> None:
    server = standin()
    response = httpx.post(f"{server.url}/chat/completions", content=body, headers={"Content-Type": "application/json"})
    assert response.status_code == 400, response.text
    assert expected in response.json()["error"]["message"]
    assert httpx.get(f"{server.url}/models").status_code == 200  # the server keeps serving


def test_too_many_images_is_a_400_naming_the_limit(standin) -> None:
    server = standin(max_images=4)
    assert chat(server, agos_messages(views=3)).status_code == 200
    response = chat(server, agos_messages(views=6))
    assert response.status_code == 400
    limit = re.search(r"At most (\d+) image\(s\) may be provided in one prompt", response.json()["error"]["message"])
    assert limit is not None and limit.group(1) == "4"
    with pytest.raises(VlmError, match=r"HTTP 400.*At most 4 image\(s\)"):
        asyncio.run(complete(client(server), agos_messages(views=6)))


def test_unknown_paths_and_stats_endpoint(standin) -> None:
    server = standin()
    assert httpx.get(f"{server.url}/embeddings").status_code == 404
    assert httpx.post(f"{server.url}/completions", json={}).status_code == 404
    chat(server)
    stats = httpx.get(f"http://127.0.0.1:{server.port}/stats").json()
    assert stats["chat_completions"] == 1 and stats["outcomes"]["ok"] == 1 and stats["faults"] == 0
    assert stats["errors"] == {"404": 2} and stats["requests"] == 4


def test_structured_replies_are_plain_json_else_sometimes_wrapped(standin) -> None:
    fmt = {"type": "json_schema", "json_schema": {"name": "action", "schema": {"type": "object"}}}
    always = standin(wrap_p=1.0, seed=1)
    for _ in range(4):
        assert json.loads(content(chat(always, response_format=fmt))) == REPLY
    wrapped = [content(chat(always)) for _ in range(6)]
    for text in wrapped:
        with pytest.raises(json.JSONDecodeError):
            json.loads(text)
        assert json.dumps(REPLY) in text
    assert any(t.startswith("```json") for t in wrapped) and any(not t.startswith("```") for t in wrapped)
    never = standin(wrap_p=0.0)
    assert all(json.loads(content(chat(never))) == REPLY for _ in range(3))


def test_max_tokens_cuts_the_reply_with_finish_reason_length(standin) -> None:
    server = standin(lambda request: {"action": "WAIT", "reason": "a long explanation " * 20})
    body = chat(server, max_tokens=8).json()
    assert body["choices"][0]["finish_reason"] == "length" and len(content_of(body)) == 32
    assert chat(server, max_tokens=500).json()["choices"][0]["finish_reason"] == "stop"


def content_of(body: dict) -> str:
    return body["choices"][0]["message"]["content"]


# --- injected faults ---------------------------------------------------------------------------------------


def test_fault_429_has_retry_after_headers(standin) -> None:
    server = standin(faults={"429": 1.0}, retry_after_s=0.25)
    response = chat(server)
    error = response.json()["error"]
    assert response.status_code == 429 and (error["type"], error["code"]) == ("rate_limit_error", "rate_limit_exceeded")
    assert response.headers["Retry-After"] == "0.25" and response.headers["retry-after-ms"] == "250"


def test_fault_500(standin) -> None:
    response = chat(standin(faults={"500": 1.0}))
    assert response.status_code == 500 and "injected" in response.json()["error"]["message"]


def test_fault_timeout_hangs_past_the_client_timeout(standin) -> None:
    server = standin(faults={"timeout": 1.0}, hang_s=1.0)
    started = time.monotonic()
    with pytest.raises(httpx.ReadTimeout):
        chat(server, timeout=0.2)
    assert time.monotonic() - started >= 0.2
    late = chat(server, timeout=10.0)  # a patient client gets the late answer
    assert late.status_code == 200 and json.loads(content(late)) == REPLY


def test_fault_malformed_is_not_json(standin) -> None:
    server = standin(faults={"malformed": 1.0})
    for _ in range(6):
        response = chat(server)
        assert response.status_code == 200 and response.json()["choices"][0]["finish_reason"] == "stop"
        with pytest.raises(json.JSONDecodeError):
            json.loads(content(response))


def test_fault_fenced_wraps_json_in_fences_and_trailing_text(standin) -> None:
    text = content(chat(standin(faults={"fenced": 1.0}), response_format={"type": "json_object"}))
    match = re.fullmatch(r"```json\n(.*)\n```\n(.+)", text, re.DOTALL)
    assert match is not None and json.loads(match.group(1)) == REPLY and match.group(2).strip()


def test_fault_empty_content(standin) -> None:
    server = standin(faults={"empty": 1.0})
    contents = [content(chat(server)) for _ in range(8)]
    assert set(contents) <= {"", None}


def test_fault_length_truncates_json(standin) -> None:
    server = standin(faults={"length": 1.0})
    for _ in range(4):
        body = chat(server).json()
        text = content_of(body)
        assert body["choices"][0]["finish_reason"] == "length"
        assert json.dumps(REPLY).startswith(text) and len(text) < len(json.dumps(REPLY))


def test_fault_garbage_is_a_non_json_body(standin) -> None:
    response = chat(standin(faults={"garbage": 1.0}))
    assert response.status_code == 200 and response.headers["Content-Type"] == "text/html"
    with pytest.raises(json.JSONDecodeError):
        response.json()


def test_client_retries_every_transport_fault_and_succeeds(standin) -> None:
    server = standin(script=("429", "500", "timeout", "garbage", "ok"), retry_after_s=0.3, hang_s=2.0)
    reply = asyncio.run(complete(client(server, timeout_s=0.4, max_retries=5)))
    assert reply.attempts == 5 and json.loads(reply.text) == REPLY
    assert reply.latency_s >= 0.3 + 0.4  # the Retry-After of the 429, then the client timeout
    assert server.sequence() == ["429", "500", "timeout", "garbage", "ok"]


def test_retry_after_is_honoured(standin) -> None:
    server = standin(script=("429", "429"), retry_after_s=0.25)
    started = time.monotonic()
    reply = asyncio.run(complete(client(server, backoff_base_s=0.0)))
    assert reply.attempts == 3 and time.monotonic() - started >= 0.5


def test_client_gives_up_after_repeated_timeouts(standin) -> None:
    server = standin(faults={"timeout": 1.0}, hang_s=1.0)
    with pytest.raises(VlmError, match=r"3 attempts.*Timeout"):
        asyncio.run(complete(client(server, timeout_s=0.1, max_retries=2)))
    assert server.stats()["outcomes"]["timeout"] == 3


def test_seeded_mix_is_retried_until_every_decision_succeeds(standin) -> None:
    faults = {"429": 0.25, "500": 0.2, "timeout": 0.05}
    server = standin(faults=faults, seed=11, retry_after_s=0.01, hang_s=2.0)

    async def decisions() -> list:
        c = client(server, timeout_s=0.5, max_retries=12)
        try:
            return [await c.complete(agos_messages(views=1)) for _ in range(12)]
        finally:
            await c.close()

    replies = asyncio.run(decisions())
    stats = server.stats()
    assert all(r.text is not None for r in replies)
    assert sum(r.attempts for r in replies) == stats["chat_completions"] == 12 + stats["faults"]
    assert stats["faults"] > 0 and stats["outcomes"]["ok"] == 12
    assert server.sequence() == fault_sequence(faults, 11, stats["chat_completions"])


def test_seeded_fault_sequence_is_reproducible(standin) -> None:
    faults = {"429": 0.1, "500": 0.1, "malformed": 0.1, "fenced": 0.2, "empty": 0.1, "length": 0.1}

    def serve(seed: int) -> tuple[list[str], list]:
        server = standin(faults=faults, seed=seed, wrap_p=0.5)
        replies = [chat(server) for _ in range(30)]
        return server.sequence(), [(r.status_code, content(r) if r.status_code == 200 else None) for r in replies]

    first, again, other = serve(5), serve(5), serve(6)
    assert first == again
    assert first[0] == fault_sequence(faults, 5, 30) and first[0] != other[0]
    assert {"ok", "fenced"} <= set(first[0])


def test_latency_sleeps_without_blocking_other_requests(standin) -> None:
    server = standin(latency_ms=300, jitter_ms=50)

    async def four() -> float:
        c = client(server, concurrency=4)
        started = time.monotonic()
        try:
            await asyncio.gather(*(c.complete(agos_messages(views=0)) for _ in range(4)))
        finally:
            await c.close()
        return time.monotonic() - started

    assert asyncio.run(four()) >= 0.3
    assert server.stats()["max_in_flight"] >= 2


def test_close_releases_a_hung_request(standin) -> None:
    server = standin(faults={"timeout": 1.0}, hang_s=30.0)
    errors: list[BaseException] = []

    def call() -> None:
        try:
            chat(server, timeout=60.0)
        except httpx.HTTPError as exc:
            errors.append(exc)

    caller = threading.Thread(target=call)
    caller.start()
    while server.stats()["in_flight"] == 0:
        time.sleep(0.01)
    server.close()
    caller.join()
    assert len(errors) == 1 and isinstance(errors[0], httpx.TransportError)


# --- pure parts ---------------------------------------------------------------------------------------------


def test_parse_faults_and_errors_name_the_bad_entry() -> None:
    assert parse_faults("429=0.1, 500=0.05,timeout=0.02,malformed=0.05,fenced=0.2,empty=0.05") == {
        "429": 0.1, "500": 0.05, "timeout": 0.02, "malformed": 0.05, "fenced": 0.2, "empty": 0.05}
    assert parse_faults("") == {}
    for spec, expected in [("429=0.1,oops=0.2", "'oops=0.2'.*unknown fault 'oops'"), ("500", "'500'.*KIND=PROBABILITY"),
                           ("500=lots", "'500=lots'"), ("500=1.5", "'500=1.5'.*\\[0, 1\\]"), ("429=0.1,429=0.2", "given twice"),
                           ("429=0.6,500=0.6", "sum to 1.2")]:
        with pytest.raises(FaultSpecError, match=expected):
            parse_faults(spec)


def test_draw_outcome_stacks_probabilities_in_kind_order() -> None:
    faults = {"500": 0.2, "429": 0.1}
    assert [draw_outcome(u, faults) for u in (0.0, 0.099, 0.1, 0.29, 0.31, 0.99)] == ["429", "429", "500", "500", "ok", "ok"]
    assert all(draw_outcome(random.random(), {kind: 1.0}) == kind for kind in FAULT_KINDS)
    assert fault_sequence(faults, 3, 50) == fault_sequence(faults, 3, 50) != fault_sequence(faults, 4, 50)


def test_image_sizes_and_tokens() -> None:
    assert image_size(jpeg(512, 384)) == (512, 384) and image_size(png(256, 100)) == (256, 100)
    assert image_size(b"\xff\xd8not a jpeg") is None and image_size(b"") is None
    assert image_tokens(512, 512) + 6 * image_tokens(256, 256) == 810  # Qwen2.5-VL's count, VLM_NOTES.md
    assert image_tokens(10, 10) == 1


def test_default_responder_is_the_brain_or_a_wait_fallback() -> None:
    responder = default_responder()
    assert responder is wait_responder or (responder.__module__, responder.__name__) == ("agos.agents.vlm.standin.brain", "respond")
    assert wait_responder(SplitRequest(system="", text="", state=None, images={}))["action"] == "WAIT"


# --- the command line ------------------------------------------------------------------------------------


def _listening_url(proc: subprocess.Popen, lines: list[str]) -> str | None:
    assert proc.stdout is not None
    for line in proc.stdout:
        lines.append(line)
        match = re.search(r"listening on (http://\S+/v1)", line)
        if match:
            return match.group(1)
    return None


@pytest.mark.e2e
def test_cli_serves_on_a_free_port_and_stops_cleanly() -> None:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "AGOS_STANDIN_TEST_KEY": "cli-key"}
    proc = subprocess.Popen([sys.executable, "-m", "agos.deploy.cli", "vlm-standin", "--port", "0", "--model", "cli-vl",
                             "--faults", "fenced=0.5", "--seed", "2", "--api-key-env", "AGOS_STANDIN_TEST_KEY"],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    try:
        url = _listening_url(proc, lines)
        assert url is not None, "".join(lines)
        assert url.startswith("http://127.0.0.1:") and not url.startswith("http://127.0.0.1:0/")
        assert httpx.get(f"{url}/models", timeout=10).status_code == 401  # --api-key-env: no key, no answer
        listing = httpx.get(f"{url}/models", timeout=10, headers={"Authorization": "Bearer cli-key"})
        assert [m["id"] for m in listing.json()["data"]] == ["cli-vl"]
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    assert proc.stdout is not None
    text = "".join(lines) + proc.stdout.read()  # the rest, including what the line iterator had buffered
    assert proc.returncode == 0, text
    assert f"--vlm-base-url {url} --model cli-vl --vlm-api-key-env AGOS_STANDIN_TEST_KEY" in text and "stopped after" in text
    assert "cli-key" not in text


def test_cli_rejects_a_bad_fault_spec_naming_the_entry(agos) -> None:
    result = agos("vlm-standin", "--faults", "429=0.1,flaky=0.2")
    assert result.returncode == 2 and "'flaky=0.2'" in result.stderr and "unknown fault 'flaky'" in result.stderr


def test_cli_refuses_an_unset_api_key_variable(agos, monkeypatch) -> None:
    monkeypatch.delenv("AGOS_STANDIN_UNSET_KEY", raising=False)
    result = agos("vlm-standin", "--port", "0", "--api-key-env", "AGOS_STANDIN_UNSET_KEY")
    assert result.returncode == 2 and result.stderr.count("\n") == 1
    assert "--api-key-env AGOS_STANDIN_UNSET_KEY: AGOS_STANDIN_UNSET_KEY is not set" in result.stderr


# --- behaving like a real endpoint (issue 31, item 7) ----------------------------------------------------


def test_n_returns_n_choices_and_a_bad_n_is_a_400(standin) -> None:
    server = standin(wrap_p=0.5, seed=3)
    body = chat(server, n=4).json()
    assert [c["index"] for c in body["choices"]] == [0, 1, 2, 3]
    texts = [c["message"]["content"] for c in body["choices"]]
    assert all(json.dumps(REPLY) in t for t in texts)  # the same answer, each choice wrapped by its own draw
    assert body["usage"]["completion_tokens"] == sum(math.ceil(len(t) / 4) for t in texts)
    assert len(chat(server, n=None).json()["choices"]) == 1  # null is the default, one choice
    for bad in (0, 129, "2", 1.5, True):
        response = chat(server, n=bad)
        error = response.json()["error"]
        assert response.status_code == 400 and error["param"] == "n" and error["type"] == "invalid_request_error", bad
    assert server.stats()["chat_completions"] == 7 and server.stats()["outcomes"]["ok"] == 2  # refusals draw nothing


def _strict(schema: object, name: str = "answer") -> dict:
    return {"type": "json_schema", "json_schema": {"name": name, "strict": True, "schema": schema}}


def test_a_strict_schema_is_honoured_or_the_request_refused(standin) -> None:
    server = standin()
    own = chat(server, response_format=_strict(action_schema(["WAIT", "MOVE_TO"]), "action"))
    assert own.status_code == 200 and json.loads(content(own)) == REPLY  # agos's action schema: the answer conforms
    foreign = {"type": "object", "properties": {"answer": {"type": "string"}}, "required": ["answer"],
               "additionalProperties": False}
    refused = chat(server, response_format=_strict(foreign))
    error = refused.json()["error"]
    assert refused.status_code == 400 and (error["type"], error["param"]) == ("invalid_request_error", "response_format")
    assert "cannot answer the strict json_schema" in error["message"] and "required 'answer' missing" in error["message"]
    loose = chat(server, response_format={"type": "json_schema", "json_schema": {"name": "answer", "schema": foreign}})
    assert loose.status_code == 200  # not strict: a schema is a hint, as OpenAI's non-strict mode
    unsupported = chat(server, response_format=_strict({"type": "object", "patternProperties": {"^a": {}}}))
    assert unsupported.status_code == 400 and "'patternProperties' is not supported" in unsupported.json()["error"]["message"]


@pytest.mark.parametrize(("value", "schema", "problem"), [
    ({"action": "WAIT"}, {"type": "object", "properties": {"action": {"enum": ["GO"]}}}, "$.action: 'WAIT' is not one of"),
    ({"a": 1}, {"type": "object", "additionalProperties": False}, "property 'a' is not allowed"),
    ({"a": [1, "x"]}, {"properties": {"a": {"type": "array", "items": {"type": "integer"}}}}, "$.a[1]: 'x' is not of type integer"),
    ({"c": "Z9"}, {"properties": {"c": {"type": "string", "pattern": "^[A-E][1-5]$"}}}, "does not match"),
    ({"r": "x" * 5}, {"properties": {"r": {"type": "string", "maxLength": 4}}}, "outside its length bounds"),
    ({"v": None}, {"properties": {"v": {"anyOf": [{"type": "string"}, {"type": "integer"}]}}}, "matches none of anyOf"),
    ({"v": 1}, {"$defs": {"s": {"type": "string"}}, "properties": {"v": {"$ref": "#/$defs/s"}}}, "is not of type string"),
    (True, {"type": "integer"}, "is not of type integer"),
    ({"v": 3}, {"properties": {"v": {"type": ["integer", "null"], "maximum": 2}}}, "outside its bounds"),
])
def test_schema_violations_name_the_place(value, schema, problem: str) -> None:
    check_schema(schema)
    found = violation(value, schema)
    assert found is not None and problem in found
    assert violation(value, {"type": ["object", "boolean"]}) is None


def test_error_bodies_use_openai_types_and_string_or_null_codes(standin) -> None:
    server = standin(models=(MODEL,), script=("500",))
    cases = [
        (chat(server), 500, "server_error", None),
        (chat(server, model="gpt-99"), 404, "invalid_request_error", "model_not_found"),
        (chat(server, max_tokens=0), 400, "invalid_request_error", None),
        (httpx.get(f"{server.url}/embeddings"), 404, "invalid_request_error", None),
        (httpx.request("DELETE", f"{server.url}/models"), 501, "invalid_request_error", None),
    ]
    for response, status, kind, code in cases:
        error = response.json()["error"]
        assert (response.status_code, error["type"], error["code"]) == (status, kind, code), response.text
        assert set(error) == {"message", "type", "param", "code"}


def test_api_key_is_checked_when_configured_and_never_echoed(standin) -> None:
    server = standin(api_key="sk-standin-secret")
    missing = httpx.get(f"{server.url}/models")
    wrong = chat(server, headers={"Authorization": "Bearer sk-guess"})
    for response, code in ((missing, "missing_api_key"), (wrong, "invalid_api_key")):
        error = response.json()["error"]
        assert (response.status_code, error["type"], error["code"]) == (401, "authentication_error", code)
        assert "sk-guess" not in response.text and "sk-standin-secret" not in response.text
    good = {"Authorization": "Bearer sk-standin-secret"}
    assert httpx.get(f"{server.url}/models", headers=good).status_code == 200
    assert chat(server, headers=good).status_code == 200
    assert httpx.get(f"http://127.0.0.1:{server.port}/stats").status_code == 200  # not part of the API: open
    stats = server.stats()
    assert stats["chat_completions"] == 1 and stats["errors"] == {"401": 2}  # a refused request draws no outcome


def test_an_answer_is_one_write_so_keep_alive_requests_do_not_wait_for_an_ack(standin) -> None:
    """Headers and body written separately reach a keep-alive client as two segments, the second held
    back by Nagle's algorithm until the client's delayed ACK (~40 ms a request). One write: one read
    gets the whole answer."""
    server = standin()
    with socket.create_connection((server.host, server.port), timeout=10) as conn:
        for _ in range(3):  # the same connection, kept alive
            conn.sendall(f"GET /v1/models HTTP/1.1\r\nHost: {server.host}\r\n\r\n".encode())
            data = conn.recv(65536)
            head, _, body = data.partition(b"\r\n\r\n")
            length = int(re.search(rb"Content-Length: (\d+)", head).group(1))
            assert head.startswith(b"HTTP/1.1 200") and len(body) == length, data
            assert json.loads(body)["object"] == "list"
