"""The channel between the roles inside one episode: each role's view of the coordination state.

The world holds the truth. Each role holds a :class:`RoleView`: the candidates it knows (with the
most advanced status it has heard of), the messages delivered to it, and its teammate's last
reported pose with the time that report was made. Knowledge travels only through the seeded
link models (:mod:`agos.runtime.links`):

* after every decision a role sends a ``sync`` with its knowledge (candidates, own pose);
* on a degraded link each role also re-broadcasts a ``beacon`` every ``beacon_s`` of sim time,
  so a lost handoff is eventually repaired (a frozen UAV keeps beaconing);
* agent text goes as a ``message`` once; lost is lost.

Every transmission is written to the ledger. The link's message faults (docs/COMMS.md, "Message
faults") show there too:

* a duplicated transmission is delivered twice; the copy is a ledger entry of its own right after
  the original's (its own ``seq``, the same kind, sender, send time and size, ``fault =
  "duplicate"``), arriving ``duplicate.delay_s`` after it and carrying what the original delivered
  (a corrupted text stays corrupted). A duplicated sync or beacon merges idempotently; a duplicated
  message reaches the receiver's message list twice.
* a corrupted ``message`` arrives with some characters of its text replaced, its entry marked
  ``fault = "corrupted"`` (only when a character actually changed). Syncs and beacons are never
  corrupted: they are structured binary payloads, and a corrupted frame would fail its checksum
  and be dropped, which the loss stage already models.
"""

from __future__ import annotations

import copy
import heapq
from dataclasses import dataclass, field
from typing import Any, Literal

from agos.runtime.codec import encode
from agos.runtime.keys import ROLES
from agos.runtime.links import CommProfile, Delivery, corrupt_text, links_for
from agos.runtime.schemas import Candidate, LedgerEntry, LinkStats, MessageRecord, Pose, Role

TransmissionKind = Literal["sync", "beacon", "message"]
"""What a transmission carries (the ledger's ``kind``)."""

STATUS_RANK = {"pending": 0, "arrived": 1, "rejected": 2, "confirmed": 2, "false_confirm": 2}
MESSAGE_OVERHEAD_BYTES = 64


def sync_payload(candidates: list[Candidate], pose: Pose, t: float) -> dict[str, Any]:
    """What a sync or beacon carries: the sender's candidates, its pose, when it was sent."""
    return {"candidates": candidates, "pose": pose, "t": t}


EMPTY_SYNC_BYTES = len(encode(sync_payload([], Pose(position_world_m=(0.0, 0.0, 0.0), yaw_rad=0.0), 0.0)))
"""The size of every sync or beacon that carries no candidate (msgpack floats are fixed-width), so a
ledger reader can tell which transmissions carried one (``agos sweep``'s handoff delay)."""


@dataclass
class RoleView:
    candidates: dict[str, Candidate] = field(default_factory=dict)
    messages: list[MessageRecord] = field(default_factory=list)
    teammate_pose: Pose | None = None
    teammate_info_s: float | None = None
    """Sim time at which the teammate sent the newest information this role has."""

    def merge(self, candidates: list[Candidate]) -> bool:
        """Adopt newer candidate knowledge; True if anything changed."""
        changed = False
        for cand in candidates:
            mine = self.candidates.get(cand.candidate_id)
            if mine is None or STATUS_RANK[cand.status] > STATUS_RANK[mine.status]:
                self.candidates[cand.candidate_id] = copy.copy(cand)
                changed = True
        return changed

    def receive_sync(self, payload: dict[str, Any]) -> bool:
        """Adopt a sync or beacon (:func:`sync_payload`): merge its candidates and keep the teammate pose
        with the newest send time. Idempotent, and the result does not depend on the order in which a
        set of syncs arrives (duplicates included); True if a candidate changed."""
        changed = self.merge(payload["candidates"])
        if self.teammate_info_s is None or payload["t"] >= self.teammate_info_s:
            self.teammate_pose, self.teammate_info_s = payload["pose"], payload["t"]
        return changed

    def active_candidate(self) -> Candidate | None:
        return next((c for _, c in sorted(self.candidates.items()) if c.status in ("pending", "arrived")), None)


@dataclass(order=True)
class _Pending:
    arrive_s: float
    seq: int
    receiver: Role = field(compare=False)
    kind: TransmissionKind = field(compare=False)
    payload: dict[str, Any] = field(compare=False)


@dataclass
class Arrival:
    receiver: Role
    kind: TransmissionKind
    changed: bool
    """The receiver's knowledge changed (new candidate, status, or a message)."""
    message: MessageRecord | None = None


