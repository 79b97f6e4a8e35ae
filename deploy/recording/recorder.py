"""``agos record``: the recorder process: a run's visualisation stream -> one rerun file per episode.

    agos record --connect EP --run RUN --out DIR [--full] [--format rrd|mcap]

(``agos eval --record DIR`` and ``agos demo --record DIR`` start it for their run.)

``--format mcap`` writes ``DIR/<episode>.mcap`` instead (deploy/recording/mcap_episode.py: ROS 2 message
schemas and JSON, the same stream on the same terms); everything below holds for both formats.

Contract: the recorder only subscribes, and only to ``agos/<run>/viz/...`` (on a secured bus it is
the ``observer`` identity, which may hear nothing else), so it is never in the world's decision
path: the world publishes the stream with congestion control DROP whoever listens. Its zenoh
callbacks only put samples into a bounded queue (:class:`BoundedInbox`: at most ``QUEUE_SAMPLES``
samples and ``QUEUE_BYTES`` bytes), which drops and counts what does not fit; decoding and writing
happen on the recorder's own thread (:class:`EpisodeRecording`, deploy/recording/episode.py). A recorder
that falls behind therefore loses visualisation samples, and says how many at exit, in its log and
in ``DIR/recorder.json``; it never slows the run.

``--full`` subscribes to ``viz/*/full/<role>`` instead of the thumbnails (``frame/<role>``), which
makes the worlds send every view at full resolution (runtime/viz.py); without it the recording holds
the stream's thumbnails.

Keys name world workers (``viz/<worker>/...``), not episodes, and one worker's keys carry its episodes
one after the other: every sample goes to the recording of the episode its payload names
(``episode_id``), so a late frame of one episode and the first samples of the worker's next one, on
the same key, each land in their own file. A payload that names another run, or no valid episode id
(``keys.check_chunk``: the id is a file name), is refused and counted.

An episode's file is finished ``LATE_S`` seconds after the copy of its record arrives on
``viz/<worker>/result`` (frames are made on the world's frame thread and may arrive after it); at exit
(SIGTERM, SIGINT) the recorder goes on until every open file is finished that way, for at most
``DRAIN_S`` seconds (``agos eval`` stops the recorder once the evaluator has stored the last
record, and that copy travels at a higher priority than the stream's, so it can overtake it); then
every open recording is closed (its outcome then says no record arrived).

Fault injection: ``AGOS_FAULT_RECORDER_STALL_S=N`` in the recorder's environment makes its handler
stop for N seconds at the first sample, as a recorder stuck in its work would, to show that a
stuck recorder never slows the run (docs/VIEWING.md; tests/test_e2e_record.py). It is not a setting:
nothing but a fault test sets it.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

from agos.deploy.recording.episode import MAP_PX, EpisodeRecording
from agos.deploy.recording.mcap_episode import McapEpisodeRecording
from agos.deploy.reports.episode_map import EpisodeMap, episode_map
from agos.runtime import keys
from agos.runtime.bus import Bus, Inbox, Sample, ZenohBus
from agos.runtime.codec import DecodeError, decode
from agos.runtime.process import StopFlag, install_stop_handlers, setup_logging, stop_requested
from agos.runtime.rejections import Rejections
from agos.runtime.schemas import CoordinationState, EpisodeRecord, EpisodeSpec, EpisodeStarted, StepEvent, VizFrame
from agos.runtime.settings import AgosConfig
from agos.runtime.viz import episode_of_payload

log = logging.getLogger("agos.record")
QUEUE_SAMPLES = 4096
QUEUE_BYTES = 128 * 2**20
DRAIN_S = 5.0
LATE_S = 2.0
STATUS_FILE = "recorder.json"
FORMATS = ("rrd", "mcap")
"""File formats: rerun (the default) and MCAP (the ``robotics`` extra)."""
STALL_ENV = "AGOS_FAULT_RECORDER_STALL_S"
"""The fault-injection variable (see the module docstring)."""


def _kind(key: str) -> str:
    """What a key of the stream carries, without the role: ``events``, ``coord``, ``frame``, ``full``,
    ``spec`` or ``result`` (``?`` for a key that is no viz key)."""
    try:
        return keys.parse_slot(key).kind
    except ValueError:
        return "?"


def _dropped_of(sample: Sample) -> tuple[str, str]:
    """(episode, kind) of a sample the queue drops: the episode its payload names (``?`` when it names
    none that could be a recording's), read without decoding the rest of it."""
    episode = episode_of_payload(sample.payload)
    try:
        episode = keys.check_chunk(episode or "", what="episode id")
    except ValueError:
        episode = "?"
    return episode, _kind(sample.key)


class BoundedInbox(Inbox):
    """An inbox that never blocks its producer (zenoh's callback thread): a sample that would take
    it past ``max_samples`` or ``max_bytes`` is dropped and counted by (episode, kind), the episode
    its payload names (keys name world workers, not episodes; only a dropped sample is read for it)."""

    def __init__(self, max_samples: int = QUEUE_SAMPLES, max_bytes: int = QUEUE_BYTES) -> None:
        super().__init__()
        self.max_samples, self.max_bytes = max_samples, max_bytes
        self.queued_bytes = 0
        self.dropped: Counter[tuple[str, str]] = Counter()
        self._lock = threading.Lock()

    def put(self, sample: Sample) -> None:
        with self._lock:
            full = self._queue.qsize() >= self.max_samples or self.queued_bytes + len(sample.payload) > self.max_bytes
            if not full:
                self.queued_bytes += len(sample.payload)
        if full:
            counted = _dropped_of(sample)  # its payload read outside the lock
            with self._lock:
                self.dropped[counted] += 1
            return
        self._queue.put(sample)

    def get(self, timeout_s: float | None = None) -> Sample | None:
        sample = super().get(timeout_s)
        if sample is not None:
            with self._lock:
                self.queued_bytes -= len(sample.payload)
        return sample


class Recorder:
    """Subscribes to one run's visualisation stream and keeps one :class:`EpisodeRecording` per episode."""

    def __init__(self, bus: Bus, run_id: str, out_dir: Path, *, full: bool = False,
                 map_source: Callable[[EpisodeSpec], EpisodeMap] | None = None, inbox: BoundedInbox | None = None,
                 fmt: str = "rrd") -> None:
        if fmt not in FORMATS:
            raise ValueError(f"no recording format {fmt!r}: {' or '.join(FORMATS)}")
        self.bus, self.run_id, self.out_dir, self.full, self.fmt = bus, run_id, out_dir, full, fmt
        self.map_source = map_source
        self.inbox = inbox or BoundedInbox()
        self.open: dict[str, EpisodeRecording | McapEpisodeRecording] = {}
        self.closing: dict[str, float] = {}
        """Episode -> when (monotonic) to close its recording: its record has arrived."""
        self.finished: dict[str, dict[str, Any]] = {}
        """Episode -> what its recording holds (written to recorder.json)."""
        self.rejections = Rejections(log)
        self.stall_s = float(os.environ.get(STALL_ENV, "0") or 0)
        out_dir.mkdir(parents=True, exist_ok=True)
        self._handles = [bus.subscribe(k, self.inbox) for k in keys.viz_light(run_id, full=full)]

    def serve(self, stop: StopFlag) -> int:
        log.info("recording run %s to %s (%s, %s files)", self.run_id, self.out_dir,
                 "full resolution" if self.full else "thumbnails", self.fmt)
        self._status("recording")
        while not stop.is_set():
            sample = self.inbox.get(timeout_s=0.2)
            if sample is not None:
                self.handle(sample, stop)
            self._close_due()
        deadline = time.monotonic() + DRAIN_S
        while time.monotonic() < deadline:
            sample = self.inbox.get(timeout_s=0.1)
            if sample is not None:
                self.handle(sample, None)
            self._close_due()
            if not self.open:
                break
        left = len(self.inbox.drain())
        self.finish()
        self._status("stopped", not_written=left)
        dropped = sum(self.inbox.dropped.values()) + left
        by_kind = self._dropped_by_kind()
        log.info("recorder stops: %d episodes written to %s; %d samples dropped by its queue%s%s",
                 len(self.finished), self.out_dir, dropped,
                 f" ({', '.join(f'{k}={n}' for k, n in sorted(by_kind.items()))})" if by_kind else "",
                 f", {left} queued at exit not written" if left else "")
        self.rejections.log_summary()
        return 0

    def _close_due(self) -> None:
        """Finish the files whose record arrived ``LATE_S`` ago (their last frames have had time)."""
        for episode in [e for e, at in self.closing.items() if at <= time.monotonic()]:
            self._close(episode)

    def finish(self) -> None:
        """Close every open recording and stop listening."""
        for episode in list(self.open):
            self._close(episode)
        for handle in self._handles:
            self.bus.unsubscribe(handle)
        self._handles = []

    def handle(self, sample: Sample, stop: StopFlag | None = None) -> None:
        """One sample of the stream, on the recorder's thread."""
        if self.stall_s > 0 and stop is not None:
            log.warning("fault injection %s: the handler stops for %.0f s", STALL_ENV, self.stall_s)
            started = time.monotonic()
            stopped = stop.wait(self.stall_s)
            log.warning("fault injection %s: %s after %.1f s of the stall", STALL_ENV,
                        "stopped while stuck" if stopped else "the handler goes on", time.monotonic() - started)
            self.stall_s = 0.0
        try:
            message = decode(sample.payload)
        except DecodeError as exc:
            self.rejections.reject(sample.key, "unreadable", exc)
            return
        # The payload says which episode (keys name the world worker, whose episodes follow each other).
        episode = getattr(message, "episode_id", None)
        if not isinstance(episode, str):
            self.rejections.reject(sample.key, f"a {type(message).__name__} where none is expected")
            return
        if getattr(message, "run_id", self.run_id) != self.run_id:
            self.rejections.reject(sample.key, "names another run than its key")
            return
        try:
            keys.check_chunk(episode, what="episode id")  # a file name: nothing outside out_dir
        except ValueError as exc:
            self.rejections.reject(sample.key, "names no valid episode", exc)
            return
        try:
            self._dispatch(episode, _kind(sample.key), message, sample.key)
        except Exception as exc:  # one bad sample (or a bug) costs that sample, never the other recordings
            log.debug("sample on %s not recorded", sample.key, exc_info=True)
            self.rejections.reject(sample.key, "could not be recorded", f"{type(exc).__name__}: {exc}")

    def _dispatch(self, episode: str, kind: str, message: object, key: str) -> None:
        if isinstance(message, EpisodeStarted):
            if episode in self.closing:
                self._close(episode)
            if episode in self.finished:  # the episode again (a resumed run): a new file
                self.finished.pop(episode)
            self._recording(episode).started(message)
            return
        if episode in self.finished:
            return  # late samples of an episode already written
        recording = self._recording(episode)
        if isinstance(message, EpisodeSpec) and kind == "spec":
            recording.episode_spec(message)
        elif isinstance(message, StepEvent):
            recording.step(message)
        elif isinstance(message, CoordinationState):
            recording.coordination(message)
        elif isinstance(message, VizFrame):
            recording.frame(message)
        elif isinstance(message, EpisodeRecord):
            recording.result(message)
            self.closing[episode] = time.monotonic() + LATE_S
        else:
            self.rejections.reject(key, f"a {type(message).__name__} where none is expected")

    def _recording(self, episode: str) -> EpisodeRecording | McapEpisodeRecording:
        if episode not in self.open:  # handle() has checked the id (a file name: nothing outside out_dir)
            kind = McapEpisodeRecording if self.fmt == "mcap" else EpisodeRecording
            self.open[episode] = kind(self.out_dir, self.run_id, episode, full=self.full, map_source=self.map_source)
        return self.open[episode]

    def _close(self, episode: str) -> None:
        self.closing.pop(episode, None)
        recording = self.open.pop(episode)
        recording.seen.dropped_before = sum(n for (ep, _), n in self.inbox.dropped.items() if ep == episode)
        seen = recording.close()
        self.finished[episode] = {"file": recording.path.name, "record": recording.record is not None,
                                  "steps": seen.steps, "frames": dict(seen.frames), "coordination_states": seen.coords,
                                  "dropped_by_queue": seen.dropped_before}
        log.info("%s: %s (%d steps, frames %s)", episode, recording.path, seen.steps, dict(seen.frames))

    def _dropped_by_kind(self) -> Counter[str]:
        """Samples the queue dropped, by kind (``frame``, ``events``, ...), over all episodes."""
        by_kind = Counter[str]()
        for (_, kind), n in self.inbox.dropped.items():
            by_kind[kind] += n
        return by_kind

    def _status(self, status: str, **extra: Any) -> None:
        """``DIR/recorder.json``: what the recorder is doing and, at exit, what it wrote and lost."""
        doc = {"run_id": self.run_id, "status": status, "full_resolution": self.full, "format": self.fmt, "pid": os.getpid(),
               "episodes": self.finished, "dropped_by_queue": dict(self._dropped_by_kind()), **extra}
        tmp = self.out_dir / f".{STATUS_FILE}.tmp"
        tmp.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
        tmp.replace(self.out_dir / STATUS_FILE)


def main(cfg: AgosConfig, out_dir: Path, *, full: bool = False, fmt: str = "rrd") -> int:
    setup_logging("record")
    stop = install_stop_handlers()
    with ZenohBus.from_settings(cfg.zenoh) as bus:
        recorder = Recorder(bus, cfg.run.run_id, out_dir, full=full, fmt=fmt,  # an MCAP file draws no town map
                            map_source=None if fmt == "mcap" else lambda spec: episode_map(spec, size_px=MAP_PX))
        return recorder.serve(stop)


def wait_ready(out_dir: Path, timeout_s: float, since: float, alive: Callable[[], bool] = lambda: True) -> bool:
    """Whether a recorder started at ``since`` (epoch seconds) has subscribed and says so in
    ``DIR/recorder.json`` within ``timeout_s`` (False at once when ``alive()`` says it exited, or this
    process was asked to stop: the run is not going to start)."""
    deadline = time.monotonic() + timeout_s
    path = out_dir / STATUS_FILE
    while time.monotonic() < deadline and alive() and not stop_requested():
        try:
            if path.stat().st_mtime >= since - 1 and json.loads(path.read_text()).get("status") == "recording":
                return True
        except (OSError, ValueError):
            pass
        time.sleep(0.1)
    return False
