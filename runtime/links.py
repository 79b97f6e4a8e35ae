"""Link models between the UAV and the UGV (docs/COMMS.md): seeded, in simulated time.

A :class:`Link` decides, for each transmission, whether and when it arrives. The stages apply
in this order, each recording why a message was dropped:

1. ``blackout``: scheduled intervals with no delivery at all;
2. ``range``: beyond ``max_range_m`` nothing arrives; without line of sight (ray tests done by
   the world) an extra loss probability applies;
3. ``loss``: independent (Bernoulli) loss, or bursty loss from a two-state Gilbert-Elliott
   chain stepped once per transmission;
4. ``bandwidth``: serialization delay ``bytes * 8 / bits_per_s`` through a FIFO with a bounded
   queue (in bytes); a message that does not fit is dropped; a message lost in stages 1-3 never
   occupies the radio;
5. ``latency``: propagation delay ``mean_s`` plus jitter (normal, uniform, exponential or
   lognormal; never negative), added after the queue, so with jitter messages may arrive out of
   order (receivers keep the newest information).

Two message-fault stages then harm what was delivered (both off by default):

6. ``duplicate``: with probability ``p`` a delivered transmission arrives a second time,
   ``delay_s`` after the first (:attr:`Delivery.duplicate_arrive_s`);
7. ``corruption``: each character of a ``message`` text is replaced, with probability
   ``char_error_rate``, by another printable ASCII character (:func:`corrupt_text`, seeded by
   :attr:`Delivery.corrupt_seed`). The link does not see payloads: the channel applies it to text.

Each direction (uav->ugv, ugv->uav) has its own link and random stream, derived from the
episode seed, so the same seed gives bit-identical deliveries. The fault stages draw from a
second stream of their own (a fixed count per transmission), so adding them leaves the
deliveries of every profile without faults exactly as they were. Profiles are TOML files in
``deploy/comm/`` (see :func:`load_profile`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from agos.runtime.keys import ROLES
from agos.runtime.textfiles import read_profile

PROFILE_DIR = Path(__file__).resolve().parents[1] / "deploy" / "comm"


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class LatencySpec(_Section):
    mean_s: float = Field(0.0, ge=0)
    jitter_s: float = Field(0.0, ge=0)
    """Standard deviation (normal, lognormal), half-width (uniform); exponential ignores it."""
    distribution: Literal["normal", "uniform", "exponential", "lognormal"] = "normal"


class LossSpec(_Section):
    model: Literal["none", "bernoulli", "gilbert_elliott"] = "none"
    p: float = Field(0.0, ge=0, le=1)
    """Bernoulli loss probability."""
    p_good_to_bad: float = Field(0.0, ge=0, le=1)
    p_bad_to_good: float = Field(1.0, ge=0, le=1)
    loss_good: float = Field(0.0, ge=0, le=1)
    loss_bad: float = Field(1.0, ge=0, le=1)


class BandwidthSpec(_Section):
    bits_per_s: float | None = Field(None, gt=0)
    queue_bytes: int = Field(1_000_000, ge=0)


class RangeSpec(_Section):
    max_range_m: float | None = Field(None, gt=0)
    nlos_loss: float = Field(0.0, ge=0, le=1)
    """Extra loss probability when the line of sight between the two agents is blocked."""


class DuplicateSpec(_Section):
    p: float = Field(0.0, ge=0, le=1)
    """Probability that a delivered transmission is delivered a second time."""
    delay_s: float = Field(0.05, ge=0)
    """How long after the original the copy arrives."""


class CorruptionSpec(_Section):
    char_error_rate: float = Field(0.0, ge=0, le=1)
    """Probability that each character of a ``message`` text is replaced by another printable ASCII
    character (syncs and beacons are never corrupted: see agos.world.sim.comms)."""


class Blackout(_Section):
    start_s: float = Field(ge=0)
    end_s: float = Field(ge=0)

    @model_validator(mode="after")
    def _ordered(self) -> Blackout:
        if self.end_s < self.start_s:
            raise ValueError(f"blackout ends ({self.end_s} s) before it starts ({self.start_s} s)")
        return self


class CommProfile(_Section):
    name: str
    description: str = ""
    latency: LatencySpec = Field(default_factory=LatencySpec)
    loss: LossSpec = Field(default_factory=LossSpec)
    bandwidth: BandwidthSpec = Field(default_factory=BandwidthSpec)
    range: RangeSpec = Field(default_factory=RangeSpec)
    blackouts: list[Blackout] = Field(default_factory=list)
    duplicate: DuplicateSpec = Field(default_factory=DuplicateSpec)
    corruption: CorruptionSpec = Field(default_factory=CorruptionSpec)
    beacon_s: float = Field(5.0, gt=0)
    """Each role re-broadcasts its coordination knowledge at least this often (sim seconds)."""

    @property
    def ideal(self) -> bool:
        return (self.latency.mean_s == 0 and self.latency.jitter_s == 0 and self.loss.model == "none"
                and self.bandwidth.bits_per_s is None and self.range.max_range_m is None
                and self.range.nlos_loss == 0 and not self.blackouts
                and self.duplicate.p == 0 and self.corruption.char_error_rate == 0)


class ProfileError(ValueError):
    """A bad comm profile; the message names the file and the field."""


def load_profile(name_or_path: str | Path) -> CommProfile:
    """A profile by name (``deploy/comm/<name>.toml``) or by file path; :class:`ProfileError` (one line)
    for a missing, unreadable or invalid one."""
    return read_profile(name_or_path, PROFILE_DIR, CommProfile, ProfileError, what="comm profile",
                        known_as="known profiles")


IDEAL = CommProfile(name="ideal")
FAULT_ENTROPY = 0x6661756C
"""Mixed into the episode seed for the fault stages' streams ("faul"; stages 1-5 use "link")."""
PRINTABLE = "".join(chr(c) for c in range(0x20, 0x7F))
"""What a corrupted character becomes (printable ASCII, space included)."""


