"""Observations as arrays and actions as indices: what ``agos.pettingzoo`` and ``agos.gymnasium`` give a
learner, and the mapping both ways between the world's messages and them (docs/AGENTS.md, "Actions
as indices"; docs/LIBRARY.md).

Actions: a fixed-size ``Discrete`` space per role whose indices name one action with its argument:

* UAV, ``Discrete(35)``: 0 WAIT, 1 NO_RELIABLE_CANDIDATE, 2-26 ANNOTATE_CANDIDATE of cell A1, A2 ...
  E5 (``2 + 5 * row + column``), 27-34 MOVE_TO_UAV_WAYPOINT to ``waypoint_options[index - 27]``.
* UGV, ``Discrete(17)``: 0 WAIT, 1 STOP_OBSERVE, 2 CONFIRM, 3 REJECT (the candidate the UGV holds open,
  if any), 4 GO_TO_CANDIDATE (that candidate), 5-16 MOVE_TO_ROAD_WAYPOINT to ``waypoint_options[index - 5]``.

``action_mask`` marks the indices legal now: the action is in ``legal_actions`` and its argument
exists (a waypoint option in that slot, an open candidate with a road approach). A role not asked
this round gets the no-op mask, index 0 alone; whatever it is given is not applied. Messages to
the teammate have no index (the text-level ``agos.Env`` carries them). An index outside the mask
is given to the world as it is, which turns it into a counted WAIT, as for any agent.

Observations: a ``Dict`` per role of ``uint8``/``float32`` arrays (:func:`observation_space`):
``rgb`` (the UAV's nadir view; the UGV's six STOP_OBSERVE views in the order front-left, front,
front-right, back-left, back, back-right, or while driving its forward view in the front slot and
black elsewhere), optional ``depth`` (metres) and ``semantic`` (class ids) laid out alike, ``map``
(the region from above with both markers, when the configuration has one), ``reference`` (the
target's five reference views, background black), ``state`` (:data:`STATE_FIELDS`),
``waypoints`` (per move slot: east and north offset from the role in metres, distance in metres,
1 when the slot holds an option) and ``action_mask``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

try:
    from gymnasium import spaces
except ModuleNotFoundError as missing:  # the learning interfaces' extra is not installed
    raise ModuleNotFoundError(f"agos's learning interfaces need {missing.name}: pip install 'agos[learn]' "
                              "(gymnasium, pettingzoo; docs/LIBRARY.md)", name=missing.name) from None

from agos.agents.contract import action_for
from agos.runtime.camera import GRID_COLS, GRID_ROWS
from agos.runtime.codec import decode_image
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.schemas import Action, Candidate, ImageFrame, Observation, Role

UAV_MOVE_SLOTS = 8
"""The UAV's options: the active nodes around its own on the grid, at most 8."""
UGV_MOVE_SLOTS = 12
"""The UGV's road options (forward, far, junction exits, back): at most 9 on the procedural towns; an
option past slot 12 has no index."""
CELLS = [f"{row}{col + 1}" for row in GRID_ROWS for col in range(GRID_COLS)]
UAV_NAMES = ["WAIT", "NO_RELIABLE_CANDIDATE"] + ["ANNOTATE_CANDIDATE"] * len(CELLS) + \
    ["MOVE_TO_UAV_WAYPOINT"] * UAV_MOVE_SLOTS
UGV_NAMES = ["WAIT", "STOP_OBSERVE", "CONFIRM", "REJECT", "GO_TO_CANDIDATE"] + ["MOVE_TO_ROAD_WAYPOINT"] * UGV_MOVE_SLOTS
ACTION_NAMES: dict[Role, list[str]] = {"uav": UAV_NAMES, "ugv": UGV_NAMES}
"""Index -> action name, per role."""
FIRST_CELL = 2
FIRST_MOVE: dict[Role, int] = {"uav": FIRST_CELL + len(CELLS), "ugv": 5}
MOVE_SLOTS: dict[Role, int] = {"uav": UAV_MOVE_SLOTS, "ugv": UGV_MOVE_SLOTS}
SIX = ("front_left", "front", "front_right", "back_left", "back", "back_right")
"""The UGV's view slots (the world's six-view order); driving, its forward view is in ``front``."""
REFERENCES = ("ref_top", "ref_front_left", "ref_side", "ref_rear", "ref_front")
STATE_FIELDS = ("x_m", "y_m", "z_m", "yaw_rad", "sim_time_s", "decisions_used", "decision_budget", "annotations_used",
                "max_annotations", "confirmations_used", "mode", "fresh_stop_observe", "teammate_known",
                "teammate_dx_m", "teammate_dy_m", "candidate_open", "candidate_dx_m", "candidate_dy_m",
                "messages", "asked")
