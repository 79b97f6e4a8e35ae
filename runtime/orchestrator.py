"""The run orchestrator: leases episodes to world workers and tracks which are stored.

Workers ask on ``agos/<run>/ctl/jobs`` (a queryable); each query is answered with the next
unleased episode, with ``None`` while others are still running, or with ``run_finished``.
An episode is done when the evaluator's ack for it is seen. The manifest on
``agos/<run>/ctl/manifest`` says what the run is and whether it is running or finished.
"""

from __future__ import annotations

import logging
from collections import deque
from datetime import UTC, datetime

from agos.runtime import keys
from agos.runtime.bus import Inbox, ZenohBus
from agos.runtime.codec import DecodeError, decode, encode
from agos.runtime.schemas import EpisodeRecord, EpisodeSpec, JobGrant, JobRequest, ResultAck, RunManifest

log = logging.getLogger("agos.orchestrator")


class Orchestrator:
    def __init__(self, bus: ZenohBus, run_id: str, episodes: list[EpisodeSpec], *, policies: dict[str, str]) -> None:
        self.bus, self.run_id = bus, run_id
        self.total = len(episodes)
        self.pending: deque[EpisodeSpec] = deque(episodes)
        self.leased: dict[str, str] = {}
        self.records: dict[str, EpisodeRecord] = {}
        self.stored: set[str] = set()
        self.policies = policies
        self.created_utc = datetime.now(UTC).isoformat(timespec="seconds")
        self._queries = bus.serve(keys.jobs(run_id), lambda q: None)
        # Imported towns travel by hash: workers without the file ask agos/assets/<sha256>.
        self._asset_queries = bus.serve(keys.asset("*"), lambda q: None)
        self._inbox = Inbox()
        bus.subscribe(keys.result(run_id, "*"), self._inbox)
        bus.subscribe(keys.result_ack(run_id, "*"), self._inbox)

    @property
    def finished(self) -> bool:
        return len(self.stored) >= self.total

    def publish_manifest(self, status: str) -> None:
        self.bus.publish(keys.manifest(self.run_id), RunManifest(
            run_id=self.run_id, status=status, policies=self.policies, n_episodes=self.total,
            created_utc=self.created_utc))

    def pump(self, timeout_s: float) -> list[EpisodeRecord]:
        """Answer job queries and read results/acks for up to ``timeout_s``; return the records
        whose storage was acknowledged in this call."""
        newly: list[EpisodeRecord] = []
        for query in self._queries.drain():
            self._answer(query)
        sample = self._inbox.get(timeout_s)
        samples = ([sample] if sample else []) + self._inbox.drain()
        for s in samples:
            try:
                message = decode(s.payload)
            except DecodeError:
                continue
            if isinstance(message, EpisodeRecord):
                self.records[message.episode_id] = message
            elif isinstance(message, ResultAck) and message.episode_id not in self.stored:
                self.stored.add(message.episode_id)
                self.leased.pop(message.episode_id, None)
                if message.episode_id in self.records:
                    newly.append(self.records[message.episode_id])
        for query in self._queries.drain():
            self._answer(query)
        for query in self._asset_queries.drain():
            self._answer_asset(query)
        return newly

    def _answer_asset(self, query) -> None:
        """Serve a town asset from the local asset cache; unknown hashes get no reply."""
        from agos.world.asset import cache_dir

        sha = query.key.rsplit("/", 1)[-1]
        path = cache_dir() / keys.check_chunk(sha, what="asset hash") / "asset.msgpack"
        if path.exists():
            log.info("serving asset %s (%d bytes)", sha[:12], path.stat().st_size)
            query.reply(path.read_bytes())

    def _answer(self, query) -> None:
        try:
            request = decode(query.payload)
        except DecodeError:
            request = None
        worker = request.worker_id if isinstance(request, JobRequest) else "?"
        if self.pending:
            spec = self.pending.popleft()
            self.leased[spec.episode_id] = worker
            log.info("leased %s to %s", spec.episode_id, worker)
            query.reply(encode(JobGrant(episode=spec)))
        else:
            query.reply(encode(JobGrant(episode=None, run_finished=self.finished)))
