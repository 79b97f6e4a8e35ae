"""The spectator's board: the console page, read-only, fed by the visualisation stream.

Contract: :meth:`SpectatorBoard.take` is handed every sample an observer reads (runtime/observer.py:
only ``agos/<run>/viz/**``, what the ``observer`` identity of a secured bus may hear) and keeps,
per episode, what a viewer needs: the episode's start, its region when the world sends its spec,
the latest thumbnails of each role's views, the applied decisions and both trajectories (from
the step events), the coordination truth (candidates, messages, budget) and the outcome when the
world sends the record. Keys name world workers (``viz/<worker>/...``), not episodes, and one
worker's keys carry its episodes one after the other: a sample goes to the episode its payload names
(``run_id`` or the key's run, ``episode_id``), never to one read off the key. It never publishes
anything; :meth:`submit` refuses every action. The target's ground-truth position is not passed to
the page: what a spectator sees can be shown without giving the search away.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict, deque
from typing import Any

from agos.agents.human.board import PageBoard, Verdict
from agos.runtime import keys
from agos.runtime.codec import DecodeError, decode
from agos.runtime.schemas import (
    CoordinationState,
    EpisodeRecord,
    EpisodeSpec,
    EpisodeStarted,
    StepEvent,
    VizFrame,
)

EPISODES_KEPT = 12
STEPS_KEPT = 40
IMAGES_KEPT = 300
TRAJECTORY_KEPT = 400


class SpectatorBoard(PageBoard):
    def __init__(self, run_id: str | None = None) -> None:
        """``run_id``: shown on the page (the observer decides which runs are heard)."""
        super().__init__(IMAGES_KEPT)
        self.run_id = run_id
        self._episodes: OrderedDict[tuple[str, str], dict[str, Any]] = OrderedDict()
        self.unreadable = 0

    def take(self, key: str, payload: bytes) -> None:
        """One sample of the visualisation stream (the observer's thread); samples of runs other than
        ``run_id`` (when given) are ignored."""
        if self.run_id is not None and self._run_of(key) != self.run_id:
            return
        try:
            message = decode(payload)
        except DecodeError:
            self.unreadable += 1
            return
        with self._cond:
            if isinstance(message, EpisodeStarted):
                ep = self._episode(message.run_id, message.episode_id)
                ep.update(difficulty=message.difficulty, town_id=message.town_id, worker_id=message.worker_id)
            elif isinstance(message, EpisodeSpec):
                ep = self._episode(self._run_of(key), message.episode_id)
                ep.update(difficulty=message.difficulty, town_id=message.town.town_id,
                          region_m=[round(v, 1) for v in message.region_world_m])
            elif isinstance(message, StepEvent):
                self._step(message)
            elif isinstance(message, CoordinationState):
                ep = self._episode(message.run_id, message.episode_id)
                ep.update(sim_time_s=round(message.sim_time_s, 1),
                          budget={"used": message.decisions_used, "total": message.decision_budget},
                          candidates=[{"id": c.candidate_id, "cell": c.cell, "status": c.status,
                                       "center_m": [round(v, 1) for v in c.center_world_m],
                                       "polygon_m": [[round(x, 1), round(y, 1)] for x, y in c.polygon_world_m]}
                                      for c in message.candidates],
                          messages=[{"from": m.sender, "to": m.receiver, "text": m.text,
                                     "delivered_s": round(m.delivered_sim_time_s, 1)} for m in message.messages])
            elif isinstance(message, VizFrame):
                self._frame(message)
            elif isinstance(message, EpisodeRecord):
                ep = self._episode(message.run_id, message.episode_id)
                ep["outcome"] = {"termination": message.termination, "success": message.success,
                                 "decisions": message.decisions_uav + message.decisions_ugv,
                                 "final_distance_m": round(message.final_distance_m, 1)}
            else:
                return
            self._changed()

    @staticmethod
    def _run_of(key: str) -> str:
        try:
            return keys.run_of(key)
        except ValueError:
            return ""

    def _episode(self, run_id: str, episode_id: str) -> dict[str, Any]:
        key = (run_id, episode_id)
        ep = self._episodes.get(key)
        if ep is None:
            ep = self._episodes[key] = {"run_id": run_id, "episode_id": episode_id, "steps": deque(maxlen=STEPS_KEPT),
                                        "paths": {"uav": [], "ugv": []}, "frames": {}, "candidates": [],
                                        "messages": [], "budget": None, "outcome": None, "region_m": None}
            while len(self._episodes) > EPISODES_KEPT:
                self._episodes.popitem(last=False)
        self._episodes.move_to_end(key)
        return ep

    def _step(self, event: StepEvent) -> None:
        ep = self._episode(event.run_id, event.episode_id)
        requested = event.requested
        arg = None if requested is None else (requested.waypoint_id or requested.cell or requested.candidate_id)
        ep["steps"].append({"role": event.role, "decision_index": event.decision_index, "applied": event.applied,
                            "argument": arg, "message": None if requested is None else requested.message,
                            "fallback_reason": event.fallback_reason, "sim_time_s": round(event.sim_time_s, 1)})
        path = ep["paths"][event.role]
        path.append([round(event.pose_after.position_world_m[0], 1), round(event.pose_after.position_world_m[1], 1)])
        del path[:-TRAJECTORY_KEPT]
        ep["sim_time_s"] = round(event.sim_time_s, 1)

    def _frame(self, frame: VizFrame) -> None:
        ep = self._episode(frame.run_id, frame.episode_id)
        digest = hashlib.sha256(frame.image.data).hexdigest()[:16]
        self._keep_image(digest, frame.image.data, "image/jpeg" if frame.image.encoding == "jpeg" else "image/png")
        seen = ep["frames"].get(frame.role)
        if seen is None or seen["decision_index"] != frame.decision_index:
            seen = ep["frames"][frame.role] = {"decision_index": frame.decision_index, "views": {}}
        seen["sim_time_s"] = round(frame.sim_time_s, 1)
        seen["views"][frame.image.name] = f"/img/{digest}"

    def snapshot(self) -> dict[str, Any]:
        with self._cond:
            episodes = [{**ep, "steps": list(ep["steps"])[::-1]} for ep in reversed(self._episodes.values())]
            return {"mode": "spectate", "run_id": self.run_id, "version": self.version, "episodes": episodes}

    def submit(self, body: Any) -> Verdict:
        return Verdict(False, 403, "This is a read-only spectator view: it cannot decide.")