class Channel:
    def __init__(self, profile: CommProfile, seed: int, start_poses: dict[Role, Pose]) -> None:
        self.profile = profile
        self.links = links_for(profile, seed)
        self.views: dict[Role, RoleView] = {"uav": RoleView(), "ugv": RoleView()}
        # The paper's initial communication: both start knowing where the other is.
        for role, other in (ROLES, ROLES[::-1]):
            self.views[role].teammate_pose = start_poses[other]
            self.views[role].teammate_info_s = 0.0
        self.ledger: list[LedgerEntry] = []
        self._pending: list[_Pending] = []
        self._seq = 0
        beacons = not profile.ideal
        self.next_beacon: dict[Role, float] = {r: (profile.beacon_s if beacons else float("inf")) for r in ROLES}
        self._ages: dict[Role, list[float]] = {"uav": [], "ugv": []}

    # ----- sending ------------------------------------------------------------------------------
    def _send(self, sender: Role, kind: TransmissionKind, t: float, payload: dict[str, Any], size: int,
              geometry: tuple[float, bool]) -> Delivery:
        receiver: Role = "ugv" if sender == "uav" else "uav"
        distance, los = geometry
        d = self.links[(sender, receiver)].transmit(t, size, distance_m=distance, line_of_sight=los)
        fault: Literal["corrupted"] | None = None
        if kind == "message" and d.delivered and d.corrupt_seed is not None:  # text only (module docstring)
            text = corrupt_text(payload["text"], self.profile.corruption.char_error_rate, d.corrupt_seed)
            if text != payload["text"]:
                payload, fault = {**payload, "text": text}, "corrupted"
        self._seq += 1
        self.ledger.append(LedgerEntry(
            seq=self._seq, kind=kind, sender=sender, receiver=receiver, sent_s=round(t, 4), size_bytes=size,
            delivered=d.delivered, arrive_s=None if d.arrive_s is None else round(d.arrive_s, 4),
            delay_s=None if d.arrive_s is None else round(d.arrive_s - t, 4), drop_reason=d.reason, fault=fault))
        if d.delivered and d.arrive_s is not None:  # a delivered transmission always has its arrival time
            heapq.heappush(self._pending, _Pending(d.arrive_s, self._seq, receiver, kind, payload))
            if d.duplicate_arrive_s is not None:  # the copy: its own entry, right after the original's
                self._seq += 1
                self.ledger.append(LedgerEntry(
                    seq=self._seq, kind=kind, sender=sender, receiver=receiver, sent_s=round(t, 4), size_bytes=size,
                    delivered=True, arrive_s=round(d.duplicate_arrive_s, 4),
                    delay_s=round(d.duplicate_arrive_s - t, 4), fault="duplicate"))
                heapq.heappush(self._pending, _Pending(d.duplicate_arrive_s, self._seq, receiver, kind, payload))
        return d

    def sync(self, sender: Role, t: float, pose: Pose, geometry: tuple[float, bool], *,
             kind: TransmissionKind = "sync") -> None:
        """Send the sender's knowledge (its candidates and its pose) to the teammate."""
        cands = [copy.copy(c) for _, c in sorted(self.views[sender].candidates.items())]
        payload = sync_payload(cands, pose, t)
        size = len(encode(payload))
        self._send(sender, kind, t, payload, size, geometry)

    def message(self, sender: Role, t: float, text: str, geometry: tuple[float, bool]) -> None:
        self._send(sender, "message", t, {"text": text, "t": t}, len(text.encode()) + MESSAGE_OVERHEAD_BYTES, geometry)

    # ----- time -----------------------------------------------------------------------------------
    def next_arrival_s(self) -> float:
        return self._pending[0].arrive_s if self._pending else float("inf")

    def next_beacon_s(self) -> float:
        return min(self.next_beacon.values())

    def deliver_until(self, t: float) -> list[Arrival]:
        arrivals = []
        while self._pending and self._pending[0].arrive_s <= t + 1e-9:
            item = heapq.heappop(self._pending)
            view = self.views[item.receiver]
            sender: Role = "uav" if item.receiver == "ugv" else "ugv"
            if item.kind == "message":
                record = MessageRecord(sender=sender, receiver=item.receiver, text=item.payload["text"][:500],
                                       sent_sim_time_s=item.payload["t"], delivered_sim_time_s=round(item.arrive_s, 4))
                view.messages.append(record)
                arrivals.append(Arrival(item.receiver, "message", True, record))
                continue
            changed = view.receive_sync(item.payload)
            arrivals.append(Arrival(item.receiver, item.kind, changed))
        return arrivals

    def info_age(self, role: Role, t: float) -> float | None:
        """Age of the teammate information in ``role``'s view at time ``t`` (recorded)."""
        info = self.views[role].teammate_info_s
        age = None if info is None else round(t - info, 4)
        if age is not None:
            self._ages[role].append(age)
        return age

    # ----- summary ------------------------------------------------------------------------------
    def stats(self, truth_candidates: list[Candidate]) -> LinkStats:
        """The ledger summed up. Duplicate copies are counted in ``duplicated`` only: ``sent``,
        ``delivered``, the delays and ``bytes_sent`` are about the transmissions the roles made."""
        made = [e for e in self.ledger if e.fault != "duplicate"]
        sent = len(made)
        delivered = [e for e in made if e.delivered]
        dropped: dict[str, int] = {}
        for e in made:
            if not e.delivered:
                dropped[e.drop_reason or "unknown"] = dropped.get(e.drop_reason or "unknown", 0) + 1
        delays = [e.delay_s for e in delivered if e.delay_s is not None]
        known = set(self.views["ugv"].candidates)
        return LinkStats(
            profile=self.profile.name, sent=sent, delivered=len(delivered), dropped=dict(sorted(dropped.items())),
            delivery_rate=round(len(delivered) / sent, 4) if sent else None,
            mean_delay_s=round(sum(delays) / len(delays), 4) if delays else None,
            max_delay_s=round(max(delays), 4) if delays else None,
            bytes_sent=sum(e.size_bytes for e in made),
            mean_info_age_s={r: round(sum(a) / len(a), 3) if a else None for r, a in self._ages.items()},
            candidates_delivered=sum(c.candidate_id in known for c in truth_candidates),
            candidates_lost=sum(c.candidate_id not in known for c in truth_candidates),
            duplicated=sum(e.fault == "duplicate" for e in self.ledger),
            corrupted=sum(e.fault == "corrupted" for e in self.ledger))
