"""Wire messages of agos: one ``msgspec.Struct`` per message type (a contract: docs/ARCHITECTURE.md §8).

Every payload on the bus is a msgpack map with ``type`` (the tag of the message's struct) and ``v``
(schema version). Messages here are plain data: numbers, strings, lists, maps and raw bytes, so
any msgpack decoder in any language reads them. Positions are world-frame metres (x east, y north,
z up); yaw is radians, counter-clockwise from +x. Times are simulated seconds unless a name says
``wall``.

These classes are the only definition of each message: the world builds them, policies read and
answer them, the evaluator stores them. A struct is not validated when it is built (as a dataclass
is not): every value is type-checked in C when a payload is decoded (:func:`agos.runtime.codec.decode`,
which dispatches on ``type`` through :data:`WireMessage`), and a sender that builds from untrusted
parts checks its message by decoding what it encodes (the agent service does this for actions).
Build with the declared types (floats for ``float`` fields): an ``int`` where a ``float`` is
declared is decoded fine but written as a msgpack int, which changes the payload's size.
"""

from __future__ import annotations

from typing import Any, Final, Literal

import msgspec

from agos.runtime.keys import Role

SCHEMA_VERSION: Final = 3
"""The version every live process writes and the only one it accepts from the bus
(runtime/codec.py ``decode``: another is refused in one line naming both). Stored messages (records
in results files and SQLite, specs in split files) of every version in :data:`SchemaVersion` still
read (``from_json``).

The rule for every change of the wire: bump this and add the new number to ``SchemaVersion``; a
change of what a message holds also gives readers of older stored versions their upgrade (a default
for a new field, say), tested with a payload of each older version (tests/test_codec.py).

- 1: keys named episodes (``agos/<run>/ep/<ep>/...``).
- 2: keys name world workers' slots (``agos/<run>/slot/<worker>/...``, ``viz/<worker>/...``) and lease
  notices travel on ``ctl/lease``; the messages are those of version 1.
- 3: sensing and links (docs/COMMS.md): records, steps and traces carry the localisation error, the
  link to the model (bytes up and down, link time) and message faults (duplicates, corrupted text);
  older stored messages read with those fields empty."""
SchemaVersion = Literal[1, 2, 3]
"""Every ``v`` a stored message may carry."""

Difficulty = Literal["easy", "mid", "hard"]
DIFFICULTIES: tuple[Difficulty, ...] = ("easy", "mid", "hard")
"""The difficulties, easiest first: the order of sampling streams, tables and figures."""
Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]

UavActionName = Literal["MOVE_TO_UAV_WAYPOINT", "ANNOTATE_CANDIDATE", "NO_RELIABLE_CANDIDATE", "WAIT"]
UgvActionName = Literal[
    "MOVE_TO_ROAD_WAYPOINT", "GO_TO_CANDIDATE", "STOP_OBSERVE", "CONFIRM", "REJECT", "WAIT"
]
ActionName = Literal[
    "MOVE_TO_UAV_WAYPOINT",
    "ANNOTATE_CANDIDATE",
    "NO_RELIABLE_CANDIDATE",
    "MOVE_TO_ROAD_WAYPOINT",
    "GO_TO_CANDIDATE",
    "STOP_OBSERVE",
    "CONFIRM",
    "REJECT",
    "WAIT",
]
EpisodeStatus = Literal["finished", "agent_crashed", "world_crashed", "timeout", "invalid", "infra_error"]
"""Closed status vocabulary: only ``finished`` episodes say anything about the agents. ``infra_error``:
the model endpoint gave no answer in every attempt the run allowed (``[run] max_infra_attempts``)."""

Termination = Literal["confirmed", "false_confirm", "budget_exhausted", "sim_time_limit", "error"]


class Part(msgspec.Struct, forbid_unknown_fields=True):
    """Base of every wire struct: unknown fields are refused when decoding."""


class Message(Part, tag_field="type"):
    """Base of the top-level messages: tagged by ``type`` (written first), versioned by ``v``."""

    v: SchemaVersion = SCHEMA_VERSION


class Pose(Part, kw_only=True):
    position_world_m: Vec3
    """Position in the world frame, metres."""
    yaw_rad: float
    """Heading, radians counter-clockwise from world +x."""


