"""The VLM call cache (agents/vlm/cache.py): its keys, its file format, record and replay through
the client's hook, the replay index per stream, and ``agos vlm-cache stats``. No sockets: the
client's endpoint is an httpx mock transport that counts what reaches it."""

from __future__ import annotations

import asyncio
import hashlib
import json
import sqlite3
import threading

import httpx
import pytest

from agos.agents.agent_service import serve_async
from agos.agents.contract import FatalPolicyError
from agos.agents.vlm.cache import (
    CACHE_FILE,
    CacheError,
    CacheMiss,
    CacheStats,
    CallTag,
    ModelStats,
    ReplyCache,
    cache_stats,
    canonical_request,
    size_line,
    stats_table,
)
from agos.agents.vlm.client import Reply, VlmClient, VlmError, image_part
from agos.deploy.run.evaluate import exited_children
from agos.runtime import keys
from agos.runtime.bus import Inbox, MemoryBus
from agos.runtime.codec import encode
from agos.runtime.process import StopFlag
from agos.runtime.schemas import CoordinationState, Observation, Pose
from agos.runtime.settings import load_config

from support.waiting import wait_until

PNG_A = b"\x89PNG\r\n\x1a\n" + b"a" * 64
PNG_B = b"\x89PNG\r\n\x1a\n" + b"b" * 64


def body(image: bytes = PNG_A, *, model: str = "m", temperature: float = 0.0, max_tokens: int = 512,
         schema: dict | None = None, text: str = "where is the car?") -> dict:
    out = {"model": model, "max_tokens": max_tokens, "temperature": temperature,
           "messages": [{"role": "system", "content": "You search."},
                        {"role": "user", "content": [{"type": "text", "text": text}, image_part(image, "png")]}]}
    if schema is not None:
        out["response_format"] = {"type": "json_schema", "json_schema": {"name": "action", "schema": schema}}
    return out


class Endpoint:
    """A chat-completions endpoint as an httpx mock transport: reply k is ``{"action": "WAIT", "k": k}``
    (a model sampling at temperature > 0 answers an identical request differently), or HTTP
    ``status``; counts every request that reaches it."""

    def __init__(self, status: int = 200) -> None:
        self.requests = 0
        self.status = status

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.requests += 1
        if self.status != 200:
            return httpx.Response(self.status, json={"error": {"message": "down"}})
        text = json.dumps({"action": "WAIT", "k": self.requests})
        return httpx.Response(200, json={"choices": [{"message": {"content": text}, "finish_reason": "stop"}],
                                         "usage": {"prompt_tokens": 100, "completion_tokens": 7}})


def client(endpoint: Endpoint, cache: ReplyCache | None) -> VlmClient:
    return VlmClient("http://model.invalid/v1", "m", transport=httpx.MockTransport(endpoint), cache=cache,
                     max_retries=1, backoff_base_s=0.0)


def ask(c: VlmClient, call: CallTag | None, *, image: bytes = PNG_A) -> Reply:
    messages = body(image)["messages"]

    async def go() -> Reply:
        return await c.complete(messages, schema={"type": "object"}, call=call)

    return asyncio.run(go())


UAV0 = CallTag("ep-1", "uav", 0)


# ----- keys -----------------------------------------------------------------------------------------
def test_the_key_is_the_sha256_of_the_stored_body_with_images_replaced_by_their_hash() -> None:
    request = canonical_request(body(schema={"type": "object"}))
    assert request.key == hashlib.sha256(request.body_json.encode()).hexdigest()
    digest = hashlib.sha256(PNG_A).hexdigest()
    assert request.images == ((digest, "image/png", PNG_A),)
    stored = json.loads(request.body_json)
    assert stored["messages"][1]["content"][1]["image_url"]["url"] == f"sha256:{digest}"
    assert "base64" not in request.body_json
    assert request.model == "m"
    assert canonical_request(body(schema={"type": "object"})).key == request.key  # deterministic
    # Key order of the body does not matter: the canonical JSON sorts keys.
    reordered = dict(reversed(list(body(schema={"type": "object"}).items())))
    assert canonical_request(reordered).key == request.key