@dataclass(frozen=True)
class Delivery:
    delivered: bool
    arrive_s: float | None
    reason: str | None = None
    """Why it was dropped: blackout, out_of_range, nlos, loss, queue_full."""
    duplicate_arrive_s: float | None = None
    """Delivered a second time, arriving then (the ``duplicate`` stage); None: once."""
    corrupt_seed: int | None = None
    """Seed for :func:`corrupt_text` when the ``corruption`` stage is on and it was delivered; None: off."""


@dataclass
class Link:
    """One direction of the channel between the two roles."""

    profile: CommProfile
    rng: np.random.Generator
    fault_rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(FAULT_ENTROPY))
    """The fault stages' own stream (:func:`links_for` derives one per direction from the seed)."""
    _bad: bool = False
    _busy_until_s: float = 0.0
    _queue: list[tuple[float, int]] = field(default_factory=list)
    """(serialization end time, bytes) of messages still in the sender's queue."""

    def transmit(self, t_send: float, size_bytes: int, *, distance_m: float = 0.0, line_of_sight: bool = True) -> Delivery:
        p = self.profile
        # Draw every random number in a fixed order whatever happens, so one message's fate
        # never shifts the stream of the next (bit-identical replays, comparable sweeps).
        u_loss, u_nlos, u_state, z = self.rng.random(), self.rng.random(), self.rng.random(), self.rng.standard_normal()
        # The fault stages' draws come from their own stream, likewise fixed in number, so a
        # profile without faults delivers exactly what it did before they existed.
        u_dup, corrupt_seed = self.fault_rng.random(), int(self.fault_rng.integers(0, 2**63 - 1))
        delivery = self._deliver(t_send, size_bytes, distance_m, line_of_sight, u_loss, u_nlos, u_state, z)
        if not delivery.delivered or delivery.arrive_s is None:
            return delivery
        dup = delivery.arrive_s + p.duplicate.delay_s if u_dup < p.duplicate.p else None
        seed = corrupt_seed if p.corruption.char_error_rate > 0 else None
        if dup is None and seed is None:
            return delivery
        return Delivery(True, delivery.arrive_s, duplicate_arrive_s=dup, corrupt_seed=seed)

    def _deliver(self, t_send: float, size_bytes: int, distance_m: float, line_of_sight: bool,
                 u_loss: float, u_nlos: float, u_state: float, z: float) -> Delivery:
        """Stages 1-5 (the draws made by :meth:`transmit`)."""
        p = self.profile
        lost = self._lost(u_loss, u_state)  # the loss chain steps on every transmission, whatever its fate
        if any(b.start_s <= t_send < b.end_s for b in p.blackouts):
            return Delivery(False, None, "blackout")
        if p.range.max_range_m is not None and distance_m > p.range.max_range_m:
            return Delivery(False, None, "out_of_range")
        if not line_of_sight and u_nlos < p.range.nlos_loss:
            return Delivery(False, None, "nlos")
        if lost:
            return Delivery(False, None, "loss")
        start = t_send
        if p.bandwidth.bits_per_s is not None:
            self._queue = [(end, b) for end, b in self._queue if end > t_send]
            if sum(b for _, b in self._queue) + size_bytes > p.bandwidth.queue_bytes:
                return Delivery(False, None, "queue_full")
            start = max(t_send, self._busy_until_s)
            self._busy_until_s = start + size_bytes * 8 / p.bandwidth.bits_per_s
            self._queue.append((self._busy_until_s, size_bytes))
            start = self._busy_until_s
        return Delivery(True, start + self._delay(z))

    def _lost(self, u_loss: float, u_state: float) -> bool:
        loss = self.profile.loss
        if loss.model == "bernoulli":
            return u_loss < loss.p
        if loss.model == "gilbert_elliott":
            lost = u_loss < (loss.loss_bad if self._bad else loss.loss_good)
            self._bad = (u_state < loss.p_good_to_bad) if not self._bad else not (u_state < loss.p_bad_to_good)
            return lost
        return False

    def _delay(self, z: float) -> float:
        lat = self.profile.latency
        if lat.distribution == "uniform":
            u = 0.5 * (1 + math.erf(z / math.sqrt(2)))  # the normal draw mapped to [0, 1)
            d = lat.mean_s + (2 * u - 1) * lat.jitter_s
        elif lat.distribution == "exponential":
            u = 0.5 * (1 + math.erf(z / math.sqrt(2)))
            d = -lat.mean_s * math.log(max(1e-12, 1 - u))
        elif lat.distribution == "lognormal":
            if lat.mean_s == 0:
                return 0.0
            sigma2 = math.log(1 + (lat.jitter_s / lat.mean_s) ** 2)
            d = math.exp(math.log(lat.mean_s) - sigma2 / 2 + math.sqrt(sigma2) * z)
        else:
            d = lat.mean_s + lat.jitter_s * z
        return max(0.0, d)