class CameraIntrinsics(Part, kw_only=True):
    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float


class ImageFrame(Part, kw_only=True):
    """One encoded image with the camera that took it."""

    name: str
    """Camera name: ``nadir``, ``forward``, ``front_left`` ... ``back_right``, ``ref_<view>``."""
    kind: Literal["rgb", "depth", "semantic", "rgb_grid", "map"]
    """``depth`` is uint16 PNG in units of ``depth_scale_m``; ``semantic`` is a uint8 class map."""
    encoding: Literal["png", "jpeg"]
    data: bytes
    intrinsics: CameraIntrinsics | None = None
    world_from_camera: list[float] | None = None
    """Row-major 4x4 pose of the camera (OpenCV frame: x right, y down, z forward)."""
    depth_scale_m: float | None = None
    """Metres per depth unit (depth images only)."""
    metres_per_px: float | None = None
    """Ground or object scale, where the image has one (reference views, maps)."""


class Waypoint(Part, kw_only=True):
    waypoint_id: str
    position_world_m: Vec3
    kind: str
    """``uav_grid``, ``cruise``, ``junction_entry``, ``junction_exit``, ``dead_end`` ..."""
    path_length_m: float | None = None
    """Road distance from the agent's current node (UGV options only)."""
    option: str | None = None
    """UGV options: ``forward`` (~10 m), ``forward_far`` (~30 m), ``junction_exit``, ``backward``."""
    distance_to_candidate_m: float | None = None
    """Without road-graph path planning (no_rgpp ablation): straight-line distance from this
    option to the active candidate's centre, the hint the UGV navigates by."""


CandidateStatus = Literal["pending", "arrived", "rejected", "confirmed", "false_confirm"]


class Candidate(Part, kw_only=True):
    """A handoff region; each role holds its own copy, updated through the link model."""

    candidate_id: str
    """``C001``, ``C002`` ... in order of annotation (1-based rank for ACG)."""
    cell: str
    """Grid cell label of the UAV image, ``A1`` (top-left) to ``E5`` (bottom-right)."""
    polygon_world_m: list[Vec2]
    """The cell projected onto the ground plane (Ego-to-Allo projection)."""
    center_world_m: Vec2
    status: CandidateStatus
    created_sim_time_s: float
    approach_waypoint_id: str | None = None
    """Road decision anchor chosen by road-graph path planning, if reachable."""


class MessageRecord(Part, kw_only=True):
    sender: Role
    receiver: Role
    text: str
    sent_sim_time_s: float
    delivered_sim_time_s: float


class CoordinationState(Message, tag="coordination_state", kw_only=True):
    """C_t: what the roles share (candidates, messages, poses, budget)."""

    run_id: str
    episode_id: str
    sim_time_s: float
    candidates: list[Candidate] = []
    messages: list[MessageRecord] = []
    """Most recent delivered messages, oldest first."""
    poses: dict[str, Pose] = {}
    decisions_used: int = 0
    decision_budget: int = 80
    annotations_used: int = 0
    max_annotations: int = 5
    confirmations_used: int = 0
    """CONFIRMs made so far in the episode (0 in every observation: a CONFIRM ends the episode)."""
    max_confirmations: int = 1
    """CONFIRMs an episode allows (world/sim/rules.py ``MAX_CONFIRMATIONS``): the remaining
    confirmation budget is ``max_confirmations - confirmations_used`` (docs/AGENTS.md)."""


class OracleHints(Part, kw_only=True):
    """Ground truth, given only to the ``oracle`` policy (an upper bound and solvability check)."""

    target_world_m: Vec2
    target_in_view: bool
    """The target is oracle-visible in this observation's images."""
    confirm_would_succeed: bool
    """A CONFIRM now would pass the checker (UGV after STOP_OBSERVE)."""


class ExpertStep(Part, kw_only=True):
    """One decision of the expert's plan (agos.world.expert): the action it takes and when the
    world will ask for it."""

    sim_time_s: float
    """When the world asks for this decision (the plan's timeline, the world's own timing)."""
    action: ActionName
    waypoint_id: str | None = None
    cell: str | None = None
    candidate_id: str | None = None
    message: str | None = None


