"""The VLM client against the real stand-in server on loopback (``agos vlm-standin``), which injects faults."""

from __future__ import annotations

import asyncio
import json
import math
import random
from collections.abc import Iterator

import cv2
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
    with pytest.raises(VlmError, match="available: stand-in-vl"):
        run(go("gpt-99"))


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