def corrupt_text(text: str, char_error_rate: float, seed: int) -> str:
    """``text`` with each character replaced, with probability ``char_error_rate``, by a printable ASCII
    character other than itself (so every hit changes the text). The per-message generator seeded
    by ``seed`` draws two values per character, whatever the rate."""
    if not text:
        return text
    rng = np.random.default_rng(seed)
    hits = rng.random(len(text)) < char_error_rate
    picks = rng.integers(0, len(PRINTABLE) - 1, size=len(text))
    out = list(text)
    for i in np.flatnonzero(hits):
        k = int(picks[i])
        own = PRINTABLE.find(out[i])
        out[i] = PRINTABLE[k + 1 if 0 <= own <= k else k]  # skip the character itself
    return "".join(out)


def links_for(profile: CommProfile, seed: int) -> dict[tuple[str, str], Link]:
    """The two directed links of an episode, with independent seeded streams: one per direction for
    stages 1-5 and one per direction for the fault stages."""
    streams = np.random.SeedSequence([seed, 0x6C696E6B]).spawn(2)
    faults = np.random.SeedSequence([seed, FAULT_ENTROPY]).spawn(2)
    uav, ugv = ROLES
    return {(uav, ugv): Link(profile, np.random.default_rng(streams[0]), np.random.default_rng(faults[0])),
            (ugv, uav): Link(profile, np.random.default_rng(streams[1]), np.random.default_rng(faults[1]))}