class ExpertWaypoint(Part, kw_only=True):
    """One point of an expert trajectory: a UAV grid node or a UGV road anchor (``R<n>``), reached at
    ``t_s`` (sim seconds from the episode's start)."""

    waypoint_id: str
    position_world_m: tuple[float, float]
    t_s: float


class PassedView(Part, kw_only=True):
    """The role's camera between two decisions (dataset builds: ``capture_every_m``): rendered where
    the platform passes ``distance_m`` along its move, at ``sim_time_s``; RGB, depth and semantic
    frames like an observation's."""

    sim_time_s: float
    distance_m: float
    """Along the move that started at the role's last decision."""
    pose: Pose
    images: list[ImageFrame]


class ExpertHints(Part, kw_only=True):
    """The expert's plan for one role, computed by the world (which holds the ground truth) and
    given only when the run's policy is ``expert``: its whole decision script, one step per
    decision, in order (step k answers the role's decision k + 1), the trajectories it realises
    (docs/DATASET.md), and the views passed since the role's last decision."""

    steps: list[ExpertStep]
    raw_trajectory: list[ExpertWaypoint] = []
    """Tra_0: the first mTSP solution's route of this role, before truncation."""
    trajectory: list[ExpertWaypoint] = []
    """Tra: where the role decides, truncated at ``t_f_s`` (the UGV's with its handoff path)."""
    t_f_s: float | None = None
    """First time either role would find the target."""
    t_arr_s: float | None = None
    """When the UGV arrives where it confirms (``t_f_s`` when the UGV finds the target itself)."""
    finder: Role | None = None
    wrong_candidates: int = 0
    passed: list[PassedView] = []
    """Views along the move since this role's last decision (``EpisodeConfig.capture_every_m``)."""


class Observation(Message, tag="observation", kw_only=True):
    """World -> agent: everything a role may know at its decision ``decision_index``."""

    run_id: str
    episode_id: str
    role: Role
    decision_index: int
    """1-based index of this role's decision in the episode."""
    attempt: int = 1
    """Which lease of the episode this is (re-leased after a dead or stuck world: 2, 3): every attempt is
    a fresh episode, so an agent forgets earlier attempts and answers with this number."""
    decision_timeout_s: float | None = None
    """Wall seconds the world waits for the answer before it applies a WAIT fallback (the run's
    ``decision_timeout_s``, stamped by the world worker; None where no world said). What a human
    console counts down (agents/human/)."""
    sim_time_s: float
    pose: Pose
    mode: Literal["aerial", "driving", "stop_6view"]
    images: list[ImageFrame]
    references: list[ImageFrame]
    """Target reference views, background removed (black, alpha in the PNG)."""
    teammate_reference: ImageFrame | None = None
    """UAV only: the UGV alone seen from straight above (``teammate_top``, background removed like
    the references, with ``metres_per_px``), rendered once when the episode starts, so the UAV can
    tell its teammate from other vehicles. None for the UGV."""
    legal_actions: list[ActionName]
    waypoint_options: list[Waypoint]
    region_world_m: tuple[float, float, float, float]
    """Episode region (x_min, y_min, x_max, y_max)."""
    active_uav_waypoints: list[Waypoint] = []
    """All active UAV grid nodes of the episode (UAV only): the searchable area."""
    coordination: CoordinationState
    grid_rows: str = "ABCDE"
    grid_cols: int = 5
    fresh_stop_observe: bool = False
    """True right after STOP_OBSERVE, before any movement (UGV)."""
    oracle: OracleHints | None = None
    """Only when the run's policy is ``oracle``; never for other policies."""
    expert: ExpertHints | None = None
    """Only when the run's policy is ``expert``; never for other policies."""