@pytest.mark.parametrize("change", [
    {"image": PNG_B}, {"model": "other"}, {"temperature": 0.7}, {"max_tokens": 64},
    {"schema": {"type": "object", "required": ["action"]}}, {"text": "where is the truck?"},
])
def test_every_part_that_decides_the_answer_changes_the_key(change: dict) -> None:
    base = {"schema": {"type": "object"}}
    assert canonical_request(body(**(base | change))).key != canonical_request(body(**base)).key


def test_an_image_that_is_not_base64_is_refused() -> None:
    bad = body()
    bad["messages"][1]["content"][1]["image_url"]["url"] = "data:image/png;base64,@@not base64@@"
    with pytest.raises(CacheError, match="not valid base64"):
        canonical_request(bad)


# ----- record and replay through the client ------------------------------------------------------------
def test_record_then_replay_gives_the_kth_reply_to_the_kth_identical_request_of_a_stream(tmp_path) -> None:
    endpoint = Endpoint()
    recorder = client(endpoint, ReplyCache(tmp_path, "record"))
    recorded = [ask(recorder, UAV0).text for _ in range(3)]
    other_stream = ask(recorder, CallTag("ep-2", "uav", 0)).text
    assert endpoint.requests == 4 and len(set(recorded + [other_stream])) == 4

    replay_endpoint = Endpoint()
    cache = ReplyCache(tmp_path, "replay")
    replayer = client(replay_endpoint, cache)
    assert ask(replayer, CallTag("ep-2", "uav", 0)).text == other_stream  # streams do not share indices
    replayed = [ask(replayer, UAV0) for _ in range(3)]
    assert [r.text for r in replayed] == recorded
    assert replay_endpoint.requests == 0
    first = replayed[0]
    assert (first.finish_reason, first.prompt_tokens, first.completion_tokens, first.attempts) == ("stop", 100, 7, 1)
    assert cache.hits == 4 and cache.misses == 0


def test_a_new_attempt_of_the_episode_replays_its_stream_from_the_start(tmp_path) -> None:
    endpoint = Endpoint()
    cache = ReplyCache(tmp_path, "record")
    c = client(endpoint, cache)
    first = [ask(c, UAV0).text for _ in range(2)]
    cache.forget("ep-1", "uav")  # re-leased: the policy forgets the episode
    again = [ask(c, UAV0).text for _ in range(2)]
    assert again == first and endpoint.requests == 2  # record serves what it holds
    assert ask(c, UAV0).text not in first and endpoint.requests == 3  # a third ask is new
    assert (cache.hits, cache.misses) == (2, 3)


def test_a_replay_miss_names_the_request_in_one_line_and_is_fatal(tmp_path) -> None:
    ask(client(Endpoint(), ReplyCache(tmp_path, "record")), UAV0)
    replayer = client(Endpoint(), ReplyCache(tmp_path, "replay"))
    ask(replayer, UAV0)
    with pytest.raises(CacheMiss) as miss:
        ask(replayer, CallTag("ep-1", "uav", 5))  # the same request asked a second time
    message = str(miss.value)
    key = canonical_request(body(schema={"type": "object"})).key
    assert isinstance(miss.value, FatalPolicyError) and "\n" not in message
    for part in ("model m", "role uav", "decision ep-1 #5", key[:16], "recorded 1 time(s)", str(tmp_path)):
        assert part in message, (part, message)
    with pytest.raises(CacheMiss, match="never recorded"):
        ask(replayer, UAV0, image=PNG_B)


