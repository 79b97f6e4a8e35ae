"""One episode as a rerun recording (``agos record``): what the visualisation stream said about it.

Contract: :class:`EpisodeRecording` turns the visualisation messages of one episode
(runtime/viz.py: its spec, step events, coordination truths, frames and, at the end, its record)
into rerun entities on two timelines, and writes them to ``<dir>/<episode>.rrd`` as they arrive.
It is called from the recorder's own thread, never from a zenoh callback. The stream is lossy:
what was dropped is missing from the file (counted in the outcome), except the trajectories and
the candidates' polygons, which come from the record's step log when the record arrives.

Timelines: ``sim_time`` (simulated seconds, a duration) and ``decision`` (the episode's shared
decision count, 1 to the budget: both roles on one timeline). A frame is logged at the decision it
was shown for; the map's paths at the decision that ended there.

Entities (rerun's 2D spaces; the map's coordinates are pixels of the map image, north up,
``MAP_PX`` pixels over the region plus a margin; the map's metres per pixel are in its label):

    map                         the town around the episode region from above (static)
    map/region                  the episode region (static)
    map/search_area             the UAV's active waypoints (static)
    map/target                  the target, ground truth (static; never shown to agents)
    map/uav/path, map/ugv/path  the trajectories so far; map/<role>/position: where it is
    map/candidates/<id>         each candidate's polygon, coloured by status
    uav/nadir                   the UAV's nadir view; uav/nadir/grid, uav/nadir/cells: the A1-E5 grid;
                                uav/nadir/annotated: the cell of an ANNOTATE_CANDIDATE
    ugv/forward                 the UGV's forward view while driving
    ugv/six/<view>              the six views of each STOP_OBSERVE (front_left ... back_right)
    log/steps, log/messages, log/link, log/candidates   text logs (link: every transmission, drops as warnings)
    outcome                     the final outcome (markdown), with what the recorder saw and lost
"""

from __future__ import annotations

import bisect
import io
import logging
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import rerun as rr
import rerun.blueprint as rrb
from PIL import Image

from agos.deploy.reports.episode_map import EpisodeMap, MapFrame
from agos.runtime.camera import GRID_COLS, GRID_ROWS, parse_cell
from agos.runtime.schemas import (
    CoordinationState,
    EpisodeRecord,
    EpisodeSpec,
    EpisodeStarted,
    LoggedStep,
    Role,
    StepEvent,
    VizFrame,
)

log = logging.getLogger("agos.record")
MAP_PX = 768
"""Side of the map image."""
SIX_VIEWS = ("front_left", "front", "front_right", "back_left", "back", "back_right")
ROLE_COLOURS = {"uav": (0, 170, 230), "ugv": (220, 40, 200)}
STATUS_COLOURS = {"pending": (255, 190, 0), "arrived": (255, 120, 0), "rejected": (120, 120, 120),
                  "confirmed": (0, 200, 60), "false_confirm": (230, 0, 0)}
TARGET_COLOUR = (255, 0, 0)


@dataclass
class Seen:
    """What the recorder received of one episode (the stream is lossy)."""

    steps: int = 0
    frames: Counter[str] = field(default_factory=Counter)
    """Role -> frames (one per view) logged."""
    coords: int = 0
    dropped_before: int = 0
    """Samples of this episode the recorder's own queue had to drop (set by the recorder)."""


