"""The link to the model (docs/COMMS.md, "The link to the model"): where a VLM policy's model runs,
and what each decision's request and reply pay to get there and back, in simulated time.

A :class:`ModelLinkProfile` (``deploy/model_link/<name>.toml``, ``--model-link NAME``) has an ``up``
(robot -> model) and a ``down`` (model -> robot) direction, each with the robot link's stages that
make sense without geometry (runtime/links.py: blackouts, Bernoulli or Gilbert-Elliott loss,
bandwidth through a FIFO, latency with jitter), and the client's ``retry``: how long it waits for a
reply after its request has gone out, and how many attempts it makes. ``onboard`` (the model on the
robot) has no link at all; a configuration says so with ``model_link = None``
(:func:`placement`), so the default configuration, its hash and its records are those of before.

One model-backed decision at simulated time ``t`` (:meth:`ModelLink.exchange`): the request
(``request_bytes``) goes up as one transmission; the model answers once it has arrived (its own
compute time is not the link's); the reply (``reply_bytes``) comes down. An attempt fails when the
request or the reply is lost, or when the reply's first byte would come later than ``timeout_s``
after the request's last byte went out: the client then sends the request again, ``timeout_s``
after it finished sending it. The link time is the reply's arrival minus ``t``; when every attempt
fails the decision fails (the world applies a counted WAIT) after the last timeout. A decision
whose model was asked again (``reasks``) makes that many more exchanges, back to back, the bytes
shared evenly among them.

Each role talks to the model over its own pair of links, each direction with its own random stream
derived from the episode seed and the link seed, apart from the robot link's streams (whose
deliveries therefore do not change when a model link is configured).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from agos.runtime.keys import ROLES
from agos.runtime.links import BandwidthSpec, Blackout, CommProfile, LatencySpec, Link, LossSpec
from agos.runtime.schemas import ModelLinkStats
from agos.runtime.textfiles import read_profile

PROFILE_DIR = Path(__file__).resolve().parents[1] / "deploy" / "model_link"
MODEL_LINK_ENTROPY = 0x6D6F646C
"""Mixed into the episode seed for the model link's streams ("modl"; the robot link uses "link")."""
ONBOARD = "onboard"


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Direction(_Section):
    """One direction of the link to the model: the robot link's stages without range."""

    latency: LatencySpec = Field(default_factory=LatencySpec)
    loss: LossSpec = Field(default_factory=LossSpec)
    bandwidth: BandwidthSpec = Field(default_factory=BandwidthSpec)
    blackouts: list[Blackout] = Field(default_factory=list)

    def comm_profile(self, name: str) -> CommProfile:
        """This direction as a robot-link profile (for :class:`~agos.runtime.links.Link`)."""
        return CommProfile(name=name, latency=self.latency, loss=self.loss, bandwidth=self.bandwidth,
                           blackouts=self.blackouts)


class RetrySpec(_Section):
    timeout_s: float = Field(10.0, gt=0)
    """How long the client waits for the reply after its request has gone out (the model's compute
    time not counted) before it sends the request again."""
    max_attempts: int = Field(3, ge=1)
    """Attempts per exchange, the first included."""


class ModelLinkProfile(_Section):
    """Where the model runs and the link to it (see the module)."""

    name: str
    description: str = ""
    onboard: bool = False
    """The model runs on the robot: no link (``up``, ``down`` and ``retry`` must be left out)."""
    up: Direction = Field(default_factory=Direction)
    """Robot -> model: the request."""
    down: Direction = Field(default_factory=Direction)
    """Model -> robot: the reply."""
    retry: RetrySpec = Field(default_factory=RetrySpec)

    @model_validator(mode="after")
    def _a_link_has_a_bandwidth(self) -> ModelLinkProfile:
        if self.onboard:
            given = [k for k in ("up", "down", "retry") if k in self.model_fields_set]
            if given:
                raise ValueError(f"{given[0]}: an onboard model has no link (leave out up, down and retry)")
            return self
        for side in ("up", "down"):
            if getattr(self, side).bandwidth.bits_per_s is None:
                raise ValueError(f"{side}.bandwidth.bits_per_s: a model link needs a bandwidth (use onboard for none)")
        return self


class ModelLinkError(ValueError):
    """A bad model-link profile; the message names the file and the field."""



def load_model_link(name_or_path: str | Path) -> ModelLinkProfile:
    """A placement by name (``deploy/model_link/<name>.toml``) or by file path; :class:`ModelLinkError`
    (one line naming the file and the field) for a missing, unreadable or invalid one."""
    return read_profile(name_or_path, PROFILE_DIR, ModelLinkProfile, ModelLinkError, what="model link",
                        known_as="known placements")


def placement(profile: ModelLinkProfile | None) -> ModelLinkProfile | None:
    """What a configuration holds for ``profile``: None for the model onboard (no link), else the profile."""
    return None if profile is None or profile.onboard else profile