def test_an_unanswered_request_replays_as_the_same_error_and_record_asks_it_again(tmp_path) -> None:
    down = Endpoint(status=503)
    with pytest.raises(VlmError) as recorded:
        ask(client(down, ReplyCache(tmp_path, "record")), UAV0)
    with pytest.raises(VlmError) as replayed:
        ask(client(Endpoint(), ReplyCache(tmp_path, "replay")), UAV0)
    assert str(replayed.value) == str(recorded.value) and replayed.value.attempts == recorded.value.attempts == 2
    assert replayed.value.kind == recorded.value.kind
    up = Endpoint()
    reply = ask(client(up, ReplyCache(tmp_path, "record")), UAV0)
    assert up.requests == 1 and reply.text is not None
    assert ask(client(Endpoint(), ReplyCache(tmp_path, "replay")), UAV0).text == reply.text


# ----- the file ----------------------------------------------------------------------------------------
def test_the_file_is_one_sqlite_database_in_wal_mode_with_images_stored_once(tmp_path) -> None:
    c = client(Endpoint(), ReplyCache(tmp_path, "record"))
    for k in range(3):
        ask(c, CallTag("ep-1", "ugv", k))
    ask(c, UAV0, image=PNG_B)
    db = sqlite3.connect(tmp_path / CACHE_FILE)
    assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert dict(db.execute("SELECT name, value FROM meta")) == {"format": "agos-vlm-cache", "version": "1"}
    assert db.execute("SELECT COUNT(*) FROM images").fetchone()[0] == 2
    assert db.execute("SELECT COUNT(*) FROM requests").fetchone()[0] == 2
    rows = db.execute("SELECT stream, occurrence FROM replies ORDER BY stream, occurrence").fetchall()
    assert rows == [("ep-1/uav", 0), ("ep-1/ugv", 0), ("ep-1/ugv", 1), ("ep-1/ugv", 2)]  # one request asked 3 times
    for key, stored in db.execute("SELECT key, body FROM requests"):  # a reader outside agos can check each key
        assert hashlib.sha256(stored.encode()).hexdigest() == key
    for digest, data in db.execute("SELECT sha256, data FROM images"):
        assert hashlib.sha256(data).hexdigest() == digest


def test_handles_on_one_file_write_at_once(tmp_path) -> None:
    """Two writers (as two agent processes are: one connection each) recording at the same time."""
    errors: list[BaseException] = []

    def record(role: str) -> None:
        try:
            c = client(Endpoint(), ReplyCache(tmp_path, "record"))
            for k in range(25):
                ask(c, CallTag(f"ep-{k}", role, 0), image=bytes([k]) * 200)
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=record, args=(role,)) for role in ("uav", "ugv")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    stats = cache_stats(tmp_path)
    assert [(m.model, m.requests, m.replies, m.misses) for m in stats.models] == [("m", 25, 50, 50)]
    assert stats.images == 25


def test_a_replay_of_a_missing_cache_or_another_format_is_one_line(tmp_path) -> None:
    with pytest.raises(CacheError, match="record one first"):
        ReplyCache(tmp_path / "none", "replay")
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / CACHE_FILE).write_bytes(b"not a database at all" * 100)
    with pytest.raises(CacheError, match="not a readable SQLite file"):
        ReplyCache(tmp_path / "junk", "record")
    ReplyCache(tmp_path / "v2", "record").close()
    with sqlite3.connect(tmp_path / "v2" / CACHE_FILE) as db:
        db.execute("UPDATE meta SET value = '2' WHERE name = 'version'")
    with pytest.raises(CacheError, match="version '2'; this agos reads 'agos-vlm-cache' version 1"):
        ReplyCache(tmp_path / "v2", "replay")


