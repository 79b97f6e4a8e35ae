"""Record and replay of model calls: ``--vlm-cache DIR`` with ``--vlm-cache-mode record|replay|off``.

The cache is one SQLite file, ``DIR/vlm-cache.sqlite``, in WAL mode, so any number of agent
processes (both roles, sweep workers) read and write it at once; docs/AGENTS.md ("Record and replay
of model calls") documents the format for readers outside agos.

* **The key** of a request is the sha256 of its canonical form: the request body exactly as the
  client posts it (model, messages, ``response_format`` schema, ``temperature``, ``max_tokens`` and
  whatever else the client sends) with every ``data:`` image URL replaced by ``sha256:<hex>`` of the
  image's bytes, as compact JSON with sorted keys. The endpoint's address is not part of it.
  Images are stored once each, content-addressed by that hash.
* **The replay index.** Identical requests (at temperature > 0 a model may answer them differently)
  are told apart by their *stream*, ``<episode>/<role>``, and their *occurrence*, how many times the
  same key was asked before in that stream during the episode's current attempt. A re-leased
  attempt starts again at occurrence 0 (the policy forgets the episode), so the order in which
  worker processes play episodes, or how often an episode is re-leased, never changes which reply a
  request gets.
* **Modes.** ``record``: a reply stored for (key, stream, occurrence) is served from the cache (a
  hit); otherwise the endpoint is asked and the reply stored (a miss). ``replay``: no network; a
  miss is a :class:`CacheMiss`, which stops the agent (exit 4) with one line naming the request.
  A request the endpoint never answered (after its retries) is stored as an error and replayed as
  that error, so a replayed run reproduces the recorded one; ``record`` asks such a request again.
* A served reply carries the recorded latency and HTTP attempts (what the model call cost when it
  was made), so a replayed run's records equal the recorded run's. The reply body is stored as the
  endpoint sent it, so its size (``reply_bytes``, what ``--model-link`` carries down) is the same
  when served.
"""

from __future__ import annotations

import base64
import binascii
import fcntl
import hashlib
import json
import sqlite3
import threading
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from agos.agents.contract import FatalPolicyError
from agos.agents.vlm.client import CallTag, Reply, VlmError

if TYPE_CHECKING:
    from rich.table import Table

CACHE_FILE = "vlm-cache.sqlite"
FORMAT_NAME = "agos-vlm-cache"
FORMAT_VERSION = 1
BUSY_TIMEOUT_MS = 30_000
"""How long a writer waits for another process's write to finish."""
CacheMode = Literal["record", "replay", "off"]
Send = Callable[[dict[str, Any]], Awaitable[Reply]]

SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (name TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS images (sha256 TEXT PRIMARY KEY, mime TEXT NOT NULL, data BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS requests (key TEXT PRIMARY KEY, model TEXT NOT NULL, body TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS replies (
    key TEXT NOT NULL, stream TEXT NOT NULL, occurrence INTEGER NOT NULL,
    body TEXT, text TEXT, finish_reason TEXT, prompt_tokens INTEGER, completion_tokens INTEGER,
    latency_s REAL NOT NULL, attempts INTEGER NOT NULL, error TEXT, error_kind TEXT, recorded_utc TEXT NOT NULL,
    PRIMARY KEY (key, stream, occurrence));
CREATE TABLE IF NOT EXISTS lookups (model TEXT PRIMARY KEY, hits INTEGER NOT NULL, misses INTEGER NOT NULL);
"""


class CacheError(ValueError):
    """A cache directory that cannot be used; the message names it and what to do."""


class CacheMiss(FatalPolicyError):
    """Replay found no recorded reply for a request: the run cannot go on without the endpoint."""


class CacheBroken(FatalPolicyError):
    """The cache file could not be read or written mid-run (a disk full, a file replaced): the
    decision's reply cannot be trusted, so the run stops rather than score a WAIT."""


@dataclass(frozen=True)
class CanonicalRequest:
    """A request body in the cache's form: ``key`` = sha256 of ``body_json``; ``images``: (sha256,
    mime, bytes) of every inline image it refers to."""

    key: str
    model: str
    body_json: str
    images: tuple[tuple[str, str, bytes], ...]


def canonical_request(body: dict[str, Any]) -> CanonicalRequest:
    """The cache's form of a chat-completion request body (see the module docstring). Raises
    CacheError for a ``data:`` URL that is not base64."""
    images: dict[str, tuple[str, str, bytes]] = {}
    messages = [_canonical_message(m, images) for m in body.get("messages", [])]
    doc = {**body, "messages": messages}
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    return CanonicalRequest(hashlib.sha256(text.encode()).hexdigest(), str(body.get("model")), text,
                            tuple(images.values()))


def _canonical_message(message: Any, images: dict[str, tuple[str, str, bytes]]) -> Any:
    content = message.get("content") if isinstance(message, dict) else None
    if not isinstance(content, list):
        return message
    parts = []
    for part in content:
        image = part.get("image_url") if isinstance(part, dict) and part.get("type") == "image_url" else None
        url = image.get("url") if isinstance(image, dict) else None
        if isinstance(image, dict) and isinstance(url, str) and url.startswith("data:") and ";base64," in url[:80]:
            header, _, data = url.partition(",")
            try:
                raw = base64.b64decode(data, validate=True)
            except binascii.Error:
                raise CacheError(f"an image of the request is not valid base64 ({header})") from None
            digest = hashlib.sha256(raw).hexdigest()
            images[digest] = (digest, header[len("data:"):header.index(";")], raw)
            part = {**part, "image_url": {**image, "url": f"sha256:{digest}"}}
        parts.append(part)
    return {**message, "content": parts}


def cache_file(directory: Path) -> Path:
    return Path(directory) / CACHE_FILE


class ReplyCache:
    """One process's handle on a cache directory (thread-safe; one per policy). ``mode`` ``record``
    creates the directory and file when missing; ``replay`` needs them (CacheError otherwise)."""

    def __init__(self, directory: Path, mode: Literal["record", "replay"]) -> None:
        self.directory, self.mode = Path(directory), mode
        self.path = cache_file(self.directory)
        if mode == "replay" and not self.path.is_file():
            raise CacheError(f"--vlm-cache {self.directory}: no {CACHE_FILE} there to replay; record one first "
                             "(--vlm-cache-mode record, the default)")
        if mode == "record":
            try:
                self.directory.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise CacheError(f"--vlm-cache {self.directory}: cannot create it ({exc.strerror})") from None
        self._db = _connect(self.path)
        self._lock = threading.Lock()
        self._asked: dict[str, dict[str, int]] = {}
        """Per stream: how many times each key was asked in the stream's current attempt."""
        self._known_images: set[str] = set()
        self.hits = self.misses = 0
        """This handle's lookups (all processes' totals are in the file: :func:`cache_stats`)."""

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def forget(self, episode_id: str, role: str) -> None:
        """The episode's attempt is over (finished or re-leased): its stream starts at occurrence 0 again."""
        with self._lock:
            self._asked.pop(CallTag(episode_id, role, 0).stream, None)

    def models(self) -> list[str]:
        """The models the cache holds requests for."""
        with self._lock:
            return [m for (m,) in self._db.execute("SELECT DISTINCT model FROM requests ORDER BY model")]

    async def complete(self, body: dict[str, Any], call: CallTag | None, send: Send) -> Reply:
        """The reply to ``body``: from the cache, or (``record``) from ``send`` and then stored.
        Raises CacheMiss in ``replay`` when nothing was recorded for it, and VlmError when the
        endpoint (now, or when it was recorded) gave no answer."""
        request = canonical_request(body)
        stream = call.stream if call is not None else ""
        try:
            return await self._complete(request, body, call, stream, send)
        except sqlite3.Error as exc:
            raise CacheBroken(f"VLM cache {self.path}: {type(exc).__name__}: {exc} (model {request.model}, "
                              f"request {request.key[:16]})") from None

    async def _complete(self, request: CanonicalRequest, body: dict[str, Any], call: CallTag | None, stream: str,
                        send: Send) -> Reply:
        with self._lock:
            asked = self._asked.setdefault(stream, {})
            occurrence = asked.get(request.key, 0)
            asked[request.key] = occurrence + 1
            row = self._db.execute(
                "SELECT body, text, finish_reason, prompt_tokens, completion_tokens, latency_s, attempts, error, "
                "error_kind FROM replies WHERE key = ? AND stream = ? AND occurrence = ?",
                (request.key, stream, occurrence)).fetchone()
            if row is not None and (row[7] is None or self.mode == "replay"):
                self._count(request.model, hit=True)
                return _served(row)
            self._count(request.model, hit=False)
            if self.mode == "replay":
                recorded = self._db.execute("SELECT COUNT(*) FROM replies WHERE key = ? AND stream = ?",
                                            (request.key, stream)).fetchone()[0]
                raise CacheMiss(_miss_line(self.directory, request, call, stream, occurrence, recorded))
        started = time.monotonic()
        try:
            reply = await send(body)
        except VlmError as exc:
            self._store(request, stream, occurrence, None, round(time.monotonic() - started, 4), exc.attempts, exc)
            raise
        self._store(request, stream, occurrence, reply, reply.latency_s, reply.attempts, None)
        return reply

    def _count(self, model: str, *, hit: bool) -> None:
        if hit:
            self.hits += 1
        else:
            self.misses += 1
        self._db.execute("INSERT INTO lookups (model, hits, misses) VALUES (?, ?, ?) ON CONFLICT (model) DO UPDATE "
                         "SET hits = hits + excluded.hits, misses = misses + excluded.misses",
                         (model, int(hit), int(not hit)))

    def _store(self, request: CanonicalRequest, stream: str, occurrence: int, reply: Reply | None, latency_s: float,
               attempts: int, error: VlmError | None) -> None:
        fields = (None, None, None, None, None) if reply is None else (
            reply.body_text if reply.body_text is not None else json.dumps(reply.raw, separators=(",", ":")),
            reply.text, reply.finish_reason, reply.prompt_tokens, reply.completion_tokens)
        with self._lock:
            db = self._db
            db.execute("BEGIN IMMEDIATE")
            try:
                for digest, mime, data in request.images:
                    if digest not in self._known_images:
                        db.execute("INSERT OR IGNORE INTO images (sha256, mime, data) VALUES (?, ?, ?)", (digest, mime, data))
                db.execute("INSERT OR IGNORE INTO requests (key, model, body) VALUES (?, ?, ?)",
                           (request.key, request.model, request.body_json))
                db.execute("INSERT OR REPLACE INTO replies VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                           (request.key, stream, occurrence, *fields, latency_s, attempts,
                            None if error is None else str(error), None if error is None else error.kind,
                            datetime.now(UTC).isoformat(timespec="seconds")))
                db.execute("COMMIT")
            except BaseException:
                db.execute("ROLLBACK")
                raise
            self._known_images.update(digest for digest, _, _ in request.images)


def _connect(path: Path) -> sqlite3.Connection:
    """The cache file opened (created with its tables when missing) in WAL mode; CacheError for a
    file that is not an agos VLM cache of this version."""
    where = f"--vlm-cache {path.parent}"
    # Processes opening one new file at once take turns: SQLite answers "database is locked" at once,
    # without waiting out the busy timeout, to a switch to WAL or a schema write that races another.
    try:
        lock = (path.parent / f"{path.name}.open-lock").open("a")
    except OSError as exc:
        raise CacheError(f"{where}: cannot write beside {path.name} ({exc.strerror}); give a writable folder") from None
    with lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        try:
            db = sqlite3.connect(path, timeout=BUSY_TIMEOUT_MS / 1000, isolation_level=None, check_same_thread=False)
            db.execute(f"PRAGMA busy_timeout = {BUSY_TIMEOUT_MS}")
            if db.execute("PRAGMA journal_mode").fetchone()[0] != "wal":
                db.execute("PRAGMA journal_mode = WAL")
            db.execute("PRAGMA synchronous = NORMAL")  # WAL: a crash may lose the last replies, never corrupt the file
            db.executescript(SCHEMA)
            db.execute("INSERT OR IGNORE INTO meta VALUES ('format', ?), ('version', ?)",
                       (FORMAT_NAME, str(FORMAT_VERSION)))
            meta = dict(db.execute("SELECT name, value FROM meta").fetchall())
        except sqlite3.DatabaseError as exc:
            raise CacheError(f"{where}: {path.name} is not a readable SQLite file ({exc})") from None
    if meta.get("format") != FORMAT_NAME or meta.get("version") != str(FORMAT_VERSION):
        db.close()
        raise CacheError(f"{where}: {path.name} is format {meta.get('format')!r} version {meta.get('version')!r}; this "
                         f"agos reads {FORMAT_NAME!r} version {FORMAT_VERSION}")
    return db


def _served(row: tuple) -> Reply:
    """A stored row as the client's answer: a Reply, or the stored VlmError raised again."""
    body, text, finish_reason, prompt_tokens, completion_tokens, latency_s, attempts, error, error_kind = row
    if error is not None:
        raise VlmError(error, attempts=attempts, kind=error_kind or "http")
    return Reply(text=text, finish_reason=finish_reason, prompt_tokens=prompt_tokens, completion_tokens=completion_tokens,
                 latency_s=latency_s, attempts=attempts, raw=json.loads(body) if body else {},
                 reply_bytes=len(body.encode("utf-8")) if body else 0)


def _miss_line(directory: Path, request: CanonicalRequest, call: CallTag | None, stream: str, occurrence: int,
               recorded: int) -> str:
    who = (f"role {call.role}, decision {call.episode_id} #{call.decision_index}" if call is not None
           else "no decision named")
    why = (f"recorded {recorded} time(s) in stream {stream!r}, this is ask {occurrence + 1}" if recorded
           else f"never recorded in stream {stream!r}")
    return (f"VLM cache miss in replay: model {request.model}, {who}, request {request.key[:16]} ({why}) in {directory}; "
            "replay needs the recorded run's split, policy, model and settings, or record the missing calls with "
            "--vlm-cache-mode record")


@dataclass(frozen=True)
class ModelStats:
    """One model's share of a cache."""

    model: str
    requests: int
    """Distinct requests (keys)."""
    replies: int
    """Stored (key, stream, occurrence) rows, errors included."""
    errors: int
    """Requests the endpoint never answered when recorded."""
    prompt_tokens: int
    completion_tokens: int
    hits: int
    misses: int


@dataclass(frozen=True)
class CacheStats:
    models: list[ModelStats]
    images: int
    image_bytes: int
    file_bytes: int
    """The SQLite file with its WAL and shared-memory files."""


def cache_stats(directory: Path) -> CacheStats:
    """What a cache directory holds, and every process's hits and misses on it (CacheError when there is none)."""
    path = cache_file(directory)
    if not path.is_file():
        raise CacheError(f"{directory}: no {CACHE_FILE}; not a VLM cache (agos eval --vlm-cache DIR records one)")
    db = _connect(path)
    try:
        lookups = {m: (h, s) for m, h, s in db.execute("SELECT model, hits, misses FROM lookups")}
        rows = db.execute(
            "SELECT q.model, COUNT(DISTINCT r.key), COUNT(*), COUNT(r.error), TOTAL(r.prompt_tokens), "
            "TOTAL(r.completion_tokens) FROM replies r JOIN requests q USING (key) GROUP BY q.model").fetchall()
        per_model = {m: ModelStats(m, n_req, n_rep, n_err, int(p), int(c), *lookups.get(m, (0, 0)))
                     for m, n_req, n_rep, n_err, p, c in rows}
        for m, (hits, misses) in lookups.items():
            per_model.setdefault(m, ModelStats(m, 0, 0, 0, 0, 0, hits, misses))
        images, image_bytes = db.execute("SELECT COUNT(*), TOTAL(LENGTH(data)) FROM images").fetchone()
    finally:
        db.close()
    files = [path, path.with_name(path.name + "-wal"), path.with_name(path.name + "-shm")]
    return CacheStats(sorted(per_model.values(), key=lambda s: s.model), images, int(image_bytes),
                      sum(f.stat().st_size for f in files if f.exists()))


def stats_table(stats: CacheStats, *, title: str) -> Table:
    """``agos vlm-cache stats``' table: one row per model, every count with thousands separators."""
    from rich.table import Table

    table = Table(title=title)
    table.add_column("model", no_wrap=True, min_width=max([5, *(len(m.model) for m in stats.models)]))
    for name in ("requests", "replies", "errors", "hits", "misses", "tokens in", "tokens out"):
        table.add_column(name, justify="right")
    for m in stats.models:
        table.add_row(m.model, *(f"{v:,}" for v in (m.requests, m.replies, m.errors, m.hits, m.misses, m.prompt_tokens,
                                                     m.completion_tokens)))
    return table


def size_line(stats: CacheStats) -> str:
    """The line under :func:`stats_table`: the cache's size on disk and its images'."""
    return (f"size: {stats.file_bytes / 1e6:.1f} MB ({stats.images:,} images, {stats.image_bytes / 1e6:.1f} MB); "
            "hits and misses count every lookup of every run, replies errors included")