class DecisionTrace(Part, kw_only=True):
    """How a model-backed policy reached one decision (VLM policies; None for scripted ones).

    Retries, re-asks and repairs are counted here, never as decisions (DS counts decisions)."""

    policy: str
    model: str
    stage: str
    """The prompt's task stage (``search``, ``candidate_reminder``, ``six_view`` ...)."""
    prompt_sha256: str
    """Hash of the request body of the first attempt (text and images), not the request itself."""
    image_bytes: dict[str, int]
    """Label -> encoded size of each image sent."""
    raw_reply: str | None
    """The last reply's text, cut to 2,000 characters."""
    parsed_action: str
    fallback: bool
    fallback_reason: str | None = None
    repaired: bool = False
    """The reply's JSON needed syntax repair (fences, quotes, trailing text)."""
    reasks: int = 0
    """Extra requests after a reply that could not be used."""
    http_attempts: int = 0
    """HTTP requests made, retries included."""
    latency_s: float = 0.0
    request_bytes: int = 0
    """The HTTP request body sent to the model (its images included), bytes: what the link to the
    model carries up (``--model-link``)."""
    reply_bytes: int = 0
    """The reply body, bytes: what the link to the model carries down."""
    prompt_tokens: int | None = None
    completion_tokens: int | None = None
    error: str | None = None
    """Why the endpoint gave no answer at all (the decision then became a fallback)."""


class Action(Message, tag="action", kw_only=True):
    """Agent -> world: one decision."""

    run_id: str
    episode_id: str
    role: Role
    decision_index: int
    attempt: int = 1
    """The observation's attempt: the world ignores answers to another attempt of the episode."""
    action: ActionName
    waypoint_id: str | None = None
    cell: str | None = None
    candidate_id: str | None = None
    message: str | None = None
    """Optional short text to the teammate, delivered through the link model."""
    rationale: str | None = None
    agent_wall_latency_s: float | None = None
    trace: DecisionTrace | None = None
    """Model-backed policies: how the decision was reached (stored with the episode)."""
    outage: str | None = None
    """Set when the policy could not decide because its model endpoint gave no answer after its retries
    (agents/contract.py::EndpointOutage): one line naming the endpoint and what failed. Not a decision:
    the world applies nothing, abandons the attempt and gives the episode back (docs/AGENTS.md)."""


class AgentMessage(Message, tag="agent_message", kw_only=True):
    run_id: str
    episode_id: str
    sender: Role
    receiver: Role
    text: str
    sent_sim_time_s: float
    delivered_sim_time_s: float


class VehicleSpec(Part, kw_only=True, omit_defaults=True):
    """A target or look-alike of an episode. The attributes (``roof``, ``rack``, ``stripe``) are
    drawn only by the rich look, which refuses none of them; the flat look refuses a vehicle that
    has any (agos.world.sim.episode_vehicles). Fields at their defaults are not written, so
    episodes without attributes encode exactly as before the attributes existed."""

    model: str
    """Body type from the catalog (``sedan``, ``suv`` ...; ``bus`` only in the rich look)."""
    colour: str
    position_world_m: Vec3
    yaw_rad: float
    roof: str | None = None
    """Colour name of a two-tone roof (greenhouse and roof in that colour), or None."""
    rack: bool = False
    """A roof rack carrying a cargo box."""
    stripe: str | None = None
    """Colour name of a stripe over the whole length and along both sides, or None."""


class TownRef(Part, kw_only=True):
    generator: str
    """A procedural generator (``grid``, ``irregular``, ``curved``, ``tee``, ``deck``, ``parks``)
    or ``opendrive`` for an imported map (found by its asset hash)."""
    seed: int
    town_id: str


class EpisodeSpec(Message, tag="episode_spec", kw_only=True):
    """One episode (a contract: docs/ARCHITECTURE.md §8). JSON, one per line in a split file."""

    episode_id: str
    """Versioned id, e.g. ``grid-s7-easy-000-v1``."""
    town: TownRef
    asset_sha256: str
    difficulty: Difficulty
    region_world_m: tuple[float, float, float, float]
    target: VehicleSpec
    distractors: list[VehicleSpec] = []
    uav_start_waypoint: str
    ugv_start_waypoint: str
    active_uav_waypoints: list[str]
    decision_budget: int = 80
    seed: int


class CandidateOutcome(Part, kw_only=True):
    candidate_id: str
    cell: str
    center_world_m: Vec2
    status: CandidateStatus
    distance_to_polygon_m: float
    """d_{e,j}: distance from the target centre to the candidate polygon (0 inside)."""
    center_error_m: float
    """Distance from the candidate centre to the target centre (CErr)."""