# ----- settings and the stats command ------------------------------------------------------------------
def test_the_flags_reach_the_vlm_settings(tmp_path) -> None:
    from agos.deploy.cli import build_parser
    from agos.deploy.cli.common import settings_of

    args = build_parser().parse_args(["eval", "--policy", "agos-agent", "--model", "m", "--vlm-cache", str(tmp_path),
                                      "--vlm-cache-mode", "replay"])
    vlm = settings_of(args).vlm
    assert (vlm.cache_dir, vlm.cache_mode, vlm.replaying) == (tmp_path, "replay", True)
    default = load_config(overrides={"vlm": {"cache_dir": tmp_path}}).vlm
    assert (default.cache_mode, default.replaying) == ("record", False)


def test_stats_prints_hits_misses_tokens_and_size(tmp_path, agos) -> None:
    c = client(Endpoint(), ReplyCache(tmp_path, "record"))
    ask(c, UAV0)
    ask(c, CallTag("ep-1", "uav", 1), image=PNG_B)
    ask(client(Endpoint(), ReplyCache(tmp_path, "replay")), UAV0)
    result = agos("vlm-cache", "stats", tmp_path)
    assert result.returncode == 0, result.stderr
    [row] = [line for line in result.stdout.splitlines() if line.strip("│ ").startswith("m ")]
    assert [cell.strip() for cell in row.strip("│").split("│")] == ["m", "2", "2", "0", "1", "2", "200", "14"]
    assert "size:" in result.stdout and "2 images" in result.stdout
    missing = agos("vlm-cache", "stats", tmp_path / "nothing")
    assert missing.returncode == 2 and "no vlm-cache.sqlite" in missing.stderr and "\n" not in missing.stderr.strip()


# ----- a miss stops the agent service, and agos eval says why in one line --------------------------------
class Replaying:
    """A policy whose every decision is a replay miss."""

    role, name, inline = "uav", "replaying", False

    async def act_async(self, obs):
        raise CacheMiss(f"VLM cache miss in replay: model m, role uav, decision {obs.episode_id} #{obs.decision_index}, "
                        "request 0123456789abcdef (never recorded in stream 'e1/uav')")

    def act(self, obs):
        raise AssertionError("the service awaits act_async")

    def end_episode(self, episode_id: str) -> None:
        pass

    async def preflight(self) -> None:
        pass


def test_a_miss_stops_the_agent_service_with_exit_4_and_answers_nothing(caplog) -> None:
    bus, stop, codes = MemoryBus(), StopFlag(), []
    actions = Inbox()
    bus.subscribe(keys.act("r", "*", "uav"), actions)
    thread = threading.Thread(target=lambda: codes.append(asyncio.run(serve_async(bus, Replaying(), "r", stop,
                                                                                  concurrency=2))), daemon=True)
    thread.start()
    try:
        bus.declare_token(keys.slot_live("r", "w1"))
        assert wait_until(lambda: bus.wait_for_subscriber(keys.obs("r", "w1", "uav"), 0))
        obs = Observation(run_id="r", episode_id="e1", role="uav", decision_index=3, sim_time_s=0.0,
                          pose=Pose(position_world_m=(0.0, 0.0, 80.0), yaw_rad=0.0), mode="aerial", images=[],
                          references=[], legal_actions=["WAIT"], waypoint_options=[],
                          region_world_m=(0.0, 0.0, 10.0, 10.0),
                          coordination=CoordinationState(run_id="r", episode_id="e1", sim_time_s=0.0))
        bus.publish(keys.obs("r", "w1", "uav"), encode(obs))
        thread.join(10)
    finally:
        stop.set()
    assert not thread.is_alive() and codes == [4] and stop.is_set()
    assert actions.get(0) is None  # no WAIT in the model's name
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert errors == ["VLM cache miss in replay: model m, role uav, decision e1 #3, request 0123456789abcdef "
                      "(never recorded in stream 'e1/uav')"]


