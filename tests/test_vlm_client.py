"""The VLM client against the real stand-in server on loopback (``agos vlm-standin``), which injects faults."""

from __future__ import annotations

import asyncio
import json
import math
import random
import socket
from collections.abc import Iterator

import cv2
import httpx
import numpy as np
import pytest

from agos.agents.vlm.client import VlmClient, VlmError, image_part
from agos.agents.vlm.standin.server import StandinServer

pytestmark = pytest.mark.loopback  # the stand-in server listens on loopback in this process

MODEL = "stand-in-vl"


def wait(request) -> dict:
    return {"action": "WAIT"}


@pytest.fixture
def standin() -> Iterator:
    """``standin(**kwargs)`` starts a stand-in serving MODEL that is closed after the test."""
    servers: list[StandinServer] = []

    def make(**kwargs) -> StandinServer:
        server = StandinServer(wait, models=(MODEL,), **kwargs).start()
        servers.append(server)
        return server

    yield make
    for server in servers:
        server.close()


def client(server: StandinServer, **kw) -> VlmClient:
    return VlmClient(server.url, MODEL, backoff_base_s=0.01, rng=random.Random(0), **kw)


def run(coro):
    return asyncio.run(coro)


def test_reply_usage_and_request_shape(standin, monkeypatch) -> None:
    monkeypatch.setenv("OPENAI_API_KEY", "sk-secret-value")
    server = standin()
    jpeg = cv2.imencode(".jpg", np.zeros((56, 84, 3), np.uint8))[1].tobytes()

    async def go():
        c = client(server)
        messages = [{"role": "user", "content": [{"type": "text", "text": "hi"}, image_part(jpeg, "jpeg")]}]
        reply = await c.complete(messages, schema={"type": "object"})
        await c.close()
        return reply

    reply = run(go())
    assert json.loads(reply.text) == {"action": "WAIT"} and reply.attempts == 1 and reply.finish_reason == "stop"
    assert reply.prompt_tokens == 1 + 3 * 2  # "hi" is one token; an 84x56 image is 3x2 patches of 28x28
    assert reply.completion_tokens == math.ceil(len(json.dumps({"action": "WAIT"})) / 4)
    (request,) = server.recorded
    assert request.body["model"] == MODEL and request.body["response_format"]["type"] == "json_schema"
    assert request.body["messages"][0]["content"][1]["image_url"]["url"].startswith("data:image/jpeg;base64,")
    assert request.headers["Authorization"] == "Bearer sk-secret-value"
    assert "sk-secret" not in repr(reply)


def test_retries_honour_retry_after_and_count_attempts(standin) -> None:
    server = standin(script=("429", "500", "garbage", "ok"), retry_after_s=0.2)

    async def go():
        c = client(server)
        reply = await c.complete([{"role": "user", "content": "x"}])
        await c.close()
        return reply

    reply = run(go())
    assert reply.attempts == 4 and reply.text is not None
    assert reply.latency_s >= 0.2  # waited at least the Retry-After of the 429
    assert server.stats()["chat_completions"] == 4


def test_timeouts_are_retried_then_reported(standin) -> None:
    server = standin(faults={"timeout": 1.0}, hang_s=0.5)

    async def go():
        c = client(server, timeout_s=0.1, max_retries=2)
        try:
            await c.complete([{"role": "user", "content": "x"}])
        finally:
            await c.close()

    with pytest.raises(VlmError, match="3 attempts"):
        run(go())


def test_preflight_finds_the_model_or_says_what_is_served(standin) -> None:
    server = standin()

    async def go(model: str):
        c = VlmClient(server.url, model)
        try:
            return await c.preflight()
        finally:
            await c.close()

    assert run(go(MODEL)) == [MODEL]
    with pytest.raises(VlmError, match="model 'gpt-99' is not served there; its /models lists: stand-in-vl; pick one") as err:
        run(go("gpt-99"))
    assert err.value.kind == "model"


def test_concurrency_limit(standin) -> None:
    server = standin(latency_ms=200)

    async def go():
        c = client(server, concurrency=2, timeout_s=5)
        started = asyncio.get_running_loop().time()
        await asyncio.gather(*(c.complete([{"role": "user", "content": "x"}]) for _ in range(4)))
        await c.close()
        return asyncio.get_running_loop().time() - started

    assert run(go()) >= 0.4  # four 0.2 s replies, two at a time
    assert server.stats()["max_in_flight"] <= 2


# --- endpoint failures, each in one line (agents/vlm/endpoint.py) --------------------------------------