class LedgerEntry(Part, kw_only=True):
    """One transmission between the roles through the link model."""

    seq: int
    kind: Literal["sync", "beacon", "message"]
    """``sync``: coordination knowledge after a decision; ``beacon``: periodic re-broadcast;
    ``message``: agent text."""
    sender: Role
    receiver: Role
    sent_s: float
    size_bytes: int
    delivered: bool
    arrive_s: float | None = None
    delay_s: float | None = None
    drop_reason: str | None = None
    fault: Literal["duplicate", "corrupted"] | None = None
    """A delivered transmission the link harmed: ``duplicate`` (a second copy of the entry before it,
    same ``seq`` source) or ``corrupted`` (message text with characters changed)."""


class LinkStats(Part, kw_only=True):
    """Per-episode summary of the ledger (the episode summary's ``link`` field)."""

    profile: str
    sent: int
    delivered: int
    dropped: dict[str, int]
    delivery_rate: float | None
    mean_delay_s: float | None
    max_delay_s: float | None
    bytes_sent: int
    mean_info_age_s: dict[str, float | None]
    """Per role: mean age of the teammate information its decisions were based on."""
    candidates_delivered: int
    candidates_lost: int
    """Candidates the UGV never learned of."""
    duplicated: int = 0
    """Transmissions delivered twice (the ledger's ``fault = "duplicate"`` entries)."""
    corrupted: int = 0
    """Messages delivered with their text changed."""


class LoggedStep(Part, kw_only=True, omit_defaults=True):
    """One applied decision as the record keeps it: where the role was after it. The record's step
    log is what trajectory figures are drawn from (``agos plot``). Fields at their defaults are not
    written."""

    role: Role
    decision_index: int
    """The role's own 1-based decision index."""
    sim_time_s: float
    applied: ActionName
    position_world_m: Vec2
    """Where the role is after the decision (x, y)."""
    road_path_world_m: list[Vec2] = []
    """UGV drives only: the road polyline driven to ``position_world_m``, from the previous position
    (road-graph nodes, simplified to stay within 0.25 m of them)."""
    candidate_id: str | None = None
    """The candidate the action annotated, went to, confirmed or rejected."""
    candidate_polygon_world_m: list[Vec2] = []
    """ANNOTATE_CANDIDATE only: the new candidate's ground polygon."""
    pose_error_m: float | None = None
    """Horizontal distance between the pose the role was shown at this decision and its true pose
    (None: exact localisation)."""
    model_link_s: float | None = None
    """Simulated time the decision's request and reply spent on the link to the model (None: no link)."""
    model_bytes_up: int = 0
    model_bytes_down: int = 0


class PoseErrorStats(Part, kw_only=True):
    """One role's localisation error over its decisions: the horizontal distance between the pose it
    was shown and the truth (runtime/sensing.py)."""

    mean_m: float
    max_m: float
    degraded_share: float
    """Share of its decisions taken in the degraded zone (buildings crowding the sky)."""


class ModelLinkStats(Part, kw_only=True):
    """The link to the model over one episode (runtime/model_link.py): model-backed decisions only."""

    profile: str
    decisions: int
    bytes_up: int
    bytes_down: int
    link_time_s: float
    """Sum over decisions of the simulated time their requests and replies spent on the link."""
    max_link_time_s: float
    failed: int
    """Decisions whose request or reply was lost in every attempt the client makes (a counted WAIT)."""


class StoredTrace(DecisionTrace, kw_only=True):
    """A decision trace as stored with the episode: which role and decision it belongs to."""

    role: Role
    decision_index: int


class RoleTraceStats(Part, kw_only=True):
    """Per-role totals of the decision traces of an episode (model-backed policies)."""

    decisions: int
    http_attempts: int
    reasks: int
    repaired: int
    fallbacks: int
    """Replies that became the fallback action in the agent (no answer, unparseable, illegal)."""
    prompt_tokens: int
    completion_tokens: int
    mean_latency_s: float | None