def test_agos_eval_names_an_agent_that_stopped_on_a_miss_in_one_line(tmp_path) -> None:
    miss = "VLM cache miss in replay: model m, role ugv, decision ep-1 #7, request 0123456789abcdef ([never] recorded)"
    (tmp_path / "agent-ugv.log").write_text(
        "===== agos agent started 2026-01-01 10:00:00 =====\n"
        "2026-01-01 10:00:01,000 agent-ugv[9] ERROR agos.agent: an error of an earlier start\n"
        "===== agos agent started 2026-01-01 11:00:00 =====\n"
        "2026-01-01 11:00:01,000 agent-ugv[10] INFO agos.agent: ugv agent serving run r\n"
        f"2026-01-01 11:00:05,000 agent-ugv[10] ERROR agos.agent: {miss}\n")

    class Exited:
        def __init__(self) -> None:
            self.children = {"agent-ugv": None, "world-0": None}

        def dead(self) -> dict[str, int]:
            return {"agent-ugv": 4}

    halt = exited_children(Exited(), tmp_path)  # type: ignore[arg-type]
    assert halt is not None and halt.code != 0 and "\n" not in halt.line
    assert "agent-ugv (exit 4)" in halt.line and miss.replace("[", "\\[") in halt.line  # rich markup escaped


def test_a_cache_that_breaks_mid_run_stops_the_run_rather_than_score_a_wait(tmp_path) -> None:
    cache = ReplyCache(tmp_path, "record")
    c = client(Endpoint(), cache)
    ask(c, UAV0)
    with sqlite3.connect(tmp_path / CACHE_FILE) as db:
        db.execute("DROP TABLE replies")  # another hand replaced the file's contents
    with pytest.raises(FatalPolicyError, match=r"VLM cache .*vlm-cache.sqlite: OperationalError: no such table: replies"):
        ask(c, UAV0)


@pytest.mark.parametrize(("flags", "said"), [
    (["--vlm-cache-mode", "replay"], "--vlm-cache-mode replay replays a cache: give its directory with --vlm-cache DIR"),
    (["--vlm-cache", "{tmp}/none", "--vlm-cache-mode", "replay"], "no vlm-cache.sqlite there to replay"),
    (["--vlm-cache", "{tmp}/recorded", "--vlm-cache-mode", "replay"], "holds no call of model 'other' to replay "
                                                                       "(it holds: m); give --model as recorded"),
])
def test_agos_eval_refuses_a_cache_it_cannot_replay_before_anything_starts(flags, said, tmp_path, agos) -> None:
    ask(client(Endpoint(), ReplyCache(tmp_path / "recorded", "record")), UAV0)
    args = [f.format(tmp=tmp_path) for f in flags]
    result = agos("eval", "--split", tmp_path / "split.jsonl", "--policy", "agos-agent", "--model", "other", *args,
                  cwd=tmp_path)
    assert result.returncode == 2, result.stdout + result.stderr
    assert said in result.stderr and len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert not (tmp_path / "runs").exists()  # nothing made


def test_the_stats_table_has_a_row_per_model_with_separated_counts() -> None:
    from rich.console import Console

    stats = CacheStats([ModelStats("a-long-model-name", 1200, 1300, 2, 1_234_567, 89_000, 40, 1300),
                        ModelStats("m", 0, 0, 0, 0, 0, 3, 0)], images=1500, image_bytes=2_500_000, file_bytes=12_340_000)
    table = stats_table(stats, title="VLM cache d")
    assert table.title == "VLM cache d" and [c.header for c in table.columns] == [
        "model", "requests", "replies", "errors", "hits", "misses", "tokens in", "tokens out"]
    console = Console(width=200, record=True)
    console.print(table)
    rows = [[cell.strip() for cell in line.strip("│").split("│")] for line in console.export_text().splitlines()
            if line.startswith("│")]
    assert rows == [["a-long-model-name", "1,200", "1,300", "2", "40", "1,300", "1,234,567", "89,000"],
                        ["m", "0", "0", "0", "3", "0", "0", "0"]]
    assert size_line(stats) == ("size: 12.3 MB (1,500 images, 2.5 MB); hits and misses count every lookup of every run, "
                                "replies errors included")