"""``state``'s entries: pose; time; the decision, annotation and confirmation counts the world keeps;
``mode`` 0 aerial, 1 driving, 2 stopped with six views; the teammate's last reported position and the
open candidate's centre as offsets from the role; messages received; 1 when the role is asked now."""
STATE_LIMIT = 1e6
MODES = {"aerial": 0.0, "driving": 1.0, "stop_6view": 2.0}


def action_count(role: Role) -> int:
    return len(ACTION_NAMES[role])


def open_candidate(obs: Observation) -> Candidate | None:
    """The candidate the role holds open (pending or arrived), as the world's rules pick it."""
    return next((c for c in obs.coordination.candidates if c.status in ("pending", "arrived")), None)


def action_mask(obs: Observation | None, role: Role) -> np.ndarray:
    """1 for each index legal now; ``obs`` None (the role is not asked): index 0 alone."""
    mask = np.zeros(action_count(role), np.int8)
    if obs is None:
        mask[0] = 1
        return mask
    legal = set(obs.legal_actions)
    for index, name in enumerate(ACTION_NAMES[role]):
        mask[index] = name in legal
    first, slots = FIRST_MOVE[role], MOVE_SLOTS[role]
    mask[first + len(obs.waypoint_options):first + slots] = 0
    if role == "ugv":
        candidate = open_candidate(obs)
        if candidate is None or candidate.approach_waypoint_id is None:
            mask[UGV_NAMES.index("GO_TO_CANDIDATE")] = 0
    return mask


def action_from_index(obs: Observation, index: int) -> Action:
    """The action index ``index`` names for ``obs``. An index outside the mask gives an action the
    world refuses (a counted WAIT); one outside the space raises ``ValueError``."""
    role: Role = obs.role
    if not 0 <= index < action_count(role):
        raise ValueError(f"{role} action index {index} is outside Discrete({action_count(role)})")
    name = ACTION_NAMES[role][index]
    if name.startswith("MOVE_TO_"):
        k = index - FIRST_MOVE[role]
        return action_for(obs, name, waypoint_id=obs.waypoint_options[k].waypoint_id if k < len(obs.waypoint_options)
                          else None)
    if name == "ANNOTATE_CANDIDATE":
        return action_for(obs, name, cell=CELLS[index - FIRST_CELL])
    if name in ("REJECT", "GO_TO_CANDIDATE"):
        candidate = open_candidate(obs)
        return action_for(obs, name, candidate_id=None if candidate is None else candidate.candidate_id)
    return action_for(obs, name)


def index_of(obs: Observation, action: Action) -> int | None:
    """The index naming ``action`` for ``obs`` (its message dropped), or None when it has none: a
    waypoint not among the first options, a cell outside A1..E5, another candidate than the open one."""
    role: Role = obs.role
    name = action.action
    if name.startswith("MOVE_TO_"):
        ids = [w.waypoint_id for w in obs.waypoint_options[:MOVE_SLOTS[role]]]
        return FIRST_MOVE[role] + ids.index(action.waypoint_id) if action.waypoint_id in ids else None
    if name == "ANNOTATE_CANDIDATE":
        cell = (action.cell or "").upper()
        return FIRST_CELL + CELLS.index(cell) if cell in CELLS else None
    if name in ("REJECT", "GO_TO_CANDIDATE") and action.candidate_id is not None:
        candidate = open_candidate(obs)
        if candidate is None or candidate.candidate_id != action.candidate_id:
            return None
    names = ACTION_NAMES[role]
    return names.index(name) if name in names else None


# ----- observations ------------------------------------------------------------------------------
def image_shapes(role: Role, config: EpisodeConfig) -> tuple[int, ...]:
    """The leading dimensions of ``rgb``/``depth``/``semantic``: (side, side) or (6, side, side)."""
    cam = config.cameras
    return (cam.nadir_px, cam.nadir_px) if role == "uav" else (len(SIX), cam.ground_px, cam.ground_px)


def observation_space(role: Role, config: EpisodeConfig, *, depth: bool = False, semantic: bool = False) -> spaces.Dict:
    """The role's observation space (module docstring)."""
    cam, lead = config.cameras, image_shapes(role, config)
    parts: dict[str, spaces.Space] = {"rgb": spaces.Box(0, 255, (*lead, 3), np.uint8)}
    if depth:
        parts["depth"] = spaces.Box(0.0, 65535 * 0.005, lead, np.float32)
    if semantic:
        parts["semantic"] = spaces.Box(0, 255, lead, np.uint8)
    if cam.map_px:
        parts["map"] = spaces.Box(0, 255, (cam.map_px, cam.map_px, 3), np.uint8)
    parts["reference"] = spaces.Box(0, 255, (len(REFERENCES), cam.reference_px, cam.reference_px, 3), np.uint8)
    parts["state"] = spaces.Box(-STATE_LIMIT, STATE_LIMIT, (len(STATE_FIELDS),), np.float32)
    parts["waypoints"] = spaces.Box(-STATE_LIMIT, STATE_LIMIT, (MOVE_SLOTS[role], 4), np.float32)
    parts["action_mask"] = spaces.Box(0, 1, (action_count(role),), np.int8)
    return spaces.Dict(parts)