class ModelUsage(Part, kw_only=True):
    """One model's calls in an episode, totalled from the decision traces answered with it: what the
    episode's token count and cost are computed from (docs/METRICS.md, "Tokens, cost and latency")."""

    model: str
    decisions: int
    """Decisions answered with this model (one trace each; fallbacks included)."""
    http_attempts: int
    """HTTP requests made for those decisions, re-asks and retries included."""
    prompt_tokens: int
    """Input tokens the endpoint reported, summed over the requests it answered (re-asks included)."""
    completion_tokens: int
    """Output tokens the endpoint reported, likewise."""


class EpisodeRecord(Message, tag="episode_record", kw_only=True):
    """World -> evaluator: the episode summary (the episode-summary fields plus provenance)."""

    run_id: str
    episode_id: str
    difficulty: Difficulty
    status: EpisodeStatus
    termination: Termination
    success: bool
    """C_e: ended with a CONFIRM accepted by the checker."""
    ground_observed: bool
    """O_e: a STOP_OBSERVE at some point would have passed the checker."""
    n_confirm: int
    ugv_path_length_m: float
    shortest_path_length_m: float | None
    """Road distance from the UGV start to the nearest pose where CONFIRM succeeds."""
    final_distance_m: float
    uav_budget: int
    """T_e: the episode's decision budget."""
    uav_first_visible_step: int | None
    """tau_e: first UAV decision (1-based) whose nadir view had the target oracle-visible."""
    candidates: list[CandidateOutcome]
    decisions_uav: int
    decisions_ugv: int
    fallbacks: int = 0
    """Decisions whose action was illegal, unparseable or late and became WAIT."""
    sim_time_s: float
    wall_time_s: float
    worker_id: str
    town_id: str
    asset_sha256: str
    seed: int
    renderer: str
    comm_profile: str = "ideal"
    timing_mode: Literal["lockstep", "realtime"] = "lockstep"
    link: LinkStats | None = None
    pose_error_profile: str = "exact"
    pose_error: dict[str, PoseErrorStats] = {}
    """Per role, its localisation error over its decisions (empty with exact localisation)."""
    model_link: ModelLinkStats | None = None
    """The link to the model (None: the model onboard, or no model)."""
    ledger: list[LedgerEntry] = []
    confirm_rejection: str | None = None
    """Why the checker refused the final CONFIRM (a false confirm), else None."""
    error: str | None = None
    """What went wrong in the infrastructure (status other than finished), else None."""
    tools: dict[str, bool] = {}
    """World-side tools the episode ran with (``candidates``, ``e2a``, ``rgpp``, ``oracle``)."""
    agent_stats: dict[str, RoleTraceStats] = {}
    """Per role, totals of its decision traces (empty for scripted policies)."""
    usage: list[ModelUsage] = []
    """Per model, in the order first used: the episode's decisions, requests and tokens (empty for
    scripted policies, and in records written before it existed: readers then total
    ``decision_traces``, which hold the same numbers per decision)."""
    decision_traces: list[StoredTrace] = []
    """Every decision of model-backed policies, in the order the world applied them."""
    step_log: list[LoggedStep] = []
    """Every applied decision of both roles, in order: the trajectories (empty in failure records)."""
    config: dict[str, Any] = {}
    """The episode configuration it ran with (``EpisodeConfig`` as a map; ``comm_profile``,
    ``timing_mode``, ``tools`` and ``renderer`` above repeat parts of it for readers)."""
    config_hash: str = ""
    """``EpisodeConfig.config_hash()`` of ``config``: records pool only under one hash."""
    provenance: dict[str, Any] = {}
    """What made the record (runtime/provenance.py): the agos commit and whether its tree was dirty,
    the uv.lock's sha256, the Python and package versions of the process that wrote it. Beside
    ``config``, never in it: not hashed, not scored; empty in records written before it existed."""

    @property
    def candidate_tools(self) -> bool:
        """The policy could annotate candidates (records are scored like summaries; see ACG)."""
        return self.tools.get("candidates", True)


