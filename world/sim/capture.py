"""Views between decisions, for dataset builds (AGOS-Dataset Stage 3: "every 10 m between nodes").

Contract: :func:`views_along` renders a role's own camera (the UAV's nadir view, the UGV's forward
view) at every ``every_m`` metres along a move the rules just applied, strictly between its start
and its end (the start was the last decision's view, the end is the next one's), with the sim time
the platform passes there at the role's speed. The world moves platforms in one jump and charges
the move's time (rules.py), so these are the views the platform would have had on the way. Only
runs with ``EpisodeConfig.capture_every_m`` set call it; it changes no state.
"""

from __future__ import annotations

import math

import numpy as np

from agos.runtime.schemas import PassedView, Pose, Role
from agos.world.sim import sensors
from agos.world.sim.state import EpisodeState

MIN_GAP_M = 1.0
"""A point closer than this to the move's end is left out: the next decision shows it."""


def views_along(st: EpisodeState, role: Role, polyline_xy: list[tuple[float, float]], t0_s: float,
                every_m: float) -> list[PassedView]:
    """``role``'s views every ``every_m`` along ``polyline_xy`` (its move, start first), timed from
    ``t0_s`` at the role's speed."""
    cam, cfg = st.cfg.cameras, st.cfg
    speed = cfg.uav_speed_mps if role == "uav" else cfg.ugv_speed_mps
    out: list[PassedView] = []
    for distance_m, (x, y), heading in _points_every(polyline_xy, every_m):
        if role == "uav":
            altitude = st.uav.position[2]
            shot = sensors.nadir(st.scene, (x, y), altitude, cam)
            pose = Pose(position_world_m=(x, y, altitude), yaw_rad=math.pi / 2)
        else:
            shot = sensors.ground_view(st.scene, "forward", (x, y), heading, cam)
            pose = Pose(position_world_m=(x, y, 0.0), yaw_rad=round(heading, 6))
        out.append(PassedView(sim_time_s=round(t0_s + distance_m / speed, 3), distance_m=round(distance_m, 3),
                              pose=pose, images=sensors.frames_of(shot, st.scene, cam)))
    return out


def _points_every(polyline_xy: list[tuple[float, float]], every_m: float
                  ) -> list[tuple[float, tuple[float, float], float]]:
    """(distance along, point, heading of its segment) every ``every_m`` strictly inside the line."""
    pts = np.asarray(polyline_xy, dtype=np.float64)
    if len(pts) < 2:
        return []
    seg = np.diff(pts, axis=0)
    lengths = np.hypot(seg[:, 0], seg[:, 1])
    total = float(lengths.sum())
    ends = np.cumsum(lengths)
    out = []
    d = every_m
    while d < total - MIN_GAP_M:
        k = int(np.searchsorted(ends, d))
        start = ends[k] - lengths[k]
        f = (d - start) / lengths[k] if lengths[k] > 0 else 0.0
        x, y = pts[k] + f * seg[k]
        out.append((d, (float(x), float(y)), math.atan2(seg[k][1], seg[k][0])))
        d += every_m
    return out