def preflight_error(url: str, *, model: str = MODEL, timeout_s: float = 5.0, key_env: str = "AGOS_TEST_KEY",
                    transport: httpx.AsyncBaseTransport | None = None) -> VlmError:
    """The VlmError a preflight of ``url`` raises (the test fails when it raises none)."""

    async def go() -> None:
        c = VlmClient(url, model, api_key_env=key_env, timeout_s=timeout_s, transport=transport)
        try:
            await c.preflight()
        finally:
            await c.close()

    with pytest.raises(VlmError) as err:
        run(go())
    assert "\n" not in str(err.value)
    return err.value


def test_preflight_says_connection_refused_naming_host_and_port() -> None:
    with socket.socket() as s:  # a port nothing listens on: bound, never listening
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        err = preflight_error(f"http://127.0.0.1:{port}/v1")
    assert err.kind == "refused"
    assert f"connection refused: nothing listens on 127.0.0.1:{port}; start the model server there" in str(err)


def test_preflight_says_a_host_name_does_not_resolve() -> None:
    err = preflight_error("http://agos-no-such-endpoint.invalid:8000/v1")
    assert err.kind == "unreachable"
    assert "cannot resolve the host name 'agos-no-such-endpoint.invalid'" in str(err) and "--vlm-base-url" in str(err)


def test_preflight_says_a_silent_server_timed_out() -> None:
    with socket.socket() as s:  # accepts connections (the kernel's backlog) and never answers
        s.bind(("127.0.0.1", 0))
        s.listen()
        err = preflight_error(f"http://127.0.0.1:{s.getsockname()[1]}/v1", timeout_s=0.3)
    assert err.kind == "timeout"
    assert "accepted the connection but did not answer /models within 0.3 s" in str(err) and "--vlm-timeout" in str(err)


def test_preflight_names_the_key_variable_and_whether_it_is_set(monkeypatch) -> None:
    server = StandinServer(wait, models=(MODEL,), api_key="right-key").start()
    try:
        monkeypatch.delenv("AGOS_TEST_KEY", raising=False)
        err = preflight_error(server.url)
        assert err.kind == "auth"
        assert "answered 401 Unauthorized" in str(err) and "AGOS_TEST_KEY is not set" in str(err)
        monkeypatch.setenv("AGOS_TEST_KEY", "wrong-key-value")
        err = preflight_error(server.url)
        assert "it refused the API key in AGOS_TEST_KEY (set)" in str(err) and "wrong-key-value" not in str(err)
        monkeypatch.setenv("AGOS_TEST_KEY", "right-key")

        async def go() -> list[str]:
            c = VlmClient(server.url, MODEL, api_key_env="AGOS_TEST_KEY")
            try:
                return await c.preflight()
            finally:
                await c.close()

        assert run(go()) == [MODEL]
    finally:
        server.close()


def test_a_403_to_a_chat_request_names_the_key_variable_without_retrying(monkeypatch) -> None:
    monkeypatch.setenv("AGOS_TEST_KEY", "sk-echoed")
    calls = []

    def forbid(request: httpx.Request) -> httpx.Response:
        calls.append(request)
        return httpx.Response(403, json={"error": {"message": "key sk-echoed has no access to this model",
                                                   "type": "permission_error", "code": None}})

    async def go():
        c = VlmClient("http://vlm.test/v1", MODEL, api_key_env="AGOS_TEST_KEY", transport=httpx.MockTransport(forbid))
        try:
            await c.complete([{"role": "user", "content": "x"}])
        finally:
            await c.close()

    with pytest.raises(VlmError) as err:
        run(go())
    assert len(calls) == 1 and err.value.kind == "auth"
    assert "answered 403 Forbidden (key <redacted> has no access to this model)" in str(err.value)
    assert "AGOS_TEST_KEY (set)" in str(err.value) and "sk-echoed" not in str(err.value)


def test_preflight_of_a_base_url_without_v1_says_so(standin) -> None:
    server = standin()
    err = preflight_error(server.url.removesuffix("/v1"))
    assert err.kind == "http" and "answered 404 Not Found" in str(err) and "usually ends in /v1" in str(err)
    html = httpx.MockTransport(lambda request: httpx.Response(200, text="<html>a proxy's page</html>"))
    err = preflight_error("http://vlm.test/v1", transport=html)
    assert err.kind == "http" and "without a model list (<html>a proxy's page</html>)" in str(err)


def test_litellm_renamed_retry_after_header_is_honoured() -> None:
    c = VlmClient("http://vlm.test/v1", MODEL, rng=random.Random(0), backoff_base_s=5.0)
    renamed = httpx.Response(429, headers={"llm_provider-retry-after": "0.75"})
    assert c._delay(0, renamed) == 0.75
    assert c._delay(0, httpx.Response(429, headers={"retry-after": "1.5"})) == 1.5
    assert c._delay(0, httpx.Response(429, headers={"retry-after-ms": "250", "retry-after": "9"})) == 0.25
    run(c.close())
