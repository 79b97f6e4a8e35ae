"""The VLM client against a real HTTP server on loopback that injects faults."""

from __future__ import annotations

import asyncio
import json
import random
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from agos.agents.vlm.client import VlmClient, VlmError, image_part


class FaultServer:
    """Answers chat completions; ``script`` lists what the next requests get:
    ("ok"), ("429", retry-after seconds), ("500"), ("slow", seconds), ("garbage")."""

    def __init__(self) -> None:
        self.script: list[tuple] = []
        self.requests: list[dict] = []
        self.headers: list[dict] = []
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args) -> None:
                pass

            def _send(self, status: int, body: bytes, headers: dict | None = None) -> None:
                self.send_response(status)
                for k, v in (headers or {}).items():
                    self.send_header(k, v)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def do_GET(self) -> None:
                self._send(200, json.dumps({"data": [{"id": "stand-in-vl"}]}).encode())

            def do_POST(self) -> None:
                length = int(self.headers["Content-Length"])
                outer.requests.append(json.loads(self.rfile.read(length)))
                outer.headers.append(dict(self.headers))
                step = outer.script.pop(0) if outer.script else ("ok",)
                if step[0] == "429":
                    self._send(429, b"{}", {"Retry-After": str(step[1])})
                elif step[0] == "500":
                    self._send(500, b"oops")
                elif step[0] == "slow":
                    import time

                    time.sleep(step[1])
                    self._send(200, b"{}")
                elif step[0] == "garbage":
                    self._send(200, b"<html>not json</html>")
                else:
                    reply = {"choices": [{"message": {"content": '{"action": "WAIT"}'}, "finish_reason": "stop"}],
                             "usage": {"prompt_tokens": 812, "completion_tokens": 9}}
                    self._send(200, json.dumps(reply).encode())

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_port}/v1"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def server():
    s = FaultServer()
    yield s
    s.close()


def client(server: FaultServer, **kw) -> VlmClient:
    return VlmClient(server.url, "stand-in-vl", backoff_base_s=0.01, rng=random.Random(0), **kw)


def run(coro):
    return asyncio.run(coro)


def test_reply_usage_and_request_shape(server, monkeypatch) -> None:
    monkeypatch.setenv("OPENAI_API_KEY", "sk-secret-value")

    async def go():
        c = client(server)
        messages = [{"role": "user", "content": [{"type": "text", "text": "hi"}, image_part(b"\xff\xd8jpeg", "jpeg")]}]
        reply = await c.complete(messages, schema={"type": "object"})
        await c.close()
        return reply

    reply = run(go())
    assert reply.text == '{"action": "WAIT"}' and reply.attempts == 1
    assert (reply.prompt_tokens, reply.completion_tokens) == (812, 9)
    body = server.requests[0]
    assert body["model"] == "stand-in-vl" and body["response_format"]["type"] == "json_schema"
    assert body["messages"][0]["content"][1]["image_url"]["url"].startswith("data:image/jpeg;base64,")
    assert server.headers[0]["Authorization"] == "Bearer sk-secret-value"
    assert "sk-secret" not in repr(reply)


def test_retries_honour_retry_after_and_count_attempts(server) -> None:
    server.script = [("429", 0.2), ("500",), ("garbage",), ("ok",)]

    async def go():
        c = client(server)
        reply = await c.complete([{"role": "user", "content": "x"}])
        await c.close()
        return reply

    reply = run(go())
    assert reply.attempts == 4 and reply.text is not None
    assert reply.latency_s >= 0.2  # waited at least the Retry-After of the 429


def test_timeouts_are_retried_then_reported(server) -> None:
    server.script = [("slow", 0.5), ("slow", 0.5), ("slow", 0.5)]

    async def go():
        c = client(server, timeout_s=0.1, max_retries=2)
        try:
            await c.complete([{"role": "user", "content": "x"}])
        finally:
            await c.close()

    with pytest.raises(VlmError, match="3 attempts"):
        run(go())


def test_preflight_finds_the_model_or_says_what_is_served(server) -> None:
    async def go(model: str):
        c = VlmClient(server.url, model)
        try:
            return await c.preflight()
        finally:
            await c.close()

    assert run(go("stand-in-vl")) == ["stand-in-vl"]
    with pytest.raises(VlmError, match="available: stand-in-vl"):
        run(go("gpt-99"))


def test_concurrency_limit(server) -> None:
    server.script = [("slow", 0.2)] * 4 + [("ok",)] * 4

    async def go():
        c = client(server, concurrency=2, timeout_s=5)
        started = asyncio.get_running_loop().time()
        await asyncio.gather(*(c.complete([{"role": "user", "content": "x"}]) for _ in range(4)))
        await c.close()
        return asyncio.get_running_loop().time() - started

    assert run(go()) >= 0.4  # four 0.2 s replies, two at a time