@dataclass(frozen=True)
class Exchange:
    """What one decision's request and reply met on the link."""

    link_s: float
    """From the decision to the reply's arrival (or to the client giving up), the model's compute
    time excluded."""
    attempts: int
    """Attempts made over all the decision's exchanges."""
    bytes_up: int = 0
    bytes_down: int = 0
    failed: str | None = None
    """Why no reply came back (the last attempt's fate), or None."""


@dataclass
class _Pair:
    up: Link
    down: Link


@dataclass
class ModelLink:
    """One episode's link to the model: each role's pair of links, and the tally for the record."""

    profile: ModelLinkProfile
    pairs: dict[str, _Pair]
    decisions: int = 0
    bytes_up: int = 0
    bytes_down: int = 0
    times: list[float] = field(default_factory=list)
    failed: int = 0

    def exchange(self, role: str, t_s: float, request_bytes: int, reply_bytes: int, *, exchanges: int = 1,
                 compute_s: float = 0.0) -> Exchange:
        """The decision of ``role`` at ``t_s`` whose request and reply carry these bytes (over
        ``exchanges`` back-to-back exchanges, e.g. ``1 + reasks``); ``compute_s``: the model's time per
        exchange (realtime mode), spent between the request's arrival and the reply's departure."""
        n = max(1, exchanges)
        pair, retry = self.pairs[role], self.profile.retry
        ups, downs = _split(request_bytes, n), _split(reply_bytes, n)
        now, attempts, failed = t_s, 0, None
        for k in range(n):
            now, made, failed = self._one(pair, retry, now, ups[k], downs[k], compute_s)
            attempts += made
            if failed is not None:
                break
        link_s = max(0.0, now - t_s - compute_s * (k + 1))
        self.decisions += 1
        self.bytes_up += request_bytes
        self.bytes_down += reply_bytes
        self.times.append(link_s)
        self.failed += failed is not None
        return Exchange(link_s, attempts, request_bytes, reply_bytes, failed)

    @staticmethod
    def _one(pair: _Pair, retry: RetrySpec, t_s: float, up_bytes: int, down_bytes: int,
             compute_s: float) -> tuple[float, int, str | None]:
        """One request and its reply from ``t_s``, with the client's retries: (when the reply arrived,
        or when the client gave up; attempts made; why it failed, or None)."""
        up_bps = pair.up.profile.bandwidth.bits_per_s
        down_bps = pair.down.profile.bandwidth.bits_per_s
        start, why = t_s, "no attempt"
        for attempt in range(1, retry.max_attempts + 1):
            sent = start + (up_bytes * 8 / up_bps if up_bps else 0.0)
            deadline = sent + retry.timeout_s + compute_s
            up = pair.up.transmit(start, up_bytes)
            if not up.delivered or up.arrive_s is None:
                why = f"request lost ({up.reason})"
            else:
                down = pair.down.transmit(up.arrive_s + compute_s, down_bytes)
                if not down.delivered or down.arrive_s is None:
                    why = f"reply lost ({down.reason})"
                elif down.arrive_s - (down_bytes * 8 / down_bps if down_bps else 0.0) > deadline:
                    why = "reply too late (timeout)"
                else:
                    return down.arrive_s, attempt, None
            start = deadline
        return start, retry.max_attempts, why

    def stats(self) -> ModelLinkStats:
        return ModelLinkStats(profile=self.profile.name, decisions=self.decisions, bytes_up=self.bytes_up,
                              bytes_down=self.bytes_down, link_time_s=round(sum(self.times), 3),
                              max_link_time_s=round(max(self.times, default=0.0), 3), failed=self.failed)


def _split(total: int, n: int) -> list[int]:
    """``total`` bytes over ``n`` exchanges, as evenly as whole bytes allow (the first ones larger)."""
    q, r = divmod(max(0, total), n)
    return [q + (i < r) for i in range(n)]


def model_link_for(profile: ModelLinkProfile | None, seed: int) -> ModelLink | None:
    """The link to the model of an episode whose link seed is ``seed`` (the robot link's: the episode
    seed + 7919 x link_seed), or None onboard. Four streams (each role up and down), apart from the
    robot link's."""
    profile = placement(profile)
    if profile is None:
        return None
    streams = np.random.SeedSequence([seed, MODEL_LINK_ENTROPY]).spawn(4)
    up, down = profile.up.comm_profile(f"{profile.name}/up"), profile.down.comm_profile(f"{profile.name}/down")
    pairs: dict[str, _Pair] = {
        role: _Pair(Link(up, np.random.default_rng(streams[2 * i])), Link(down, np.random.default_rng(streams[2 * i + 1])))
        for i, role in enumerate(ROLES)}
    return ModelLink(profile, pairs)
