"""The episode configuration: everything that shapes an episode, in one serialisable object.

Speeds, action durations, image sizes and camera fields of view, the CONFIRM checker's thresholds,
the decision budget and timeout, the link profile, the timing mode, what the UAV may do while the
UGV verifies, and the world-side tools of the run's policies. The orchestrator builds it once per
run (defaults < TOML file < ``AGOS_WORLD__…`` environment < flags, in
:mod:`agos.deploy.run.configure`), sends it whole in every job grant, and the world runs the
episode with exactly that and stores it, with its :meth:`EpisodeConfig.config_hash`, in the
record. So two workers started with different local settings still run the same episodes, and
records made under different configurations are never pooled silently (``agos metrics`` refuses
them unless told ``--allow-mixed``).

These are the only defaults of these values in agos.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from agos.runtime.links import IDEAL, CommProfile, CorruptionSpec, DuplicateSpec
from agos.runtime.model_link import ModelLinkProfile, load_model_link, placement
from agos.runtime.sensing import EXACT, PoseErrorProfile, load_pose_error

Look = Literal["flat", "rich"]
DEFAULT_LOOK: Look = "rich"
"""The look a run, a sampler or a dataset build uses unless told otherwise."""

TimingMode = Literal["lockstep", "realtime"]
UavDuringVerification = Literal["frozen", "active"]
"""What the UAV does while the UGV verifies its candidate (docs/AGENTS.md, "The UAV while the UGV
verifies"): ``frozen``, asked nothing (the paper's method section); ``active``, asked as usual but
allowed only to move or wait, a message riding with either (the paper's prompt appendix)."""

UAV_VISIBLE_REFERENCE_PX = 512
"""Nadir image side at which ``uav_visible_min_pixels`` is given (scaled with the side squared)."""
CONFIRM_REFERENCE_PX = 256
"""Ground view side at which ``ConfirmConfig.min_target_pixels`` is given (scaled likewise)."""


class _Part(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True)


class CameraConfig(_Part):
    """Image sizes (square, pixels) and horizontal fields of view (degrees) of the cameras."""

    nadir_px: int = Field(512, ge=64)
    """UAV nadir view side."""
    nadir_fov_deg: float = Field(60.0, gt=0, lt=180)
    ground_px: int = Field(256, ge=64)
    """UGV forward view and each of the six STOP_OBSERVE views."""
    ground_fov_deg: float = Field(70.0, gt=0, lt=180)
    reference_px: int = Field(160, ge=32)
    """Each reference view of the target."""
    rgb_encoding: Literal["jpeg", "png"] = "jpeg"
    map_px: int = Field(384, ge=0)
    """Side of the top-down map M of the episode region (0: no map)."""


class ConfirmConfig(_Part):
    """The CONFIRM checker: what must hold for a CONFIRM to count as a success."""

    require_fresh_stop: bool = True
    """A STOP_OBSERVE right before, with no movement since."""
    min_target_pixels: int = Field(50, ge=0)
    """Target pixels in at least one of the six views. Given at a 256 x 256 view in the
    configuration; :meth:`EpisodeConfig.confirm_at_view_size` scales it with the view's area."""
    max_distance_m: float = Field(50.0, gt=0)
    """Largest UGV-to-target distance."""
    require_line_of_sight: bool = True


class ToolConfig(_Part):
    """World-side tools of the run's policies (set from the policy names, not by hand)."""

    candidates: bool = True
    """Structured candidates (ANNOTATE_CANDIDATE, GO_TO_CANDIDATE); off for the Baseline."""
    e2a: bool = True
    """Ego-to-Allo projection: a candidate is its grid cell on the ground (off: the centre of the
    UAV's footprint, one point, the cell kept as metadata)."""
    rgpp: bool = True
    """Road-graph path planning: GO_TO_CANDIDATE exists (off: distance hints on road waypoints)."""
    oracle: bool = False
    """Ground-truth hints in observations (the oracle policy only)."""
    expert: bool = False
    """The expert's plan in observations (the expert policy only, agos.world.expert)."""


class EpisodeConfig(_Part):
    """Everything that shapes an episode besides the episode itself (the TOML section ``[world]``)."""

    renderer: Literal["tiny", "egl"] = "tiny"
    """PyBullet renderer; the two differ pixel for pixel."""
    look: Look = DEFAULT_LOOK
    """How the world is drawn: ``rich`` (the textured city, vehicles as meshes by body type with
    attributes, drawn shadows: docs/WORLD.md) or ``flat`` (plain colours and boxes: cheaper, for
    scripted sweeps). Episodes are sampled and checked with a look, and their ids say which."""
    uav_speed_mps: float = Field(10.0, gt=0)
    ugv_speed_mps: float = Field(8.0, gt=0)
    wait_max_s: float = Field(20.0, gt=0)
    """Longest WAIT: a waiting role wakes when its view changes, or after this."""
    stop_observe_s: float = Field(2.0, gt=0)
    short_action_s: float = Field(1.0, gt=0)
    """ANNOTATE_CANDIDATE, NO_RELIABLE_CANDIDATE, REJECT."""
    uav_visible_min_pixels: int = Field(30, ge=1)
    """Oracle: target pixels for "visible from the air", at a 512 x 512 nadir view."""
    max_annotations: int = Field(5, ge=1)
    sim_time_limit_s: float = Field(3600.0, gt=0)
    recent_messages: int = Field(6, ge=0)
    """Delivered messages kept in the coordination state."""
    max_freeze_s: float = Field(120.0, gt=0)
    """A UAV that has not heard its candidate resolved by then is asked again (lossy links)."""
    uav_during_verification: UavDuringVerification = "frozen"
    """``frozen``: after ANNOTATE_CANDIDATE the UAV is asked nothing until it hears the candidate
    resolved (or ``max_freeze_s`` passes). ``active``: it keeps deciding while its candidate is open,
    but only MOVE_TO_UAV_WAYPOINT or WAIT are legal then (each may carry a message)."""
    decision_budget: int | None = Field(None, ge=1)
    """Decisions of both roles together; None: each episode's own budget (80 in the splits)."""
    decision_timeout_s: float = Field(60.0, gt=0)
    """Wall-clock wait for an action before the world logs a WAIT fallback."""
    timing_mode: TimingMode = "lockstep"
    """``lockstep``: the sim clock waits for decisions; ``realtime``: a decision's wall-clock
    latency delays its effect in sim time, while the teammate carries on."""
    link_seed: int = 0
    """Extra seed of the link streams, for repeating an episode under other link randomness."""
    cameras: CameraConfig = CameraConfig()
    confirm: ConfirmConfig = ConfirmConfig()
    tools: ToolConfig = ToolConfig()
    comm: CommProfile = IDEAL
    """The link model between the roles (docs/COMMS.md)."""
    pose_error: PoseErrorProfile = EXACT
    """Each role's localisation error (docs/COMMS.md, "Localisation error"): what it is shown as its
    own pose, sends its teammate and projects candidates from; the world and the scores use the truth."""
    model_link: ModelLinkProfile | None = None
    """Where the model of VLM policies runs, and the link to it (docs/COMMS.md, "The link to the
    model"; runtime/model_link.py). None: onboard, no link (an ``onboard`` profile is stored as None)."""
    capture_every_m: float | None = Field(None, gt=0)
    """Dataset builds (``agos dataset build``): the world also renders each role's camera every this
    many metres along its moves, delivered with the next observation (``ExpertHints.passed``, expert
    runs only). None: no views between decisions."""

    @field_validator("model_link")
    @classmethod
    def _onboard_is_none(cls, value: ModelLinkProfile | None) -> ModelLinkProfile | None:
        return placement(value)

    @field_validator("pose_error", mode="before")
    @classmethod
    def _pose_error_by_name(cls, value: Any) -> Any:
        """``pose_error = "gnss-5m"`` (a settings file, the library): the profile of that name or file."""
        return load_pose_error(value).model_dump() if isinstance(value, str) else value

    @model_validator(mode="after")
    def _expert_needs_a_frozen_uav(self) -> EpisodeConfig:
        """The expert's plan is timed for a frozen UAV (world/expert/timeline.py): an ``active`` UAV
        would be asked decisions its script does not have."""
        if self.tools.expert and self.uav_during_verification != "frozen":
            raise ValueError("uav_during_verification must be 'frozen' with the expert tool (its plan is timed "
                             "for a UAV that is asked nothing while the UGV verifies)")
        return self

    def config_hash(self) -> str:
        """Short sha256 (12 hex digits) of the canonical JSON of every field: equal hashes, equal
        configurations."""
        return config_hash(self.model_dump(mode="json"))

    def uav_visible_min_px(self) -> int:
        """``uav_visible_min_pixels`` at this configuration's nadir view size."""
        return max(1, round(self.uav_visible_min_pixels * (self.cameras.nadir_px / UAV_VISIBLE_REFERENCE_PX) ** 2))

    def confirm_at_view_size(self) -> ConfirmConfig:
        """The checker's thresholds with ``min_target_pixels`` scaled to this configuration's ground
        view size (what :func:`agos.world.sim.confirm.check_confirm` compares against)."""
        scale = (self.cameras.ground_px / CONFIRM_REFERENCE_PX) ** 2
        return self.confirm.model_copy(update={"min_target_pixels": max(1, round(self.confirm.min_target_pixels * scale))})


class StoredConfigError(ValueError):
    """A stored or sent configuration this agos cannot read; the text names where and the field."""


def read_config(data: Any, *, where: str) -> EpisodeConfig:
    """The configuration in ``data`` (a stored or sent map: a job grant, ``run.json``), checked;
    :class:`StoredConfigError` names ``where`` and the first field that fails."""
    try:
        return EpisodeConfig.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        field = ".".join(str(p) for p in err["loc"]) or "<config>"
        raise StoredConfigError(f"{where}: episode configuration field {field}: {err['msg']} "
                                "(written by another agos version?)") from None


HASHED_ONLY_WHEN_NOT: dict[str, dict[str, Any]] = {
    "": {"look": "flat", "capture_every_m": None, "uav_during_verification": "frozen",
         "pose_error": EXACT.model_dump(mode="json"), "model_link": None},
    "tools": {"expert": False},
    "comm": {"duplicate": DuplicateSpec().model_dump(mode="json"),
             "corruption": CorruptionSpec().model_dump(mode="json")}}
"""Fields added after configurations were first stored, by section ("" is the top level): left out
of the hash at these values, so configurations stored before the fields existed keep their hash. A
field may itself be a section (the link profile's message faults): it is left out when the whole of
it is at its defaults."""


def config_hash(data: dict[str, Any]) -> str:
    """Short hash of a configuration as stored (a map): the same for an object and its stored copy.
    A field of :data:`HASHED_ONLY_WHEN_NOT` counts only when it differs from the value named there."""

    def strip(section: dict[str, Any], absent: dict[str, Any]) -> dict[str, Any]:
        return {k: v for k, v in section.items() if not (k in absent and v == absent[k])}

    data = strip(data, HASHED_ONLY_WHEN_NOT[""])
    for name, absent in HASHED_ONLY_WHEN_NOT.items():
        if name and isinstance(data.get(name), dict):
            data = {**data, name: strip(data[name], absent)}
    canonical = json.dumps(data, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(canonical.encode()).hexdigest()[:12]


def differing_fields(a: dict[str, Any], b: dict[str, Any], prefix: str = "") -> list[str]:
    """Dotted names of the fields where two stored configurations differ (``cameras.nadir_px``)."""
    out: list[str] = []
    for key in sorted(set(a) | set(b)):
        va, vb = a.get(key), b.get(key)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += differing_fields(va, vb, f"{prefix}{key}.")
        elif va != vb:
            out.append(f"{prefix}{key}")
    return out


def with_model_link(config: EpisodeConfig, value: str | Path) -> EpisodeConfig:
    """``config`` with the model placed by ``value`` (a name in deploy/model_link or a TOML file;
    ``onboard``: no link, the configuration's default): for ``--model-link`` and the sweep axis
    ``model_link``. Raises :class:`~agos.runtime.model_link.ModelLinkError` (one line)."""
    return config.model_copy(update={"model_link": placement(load_model_link(value))})