class EpisodeRecording:
    """One episode's ``.rrd``: call the methods as the stream's messages arrive, then :meth:`close`."""

    def __init__(self, out_dir: Path, run_id: str, episode_id: str, *, full: bool,
                 map_source: Callable[[EpisodeSpec], EpisodeMap] | None = None) -> None:
        """``map_source``: the episode's map from its spec (deploy/reports/episode_map.py); None: no town drawn."""
        self.path = out_dir / f"{episode_id}.rrd"
        self.run_id, self.episode_id, self.full = run_id, episode_id, full
        self.map_source = map_source
        self.rec = rr.RecordingStream("agos", recording_id=f"{run_id}/{episode_id}")
        self.rec.set_log_time_enabled(False)  # the timelines are the simulation's, not the recorder's clock
        self.rec.set_log_tick_enabled(False)
        self.rec.save(self.path, default_blueprint=_blueprint())
        self.rec.send_recording_name(episode_id)
        self.seen = Seen()
        self.map: MapFrame | None = None
        self.starts: dict[Role, tuple[float, float]] = {}
        self.step_of: dict[tuple[str, int], tuple[float, int]] = {}
        """(role, role's decision index) -> (sim time, episode step) of the applied decision."""
        self.step_times: list[float] = []
        """Sim time of episode step k + 1 (non-decreasing): which decision a moment belongs to."""
        self.pending: dict[tuple[str, int], list[VizFrame]] = {}
        """Frames whose decision's step event has not arrived yet."""
        self.live_paths: dict[Role, list[tuple[float, float]]] = {"uav": [], "ugv": []}
        self.candidates: dict[str, str] = {}
        """Candidate id -> last status logged."""
        self.messages_seen: set[tuple[str, float, str]] = set()
        self.grid_sizes: set[tuple[int, int]] = set()
        self.annotated_shown = False
        self.record: EpisodeRecord | None = None

    # ----- the stream's messages --------------------------------------------------------------
    def started(self, msg: EpisodeStarted) -> None:
        self._at(0.0, 0)
        if self.seen.steps:  # another attempt (the world of the last one died): the same timeline again
            self.step_of.clear()
            self.step_times.clear()
            self.pending.clear()
            self.live_paths = {"uav": [], "ugv": []}
            self.candidates.clear()
            self.rec.log("log/steps", rr.TextLog("the episode starts again (a new attempt): what follows on this "
                                                 "timeline overlays the earlier attempt", level="WARN"))
        self.rec.log("log/steps", rr.TextLog(
            f"episode {msg.episode_id} ({msg.difficulty}) starts on {msg.worker_id}, town {msg.town_id}", level="INFO"))

    def episode_spec(self, spec: EpisodeSpec) -> None:
        """The episode spec (once, at the start): the map, region, searchable area and target."""
        made = self.map_source(spec) if self.map_source is not None else None
        m = self.map = made.frame if made is not None else MapFrame.around(spec.region_world_m, MAP_PX)
        if made is not None:
            self.starts = dict(made.starts_world_m)
            if made.rgb is not None:
                ok, png = cv2.imencode(".png", cv2.cvtColor(made.rgb, cv2.COLOR_RGB2BGR))
                if ok:
                    self.rec.log("map", rr.EncodedImage(contents=png.tobytes(), media_type="image/png",
                                                        draw_order=-10.0), static=True)
            if made.search_area_world_m:
                self.rec.log("map/search_area", rr.Points2D(m.px(made.search_area_world_m), radii=2.0,
                                                            colors=(40, 40, 40)), static=True)
        x0, y0, x1, y1 = spec.region_world_m
        corners = m.px([(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)])
        self.rec.log("map/region", rr.LineStrips2D([corners], colors=(30, 30, 200), radii=1.0,
                                                   labels=[f"episode region ({x1 - x0:.0f} x {y1 - y0:.0f} m; map "
                                                           f"{1 / m.px_per_m:.2f} m/px)"]), static=True)
        t = spec.target
        self.rec.log("map/target", rr.Points2D(m.px(t.position_world_m[:2]), radii=6.0, colors=TARGET_COLOUR,
                                               labels=[f"target (ground truth): {t.colour} {t.model}"],
                                               show_labels=True), static=True)
        for role, xy in self.starts.items():
            self.rec.log(f"map/{role}/start", rr.Points2D(m.px(xy), radii=4.0, colors=ROLE_COLOURS[role],
                                                          labels=[f"{role.upper()} start"]), static=True)

    def step(self, ev: StepEvent) -> None:
        self.seen.steps += 1
        self.step_of[(ev.role, ev.decision_index)] = (ev.sim_time_s, ev.episode_step)
        while len(self.step_times) < ev.episode_step:
            self.step_times.append(ev.sim_time_s)
        self._at(ev.sim_time_s, ev.episode_step)
        req = ev.requested
        args = (req.waypoint_id, req.cell, req.candidate_id) if req is not None else ()
        what = ev.applied + "".join(f" {v}" for v in args if v)
        text = f"{ev.role.upper()} #{ev.decision_index}: {what}"
        if ev.fallback_reason:
            text += f" (fallback: {ev.fallback_reason})"
        self.rec.log("log/steps", rr.TextLog(text, level="WARN" if ev.fallback_reason else "INFO"))
        if req is not None and req.message and not ev.fallback_reason:
            self.rec.log("log/messages", rr.TextLog(f"{ev.role.upper()} sends: {req.message}", level="INFO"))
        self.live_paths[ev.role].append((ev.pose_after.position_world_m[0], ev.pose_after.position_world_m[1]))
        self._log_path(ev.role, self.live_paths[ev.role])
        if ev.role == "uav" and ev.applied == "ANNOTATE_CANDIDATE" and req is not None and req.cell:
            self._annotated_cell(req.cell, ev.candidate_id)
        elif ev.role == "uav" and self.annotated_shown:
            self.rec.log("uav/nadir/annotated", rr.Clear(recursive=False))
            self.annotated_shown = False
        for frame in self.pending.pop((ev.role, ev.decision_index), []):
            self._log_frame(frame, ev.episode_step)

    def coordination(self, state: CoordinationState) -> None:
        self.seen.coords += 1
        self._at(state.sim_time_s, state.decisions_used)
        for c in state.candidates:
            before = self.candidates.get(c.candidate_id)
            if before == c.status:
                continue
            self.candidates[c.candidate_id] = c.status
            self.rec.log("log/candidates", rr.TextLog(
                f"{c.candidate_id} (cell {c.cell}): {before + ' -> ' if before else ''}{c.status}",
                level="WARN" if c.status in ("rejected", "false_confirm") else "INFO"))
            self._log_candidate(c.candidate_id, c.cell, c.status, c.polygon_world_m)
        for msg in state.messages:
            ident = (msg.sender, msg.sent_sim_time_s, msg.text)
            if ident not in self.messages_seen:
                self.messages_seen.add(ident)
                self._at(msg.delivered_sim_time_s, self._decision_at(msg.delivered_sim_time_s))
                self.rec.log("log/messages", rr.TextLog(
                    f"{msg.receiver.upper()} received from {msg.sender.upper()} (sent t={msg.sent_sim_time_s:.1f} s, "
                    f"{msg.delivered_sim_time_s - msg.sent_sim_time_s:.2f} s later): {msg.text}", level="INFO"))

    def frame(self, frame: VizFrame) -> None:
        """One view: logged at the decision it was shown for, once that decision's step is known."""
        known = self.step_of.get((frame.role, frame.decision_index))
        if known is None:
            self.pending.setdefault((frame.role, frame.decision_index), []).append(frame)
        else:
            self._log_frame(frame, known[1])

    def result(self, record: EpisodeRecord) -> None:
        """The record (at the end): exact trajectories from its step log, link events, the outcome."""
        self.record = record
        if record.step_log:
            self.step_times = [s.sim_time_s for s in record.step_log]
            self._paths_from_step_log(record.step_log)
        self._link_events(record)
        self._at(record.sim_time_s, len(self.step_times))
        for c in record.candidates:
            if self.candidates.get(c.candidate_id) != c.status:
                polygon = next((s.candidate_polygon_world_m for s in record.step_log
                                if s.candidate_id == c.candidate_id and s.candidate_polygon_world_m), [])
                self.candidates[c.candidate_id] = c.status
                self._log_candidate(c.candidate_id, c.cell, c.status, polygon)
        self.rec.log("log/steps", rr.TextLog(f"episode over: {record.termination} "
                                             f"({'success' if record.success else 'failure'})",
                                             level="INFO" if record.success else "WARN"))

    def _steps_lost_on_the_stream(self, step_log: list[LoggedStep]) -> None:
        """Decisions whose step event the best-effort stream lost: logged from the record instead, with
        the views that waited for them, so the file has every decision the record has."""
        for k, s in enumerate(step_log, start=1):
            if (s.role, s.decision_index) in self.step_of:
                continue
            self.step_of[(s.role, s.decision_index)] = (s.sim_time_s, k)
            self._at(s.sim_time_s, k)
            self.rec.log("log/steps", rr.TextLog(f"{s.role.upper()} #{s.decision_index}: {s.applied} (from the record: "
                                                 "its step event was lost on the stream)", level="WARN"))
            for frame in self.pending.pop((s.role, s.decision_index), []):
                self._log_frame(frame, k)

    def close(self) -> Seen:
        """Write what is still pending and the outcome, and finish the file."""
        if self.record is not None and self.record.step_log:
            # Only now: the record travels reliably and can overtake the last step events on the stream.
            self._steps_lost_on_the_stream(self.record.step_log)
        self._flush_pending()
        end = self.record.sim_time_s if self.record is not None else self.step_times[-1] if self.step_times else 0.0
        self._at(end, len(self.step_times))
        self.rec.log("outcome", rr.TextDocument(self.outcome_markdown(), media_type="text/markdown"))
        self.rec.flush()
        self.rec.disconnect()
        return self.seen

    # ----- helpers ----------------------------------------------------------------------------
    def _at(self, sim_time_s: float, decision: int | None) -> None:
        self.rec.reset_time()
        self.rec.set_time("sim_time", duration=sim_time_s)
        if decision is not None:
            self.rec.set_time("decision", sequence=decision)

    def _decision_at(self, sim_time_s: float) -> int:
        """The episode's decision count at ``sim_time_s`` (as far as this recording knows)."""
        return bisect.bisect_right(self.step_times, sim_time_s + 1e-3)  # step times are rounded to 1 ms

    def _flush_pending(self) -> None:
        """Frames of decisions whose step event was lost: at the decision their time says."""
        for (role, index), frames in sorted(self.pending.items()):
            for frame in frames:
                known = self.step_of.get((role, index))
                self._log_frame(frame, known[1] if known else self._decision_at(frame.sim_time_s) + 1)
        self.pending.clear()

    def _log_frame(self, frame: VizFrame, decision: int | None) -> None:
        self._at(frame.sim_time_s, decision)
        image = frame.image
        media = "image/jpeg" if image.encoding == "jpeg" else "image/png"
        name = image.name
        if frame.role == "uav":
            entity = "uav/nadir"
        elif name in SIX_VIEWS:
            entity = f"ugv/six/{name}"
        else:
            entity = "ugv/forward"
        self.rec.log(entity, rr.EncodedImage(contents=image.data, media_type=media))
        self.seen.frames[frame.role] += 1
        if frame.role == "uav":
            self._grid(_image_size(image.data, image.intrinsics))

    def _grid(self, size: tuple[int, int]) -> None:
        """The A1-E5 grid over the nadir image (once per image size, static)."""
        if size in self.grid_sizes:
            return
        self.grid_sizes.add(size)
        w, h = size
        rows = len(GRID_ROWS)
        strips = [[(k * w / GRID_COLS, 0.0), (k * w / GRID_COLS, float(h))] for k in range(1, GRID_COLS)]
        strips += [[(0.0, k * h / rows), (float(w), k * h / rows)] for k in range(1, rows)]
        self.rec.log("uav/nadir/grid", rr.LineStrips2D(strips, colors=(255, 255, 0), radii=0.5), static=True)
        centres = [((c + 0.5) * w / GRID_COLS, (r + 0.5) * h / rows) for r in range(rows) for c in range(GRID_COLS)]
        labels = [f"{row}{c + 1}" for row in GRID_ROWS for c in range(GRID_COLS)]
        self.rec.log("uav/nadir/cells", rr.Points2D(centres, radii=0.5, colors=(255, 255, 0), labels=labels,
                                                    show_labels=True), static=True)

    def _annotated_cell(self, cell: str, candidate_id: str | None) -> None:
        try:
            row, col = parse_cell(cell)
        except ValueError:
            return
        for w, h in self.grid_sizes:  # the nadir frames' size, known once one arrived
            self.annotated_shown = True
            cw, ch = w / GRID_COLS, h / len(GRID_ROWS)
            self.rec.log("uav/nadir/annotated", rr.Boxes2D(mins=[(col * cw, row * ch)], sizes=[(cw, ch)],
                                                           colors=(255, 60, 0), radii=1.5,
                                                           labels=[f"{candidate_id or ''} {cell}".strip()]))

    def _log_candidate(self, candidate_id: str, cell: str, status: str, polygon: list[tuple[float, float]]) -> None:
        if not polygon or self.map is None:
            return
        ring = self.map.px([*polygon, polygon[0]])
        self.rec.log(f"map/candidates/{candidate_id}", rr.LineStrips2D(
            [ring], colors=STATUS_COLOURS.get(status, (255, 255, 255)), radii=1.5,
            labels=[f"{candidate_id} {cell}: {status}"], show_labels=True))

    def _log_path(self, role: Role, points: list[tuple[float, float]]) -> None:
        if self.map is None:
            return
        start = [self.starts[role]] if role in self.starts else []
        path = self.map.px(start + points)
        colour = ROLE_COLOURS[role]
        if len(path) >= 2:
            self.rec.log(f"map/{role}/path", rr.LineStrips2D([path], colors=colour, radii=1.2))
        self.rec.log(f"map/{role}/position", rr.Points2D(path[-1:], radii=5.0, colors=colour,
                                                         labels=[role.upper()], show_labels=True))

    def _paths_from_step_log(self, steps: list[LoggedStep]) -> None:
        """The trajectories again, exact (roads as driven) and complete, at each decision's time:
        they replace what the step events drew."""
        points: dict[Role, list[tuple[float, float]]] = {"uav": [], "ugv": []}
        for k, s in enumerate(steps, start=1):
            points[s.role] += [(p[0], p[1]) for p in s.road_path_world_m] or [s.position_world_m]
            self._at(s.sim_time_s, k)
            self._log_path(s.role, points[s.role])

    def _link_events(self, record: EpisodeRecord) -> None:
        for e in record.ledger:
            self._at(e.sent_s, self._decision_at(e.sent_s))
            route = f"{e.kind} {e.sender.upper()}->{e.receiver.upper()} ({e.size_bytes} B)"
            if e.delivered:
                text, level = f"{route} delivered after {e.delay_s or 0.0:.2f} s", "INFO" if e.kind == "message" else "DEBUG"
            else:
                text, level = f"{route} dropped: {e.drop_reason or 'lost'}", "WARN"
            self.rec.log("log/link", rr.TextLog(text, level=level))

    def outcome_markdown(self) -> str:
        """The outcome as the record says, and what this recording holds of the episode."""
        r, seen = self.record, self.seen
        lines = [f"# {self.episode_id}", ""]
        if r is None:
            lines += ["No record arrived (the run was stopped, or the stream lost it): the recording ends here.", ""]
        else:
            lines += [f"**{r.termination}** ({'success' if r.success else 'failure'}, status {r.status})", "",
                      f"- decisions: UAV {r.decisions_uav}, UGV {r.decisions_ugv} (budget {r.uav_budget}), "
                      f"fallbacks {r.fallbacks}",
                      f"- sim time {r.sim_time_s:.1f} s; UGV path {r.ugv_path_length_m:.1f} m "
                      f"(shortest {r.shortest_path_length_m if r.shortest_path_length_m is not None else '-'} m); "
                      f"final distance to target {r.final_distance_m:.1f} m",
                      "- candidates: " + (", ".join(f"{c.candidate_id} {c.cell} {c.status} "
                                                     f"({c.center_error_m:.1f} m off)" for c in r.candidates) or "none")]
            if r.link is not None:
                lines.append(f"- link ({r.link.profile}): {r.link.delivered}/{r.link.sent} delivered, dropped "
                             f"{dict(r.link.dropped) or 'none'}")
            if r.confirm_rejection:
                lines.append(f"- CONFIRM refused: {r.confirm_rejection}")
            if r.error:
                lines.append(f"- error: {r.error}")
        if self.map is None:
            lines += ["", "The episode's spec never arrived (the stream lost it): no map, paths or candidates."]
        decisions = None if r is None else r.decisions_uav + r.decisions_ugv
        lines += ["", f"Recorded ({'full resolution' if self.full else 'thumbnails'}): "
                      f"{seen.steps}{f' of {decisions}' if decisions is not None else ''} step events, "
                      f"frames UAV {seen.frames['uav']}, UGV {seen.frames['ugv']}, {seen.coords} coordination states; "
                      f"{seen.dropped_before} samples dropped by the recorder's queue."]
        return "\n".join(lines)


def _image_size(data: bytes, intrinsics: Any) -> tuple[int, int]:
    """(width, height) of an encoded image: from the intrinsics, else from its header."""
    if intrinsics is not None:
        return int(intrinsics.width_px), int(intrinsics.height_px)
    with Image.open(io.BytesIO(data)) as img:
        return img.size


def _blueprint() -> rrb.Blueprint:
    """The viewer's layout: the map beside the two roles' cameras, the six views, the logs."""
    six = rrb.Grid(*[rrb.Spatial2DView(origin=f"ugv/six/{v}", name=v) for v in SIX_VIEWS], grid_columns=3)
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(rrb.Spatial2DView(origin="map", name="map"), rrb.TextDocumentView(origin="outcome", name="outcome"),
                         row_shares=[3, 1]),
            rrb.Vertical(
                rrb.Horizontal(rrb.Spatial2DView(origin="uav/nadir", name="UAV nadir"),
                               rrb.Spatial2DView(origin="ugv/forward", name="UGV forward")),
                six,
                rrb.TextLogView(origin="log", name="log"),
                row_shares=[2, 2, 2]),
            column_shares=[1, 1]),
        collapse_panels=True)