class StepEvent(Message, tag="step", kw_only=True):
    """World -> observers and evaluator: one applied decision, with oracle facts."""

    run_id: str
    episode_id: str
    role: Role
    decision_index: int
    episode_step: int
    sim_time_s: float
    requested: Action | None
    applied: ActionName
    fallback_reason: str | None = None
    pose_after: Pose
    target_visible_uav: bool | None = None
    """Oracle (never shown to agents): target pixels in the nadir view above the threshold."""
    target_visible_ugv: bool | None = None
    """Oracle: the six views would pass the CONFIRM checker (after STOP_OBSERVE)."""
    candidate_id: str | None = None
    info_age_s: float | None = None
    """Age of the teammate information in this role's view when it decided."""
    pose_error_m: float | None = None
    """As in :class:`LoggedStep`."""
    model_link_s: float | None = None
    """As in :class:`LoggedStep`."""


class VizFrame(Message, tag="viz_frame", kw_only=True):
    """World -> observers (visualisation stream, lossy): one role's camera view at one decision, small."""

    run_id: str
    episode_id: str
    role: Role
    decision_index: int
    sim_time_s: float
    pose: Pose
    image: ImageFrame
    """On ``viz/<worker>/frame/<role>``: a JPEG of at most ``runtime.viz.THUMB_PX`` a side, the camera pose
    as in the observation, its intrinsics scaled to the thumbnail. On ``viz/<worker>/full/<role>`` (only
    while a recorder asks for full resolution): the observation's own image, as the agent got it. One
    frame per RGB view (six at a STOP_OBSERVE); ``image.name`` says which."""


class EpisodeStarted(Message, tag="episode_started", kw_only=True):
    run_id: str
    episode_id: str
    difficulty: Difficulty
    worker_id: str
    town_id: str
    asset_sha256: str


class ResultAck(Message, tag="result_ack", kw_only=True):
    run_id: str
    episode_id: str
    newly_stored: bool
    """False when the record was already stored (a duplicate submission)."""


class RunManifest(Message, tag="run_manifest", kw_only=True):
    run_id: str
    status: Literal["running", "finished", "interrupted"]
    policies: dict[str, str]
    comm_profile: str = "ideal"
    timing_mode: Literal["lockstep", "realtime"] = "lockstep"
    n_episodes: int
    created_utc: str
    config_hash: str = ""
    """Short hash of the run's episode configuration."""
    resumed: bool = False


class JobRequest(Message, tag="job_request", kw_only=True):
    worker_id: str
    give_back: str | None = None
    """An episode of this worker's lease it could not finish (its agents vanished mid-episode): the
    orchestrator leases it again as the next attempt."""
    why: str = ""
    outage: bool = False
    """The episode was given back because an agent's model endpoint gave no answer (``why`` is the
    agent's line): the orchestrator pauses it, and leases nothing, for ``[run] infra_wait_s``, then
    leases it again; after ``[run] max_infra_attempts`` such attempts it stores ``infra_error``."""


class JobGrant(Message, tag="job_grant", kw_only=True):
    worker_id: str = ""
    """The worker the grant is for (the requester's id): a worker runs only grants addressed to it."""
    episode: EpisodeSpec | None
    """The leased episode, or None when there is nothing left."""
    run_finished: bool = False
    attempt: int = 1
    """1 for the first lease; re-leases after a dead or stuck worker count up (at most 3)."""
    config: dict[str, Any] = {}
    """The run's whole episode configuration (``EpisodeConfig`` as a map, runtime/episode_config.py):
    the worker runs with exactly this, whatever its own settings."""


class LeaseNotice(Message, tag="lease", kw_only=True):
    """Orchestrator -> evaluator: who holds an episode's current lease. Published at every lease and
    again every few seconds while it lasts (an evaluator started late learns it); the evaluator
    stores a result only from the current holder."""

    run_id: str
    episode_id: str
    worker_id: str
    attempt: int


WireMessage = (
    CoordinationState
    | Observation
    | Action
    | AgentMessage
    | EpisodeSpec
    | EpisodeRecord
    | StepEvent
    | EpisodeStarted
    | ResultAck
    | RunManifest
    | JobRequest
    | JobGrant
    | LeaseNotice
    | VizFrame
)
"""Every top-level message; a payload's ``type`` says which (runtime/codec.py decodes through it)."""
