"""The decision board: the decisions asked of a person, and the one place their answers are taken.

Contract. The agent service puts each observation on the board (:meth:`DecisionBoard.ask`) and
awaits the future it gets; the page's requests (web server threads) read :meth:`snapshot` and
answer with :meth:`submit`. Under one lock, a submission is accepted only when it answers a
decision that is still asked (same episode, attempt, role and decision index) and is legal by the
same rules the VLM policies' replies are checked with (agents/vlm/parse.py: a legal action, an
offered waypoint, a cell A1-E5, an active candidate), with a message of at most
``MESSAGE_LIMIT`` characters. Each decision is resolved once: a second submission (a double
click, a second browser window) is refused as already sent, one for a decision the world no
longer asks (it timed out into a WAIT, the episode ended, the page was stale) is refused as
stale, an illegal one is refused with the reason while the decision stays open. Every refusal
is a message for the page, never an exception.

An accepted decision carries a :class:`~agos.runtime.schemas.DecisionTrace` like a model's (the
world stores it with the episode): ``policy`` ``human``, ``model`` the player's name, ``stage``
the observation's mode, ``prompt_sha256`` the hash of what the page showed, ``image_bytes`` the
images shown, ``raw_reply`` the page's submission, ``latency_s`` the seconds from the
observation's arrival to the answer, ``http_attempts`` the submissions made for it and ``reasks``
those refused. With ``trace_file`` each decision is also appended there as a JSON line with the
facts shown.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future, InvalidStateError
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, NamedTuple

from agos.agents.human.page_model import Shown, active_candidates, shown
from agos.agents.vlm.parse import to_action
from agos.runtime.schemas import Action, DecisionTrace, Observation, Role

MESSAGE_LIMIT = 200
"""Characters of a message to the teammate (the VLM reply schema's limit)."""
IMAGES_KEPT = 400
"""Images the board keeps for the page (those of the latest decisions)."""
HISTORY_KEPT = 40
DECIDED_KEPT = 5000
"""Decided keys remembered, to answer a repeated observation and a repeated submission."""

log = logging.getLogger("agos.human")

Key = tuple[str, int, str, int]
"""(episode, attempt, role, decision index)."""


class Verdict(NamedTuple):
    """What the page is told about a submission."""

    ok: bool
    status: int
    """HTTP status: 200 accepted, 400 malformed, 409 already sent or stale, 422 not legal."""
    message: str


class Asked(NamedTuple):
    """What :meth:`DecisionBoard.ask` found: a ``new`` decision (await ``future``), one already
    ``pending`` (a repeated observation: nothing to do), or one ``decided`` (send ``action`` again)."""

    kind: str
    future: Future[Action] | None = None
    action: Action | None = None


@dataclass
class _Pending:
    obs: Observation
    shown: Shown
    future: Future[Action]
    received_s: float
    first_shown_s: float | None = None
    submissions: int = 0
    refusals: list[str] = field(default_factory=list)


def _key(obs: Observation) -> Key:
    return (obs.episode_id, obs.attempt, obs.role, obs.decision_index)


def describe(action: Action) -> str:
    """``MOVE_TO_UAV_WAYPOINT u_3_4``, ``ANNOTATE_CANDIDATE C3`` ..."""
    arg = action.waypoint_id or action.cell or action.candidate_id
    return action.action + (f" {arg}" if arg else "")


class PageBoard:
    """What the console's server (server.py) serves a page from: the state as JSON, a ``version``
    bumped on every change, and the latest ``images_kept`` images by digest; one condition guards it
    all. The decision board (play) and the spectator's (read-only) say what :meth:`snapshot` holds
    and what :meth:`submit` takes."""

    def __init__(self, images_kept: int) -> None:
        self._cond = threading.Condition()
        self.version = 0
        self._images: OrderedDict[str, tuple[bytes, str]] = OrderedDict()
        self._images_kept = images_kept

    def snapshot(self) -> dict[str, Any]:
        raise NotImplementedError

    def submit(self, body: Any) -> Verdict:
        raise NotImplementedError

    def snapshot_json(self) -> str:
        """:meth:`snapshot` as JSON, made under the lock (nothing changes while it is written)."""
        with self._cond:
            return json.dumps(self.snapshot(), separators=(",", ":"))

    def image(self, digest: str) -> tuple[bytes, str] | None:
        with self._cond:
            return self._images.get(digest)

    def wait_change(self, version: int, timeout_s: float) -> int:
        """Block until the board differs from ``version`` or ``timeout_s`` passes; the version now."""
        with self._cond:
            self._cond.wait_for(lambda: self.version != version, timeout=timeout_s)
            return self.version

    def _changed(self) -> None:
        """Under the lock: a new version, and every page waiting is woken."""
        self.version += 1
        self._cond.notify_all()

    def _keep_image(self, digest: str, data: bytes, mime: str) -> None:
        """Under the lock: keep an image, dropping the least recently kept beyond ``images_kept``."""
        self._images[digest] = (data, mime)
        self._images.move_to_end(digest)
        while len(self._images) > self._images_kept:
            self._images.popitem(last=False)


class DecisionBoard(PageBoard):
    def __init__(self, roles: Iterable[Role], *, player: str = "person", trace_file: Path | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(IMAGES_KEPT)
        self.roles: tuple[Role, ...] = tuple(roles)
        self.player, self.trace_file, self._clock = player, trace_file, clock
        self._pending: dict[Key, _Pending] = {}
        self._decided: OrderedDict[Key, Action] = OrderedDict()
        self._last: dict[str, dict[str, Any]] = {}  # role -> the latest view shown, for when nothing is asked
        self.history: deque[dict[str, Any]] = deque(maxlen=HISTORY_KEPT)
        self.notices: deque[dict[str, Any]] = deque(maxlen=HISTORY_KEPT)

    # ----- the agent service's side ---------------------------------------------------------------
    def ask(self, obs: Observation) -> Asked:
        """Put ``obs`` before the person. Decisions of the same episode and role that the world asked
        earlier are over (it moved on after its decision timeout): their futures are cancelled."""
        key = _key(obs)
        with self._cond:
            if key in self._decided:
                return Asked("decided", action=self._decided[key])
            if key in self._pending:
                return Asked("pending")
            for other, p in list(self._pending.items()):
                if other[0] == key[0] and other[2] == key[2] and (other[1], other[3]) < (key[1], key[3]):
                    self._close(other, p, f"{other[2].upper()} decision {other[3]} of {other[0]} is over: the world did "
                                          f"not get an answer within its {p.obs.decision_timeout_s or 0:.0f} s timeout "
                                          "and applied WAIT")
                elif other[0] == key[0] and other[2] == key[2]:
                    return Asked("pending")  # an older decision arriving late: the newer one stands
            view = shown(obs)
            for image in view.images:
                self._keep_image(image.digest, image.data, image.mime)
            future: Future[Action] = Future()
            self._pending[key] = _Pending(obs, view, future, self._clock())
            self._changed()
            return Asked("new", future=future)

    def forget(self, episode_id: str, role: Role | None = None) -> None:
        """No world runs the episode any more: what it still asked (of ``role``, or of every role) is
        dropped and the page says so."""
        with self._cond:
            for key, p in list(self._pending.items()):
                if key[0] == episode_id and role in (None, key[2]):
                    self._close(key, p, f"{episode_id} ended before {key[2].upper()} decision {key[3]} was answered")
            for r in self.roles if role is None else (role,):
                last = self._last.get(r)
                if last is not None and last["state"]["episode_id"] == episode_id and not last.get("over"):
                    last["over"] = True
                    self._notice("info", f"{episode_id} is over for the {r.upper()}")
            self._changed()

    def _close(self, key: Key, p: _Pending, why: str) -> None:
        p.future.cancel()
        del self._pending[key]
        self.history.append({"role": key[2], "episode_id": key[0], "decision_index": key[3], "action": None,
                             "outcome": "not answered", "waited_s": round(self._clock() - p.received_s, 1)})
        self._notice("warning", why)

    # ----- the page's side ------------------------------------------------------------------------
    def submit(self, body: Any) -> Verdict:
        """One submission from the page (see the module docstring for what is accepted)."""
        if not isinstance(body, dict):
            return Verdict(False, 400, "Malformed request: expected a JSON object.")
        role = body.get("role")
        if role not in self.roles:
            plays = " and ".join(r.upper() for r in self.roles)
            return Verdict(False, 400, f"This console plays the {plays}; it cannot decide for {role!r}.")
        index, attempt, episode = body.get("decision_index"), body.get("attempt", 1), body.get("episode_id")
        if not isinstance(index, int) or not isinstance(attempt, int) or not isinstance(episode, str):
            return Verdict(False, 400, "Malformed request: episode_id, attempt and decision_index are required.")
        key: Key = (episode, attempt, role, index)
        with self._cond:
            p = self._pending.get(key)
            if p is None:
                return self._not_pending(key)
            p.submissions += 1
            message = body.get("message")
            if message is not None and not isinstance(message, str):
                return self._refuse(p, "the message must be text")
            message = (message or "").strip() or None
            if message is not None and len(message) > MESSAGE_LIMIT:
                return self._refuse(p, f"the message has {len(message)} characters; at most {MESSAGE_LIMIT}")
            reply = {k: body[k] for k in ("action", "waypoint_id", "cell", "candidate_id") if body.get(k) is not None}
            reply["message"] = message
            parsed = to_action(json.dumps(reply), p.obs)
            if parsed.fallback:
                return self._refuse(p, _explained(parsed.reason or "not a decision", p.obs))
            action = parsed.action
            now = self._clock()
            raw = json.dumps({**reply, "input": str(body.get("input", ""))[:20],
                              "shown_after_s": None if p.first_shown_s is None else round(p.first_shown_s - p.received_s, 3)})
            action.rationale = f"human ({self.player})"
            action.trace = DecisionTrace(
                policy="human", model=self.player, stage=p.obs.mode, prompt_sha256=p.shown.sha256,
                image_bytes={i.label: len(i.data) for i in p.shown.images}, raw_reply=raw[:2000],
                parsed_action=action.action, fallback=False, reasks=len(p.refusals), http_attempts=p.submissions,
                latency_s=round(now - p.received_s, 3))
            try:
                p.future.set_result(action)
            except InvalidStateError:  # cancelled a moment ago: the world moved on
                return self._not_pending(key)
            del self._pending[key]
            self._decided[key] = action
            while len(self._decided) > DECIDED_KEPT:
                self._decided.popitem(last=False)
            self.history.append({"role": role, "episode_id": episode, "decision_index": index, "action": describe(action),
                                 "message": message, "outcome": "sent", "waited_s": round(now - p.received_s, 1)})
            self._last[role] = {**self._view(p, now), "decided": describe(action)}
            self._write_trace(p, action)
            self._changed()
            return Verdict(True, 200, f"Sent: {role.upper()} decision {index}, {describe(action)} "
                                      f"(after {now - p.received_s:.1f} s).")

    def _not_pending(self, key: Key) -> Verdict:
        episode, _, role, index = key
        if key in self._decided:
            return Verdict(False, 409, f"{role.upper()} decision {index} was already sent ({describe(self._decided[key])}); "
                                       "this repeated submission was ignored.")
        now_asked = [k[3] for k in self._pending if k[2] == role and k[0] == episode]
        if now_asked:
            return Verdict(False, 409, f"Stale: {role.upper()} decision {index} is no longer asked; decision "
                                       f"{now_asked[0]} is (the page shows it now). Nothing was sent.")
        return Verdict(False, 409, f"Stale: {role.upper()} decision {index} of {episode} is no longer asked (the world "
                                   "moved on or the episode ended). Nothing was sent.")

    def _refuse(self, p: _Pending, reason: str) -> Verdict:
        p.refusals.append(reason)
        self._changed()
        return Verdict(False, 422, f"Not sent: {reason}. {p.obs.role.upper()} decision {p.obs.decision_index} is "
                                   "still yours.")

    def snapshot(self) -> dict[str, Any]:
        """The page's state: per role the decision asked (the oldest, if several episodes ask at
        once) or the last one shown, the history and notices. Marks the decisions it shows as seen."""
        with self._cond:
            now = self._clock()
            roles: dict[str, Any] = {}
            for role in self.roles:
                asked = sorted((p for k, p in self._pending.items() if k[2] == role), key=lambda p: p.received_s)
                if asked:
                    p = asked[0]
                    if p.first_shown_s is None:
                        p.first_shown_s = now
                    view = self._view(p, now)
                    self._last[role] = view
                    roles[role] = {"asked": view, "queued": len(asked) - 1}
                else:
                    roles[role] = {"asked": None, "queued": 0, "last": self._last.get(role)}
            return {"mode": "play", "player": self.player, "roles": list(self.roles), "version": self.version,
                    "by_role": roles, "history": list(self.history)[::-1], "notices": list(self.notices)[::-1]}

    def _view(self, p: _Pending, now: float) -> dict[str, Any]:
        return {"state": p.shown.state, "choices": p.shown.choices, "waited_s": round(now - p.received_s, 2),
                "refusals": len(p.refusals),
                "images": [{"label": i.label, "caption": i.caption, "url": f"/img/{i.digest}"} for i in p.shown.images]}

    def _notice(self, level: str, text: str) -> None:
        self.notices.append({"level": level, "text": text, "utc": datetime.now(UTC).isoformat(timespec="seconds")})

    def _write_trace(self, p: _Pending, action: Action) -> None:
        if self.trace_file is None:
            return
        line = {"utc": datetime.now(UTC).isoformat(timespec="seconds"), "run_id": p.obs.run_id,
                "episode_id": p.obs.episode_id, "attempt": p.obs.attempt, "role": p.obs.role,
                "decision_index": p.obs.decision_index, "player": self.player, "shown": p.shown.state,
                "images": {i.label: {"bytes": len(i.data), "sha256_16": i.digest} for i in p.shown.images},
                "chosen": {"action": action.action, "waypoint_id": action.waypoint_id, "cell": action.cell,
                           "candidate_id": action.candidate_id, "message": action.message},
                "latency_s": action.trace.latency_s if action.trace else None, "refused": p.refusals}
        try:
            with self.trace_file.open("a") as f:
                f.write(json.dumps(line) + "\n")
        except OSError as exc:  # the record keeps the trace either way
            log.warning("could not append to %s: %s", self.trace_file, exc)


def _explained(reason: str, obs: Observation) -> str:
    """The parser's reason, with what would have been accepted instead."""
    if reason.startswith("waypoint"):
        return f"{reason} (options now: {', '.join(w.waypoint_id for w in obs.waypoint_options) or 'none'})"
    if reason.startswith("candidate"):
        return f"{reason} (active now: {', '.join(active_candidates(obs)) or 'none'})"
    if reason.startswith("cell"):
        return f"{reason} (rows {obs.grid_rows}, columns 1-{obs.grid_cols})"
    return f"{reason} (legal now: {', '.join(obs.legal_actions)})"