def observation_arrays(obs: Observation, space: spaces.Dict, *, asked: bool = True) -> dict[str, np.ndarray]:
    """``obs`` as arrays of ``space`` (:func:`observation_space`); ``asked`` False: the no-op mask."""
    role: Role = obs.role
    out: dict[str, np.ndarray] = {}
    for kind, key in (("rgb", "rgb"), ("depth", "depth"), ("semantic", "semantic")):
        if key in space.spaces:
            out[key] = _camera(obs, kind, space[key])
    if "map" in space.spaces:
        frame = next((f for f in obs.images if f.kind == "map"), None)
        out["map"] = _fit(_pixels(frame), space["map"]) if frame is not None else np.zeros(_shape(space["map"]), np.uint8)
    refs = {f.name: f for f in obs.references}
    ref_space = space["reference"]
    out["reference"] = np.stack([_fit(_pixels(refs[n]), ref_space, lead=1) if n in refs else
                                 np.zeros(_shape(ref_space)[1:], np.uint8) for n in REFERENCES])
    out["state"] = _state(obs, asked)
    out["waypoints"] = _waypoints(obs, MOVE_SLOTS[role])
    out["action_mask"] = action_mask(obs if asked else None, role)
    return out


def _state(obs: Observation, asked: bool) -> np.ndarray:
    c, here = obs.coordination, obs.pose.position_world_m
    mate = c.poses.get("ugv" if obs.role == "uav" else "uav")
    candidate = open_candidate(obs)
    values = [here[0], here[1], here[2], obs.pose.yaw_rad, obs.sim_time_s, c.decisions_used, c.decision_budget,
              c.annotations_used, c.max_annotations, c.confirmations_used, MODES[obs.mode], obs.fresh_stop_observe,
              mate is not None, 0.0 if mate is None else mate.position_world_m[0] - here[0],
              0.0 if mate is None else mate.position_world_m[1] - here[1], candidate is not None,
              0.0 if candidate is None else candidate.center_world_m[0] - here[0],
              0.0 if candidate is None else candidate.center_world_m[1] - here[1], len(c.messages), asked]
    return np.clip(np.asarray(values, np.float32), -STATE_LIMIT, STATE_LIMIT)


def _waypoints(obs: Observation, slots: int) -> np.ndarray:
    out = np.zeros((slots, 4), np.float32)
    here = obs.pose.position_world_m
    for k, w in enumerate(obs.waypoint_options[:slots]):
        dx, dy = w.position_world_m[0] - here[0], w.position_world_m[1] - here[1]
        out[k] = (dx, dy, w.path_length_m if w.path_length_m is not None else math.hypot(dx, dy), 1.0)
    return np.clip(out, -STATE_LIMIT, STATE_LIMIT)


def _camera(obs: Observation, kind: str, space: spaces.Space) -> np.ndarray:
    shape = _shape(space)
    frames = {f.name: f for f in obs.images if f.kind == kind}
    if obs.role == "uav":
        frame = frames.get("nadir")
        return _fit(_pixels(frame, kind), space) if frame is not None else np.zeros(shape, space.dtype)
    out = np.zeros(shape, space.dtype)
    for k, name in enumerate(SIX):
        frame = frames.get("forward" if name == "front" and "forward" in frames else name)
        if frame is not None:
            out[k] = _fit(_pixels(frame, kind), space, lead=1)
    return out


def _pixels(frame: ImageFrame, kind: str = "rgb") -> np.ndarray:
    image = decode_image(frame.data)
    if kind == "depth":
        return image.astype(np.float32) * np.float32(frame.depth_scale_m or 0.0)
    return image[:, :, :3] if image.ndim == 3 else image


def _fit(image: np.ndarray, space: spaces.Space, *, lead: int = 0) -> np.ndarray:
    """``image`` in the space's size (the world renders at the configured size; a map may differ)."""
    shape = _shape(space)[lead:]
    if image.shape[:2] != shape[:2]:
        image = cv2.resize(image, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
    return image.astype(space.dtype, copy=False)


def _shape(space: spaces.Space) -> tuple[int, ...]:
    assert space.shape is not None
    return tuple(space.shape)
