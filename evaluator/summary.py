"""The episode summary: what every metric is computed from (a contract: docs/ARCHITECTURE.md §8, fields in docs/METRICS.md).

One JSON object per episode. :class:`~agos.runtime.schemas.EpisodeRecord` (what the world
submits and the evaluator stores) carries every field, so a run directory and a JSONL file of
summaries are read the same way. Extra fields are allowed and ignored.

Lines are validated by pydantic-core against a strict TypedDict (no string-to-number or
string-to-bool coercion) and then held in slotted dataclasses: validating into full models
cost 4x more, and ``agos metrics`` must stay within 3x of merely parsing the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, NotRequired

from pydantic import ConfigDict, Field, TypeAdapter, ValidationError, with_config
from typing_extensions import TypedDict  # pydantic needs this TypedDict before Python 3.12

from agos.runtime.schemas import Difficulty

NonNegative = Annotated[float, Field(ge=0)]
Count = Annotated[int, Field(ge=0)]


class SummaryError(ValueError):
    """A bad summary line or run directory; the text names the file, the line and the field."""


@with_config(ConfigDict(strict=True, extra="ignore"))
class _CandidateIn(TypedDict):
    distance_to_polygon_m: NonNegative
    center_error_m: NonNegative
    status: NotRequired[str | None]


@with_config(ConfigDict(strict=True, extra="ignore"))
class _UsageIn(TypedDict):
    model: str
    prompt_tokens: Count
    completion_tokens: Count


@with_config(ConfigDict(strict=True, extra="ignore"))
class _TraceIn(TypedDict):
    model: str
    latency_s: NonNegative
    prompt_tokens: NotRequired[Count | None]
    completion_tokens: NotRequired[Count | None]


@with_config(ConfigDict(strict=True, extra="ignore"))
class _SummaryIn(TypedDict):
    episode_id: str
    difficulty: Difficulty
    success: bool
    ground_observed: bool
    n_confirm: Count
    ugv_path_length_m: NonNegative
    shortest_path_length_m: NotRequired[NonNegative | None]
    final_distance_m: NonNegative | None
    uav_budget: Annotated[int, Field(gt=0)]
    uav_first_visible_step: Annotated[int, Field(ge=1)] | None
    candidates: list[_CandidateIn]
    decisions_uav: Count
    decisions_ugv: Count
    status: NotRequired[str]
    termination: NotRequired[str | None]
    town_id: NotRequired[str | None]
    run_id: NotRequired[str | None]
    link: NotRequired[dict[str, Any] | None]
    tools: NotRequired[dict[str, bool] | None]
    config_hash: NotRequired[str | None]
    config: NotRequired[dict[str, Any] | None]
    usage: NotRequired[list[_UsageIn]]
    decision_traces: NotRequired[list[_TraceIn]]
    pose_error: NotRequired[dict[str, Any] | None]
    model_link: NotRequired[dict[str, Any] | None]


_SUMMARY = TypeAdapter(_SummaryIn)


@dataclass(frozen=True, slots=True)
class CandidateSummary:
    distance_to_polygon_m: float
    """d_{e,j}: target centre to the j-th candidate polygon, 0 when inside."""
    center_error_m: float
    """Candidate centre to target centre (CErr)."""
    status: str | None = None
    """``pending``, ``arrived``, ``rejected``, ``confirmed`` or ``false_confirm`` (optional)."""


@dataclass(frozen=True, slots=True)
class UsageSummary:
    """One model's tokens in an episode (``EpisodeRecord.usage``): what its cost is computed from."""

    model: str
    prompt_tokens: int
    completion_tokens: int


def _usage(d: _SummaryIn) -> tuple[UsageSummary, ...]:
    """The episode's tokens per model: its ``usage``, else (records written before it existed, or
    made without it) the totals of its decision traces."""
    if d.get("usage"):
        return tuple(UsageSummary(u["model"], u["prompt_tokens"], u["completion_tokens"]) for u in d["usage"])
    totals: dict[str, list[int]] = {}
    for t in d.get("decision_traces", ()):
        tokens = totals.setdefault(t["model"], [0, 0])
        tokens[0] += t.get("prompt_tokens") or 0
        tokens[1] += t.get("completion_tokens") or 0
    return tuple(UsageSummary(model, p, c) for model, (p, c) in totals.items())


@dataclass(frozen=True, slots=True)
class EpisodeSummary:
    episode_id: str
    difficulty: str
    """``easy``, ``mid`` or ``hard``."""
    success: bool
    """C_e."""
    ground_observed: bool
    """O_e (the osr flag)."""
    n_confirm: int
    ugv_path_length_m: float
    """P_e."""
    shortest_path_length_m: float | None
    """L_e; null when the world could not find a verifying pose."""
    final_distance_m: float | None
    """UGV-to-target distance at the end (NE); null when unknown."""
    uav_budget: int
    """T_e."""
    uav_first_visible_step: int | None
    """tau_e, 1-based; null if the target never became oracle-visible from the air."""
    candidates: tuple[CandidateSummary, ...]
    """In annotation order (rank j = 1, 2, ...)."""
    decisions_uav: int
    decisions_ugv: int
    status: str = "finished"
    """Only ``finished`` episodes are scored; others are counted apart."""
    termination: str | None = None
    town_id: str | None = None
    run_id: str | None = None
    link: dict[str, Any] | None = None
    """Link statistics of degraded messaging (optional)."""
    candidate_tools: bool = True
    """The policy could annotate candidates (False for the Baseline: ACG is undefined, not 0)."""
    config_hash: str | None = None
    """Short hash of the episode configuration the episode ran with (None: not recorded)."""
    config: dict[str, Any] | None = None
    """That configuration (runtime/episode_config.py) as stored, to name what differs."""
    usage: tuple[UsageSummary, ...] = ()
    """Tokens per model of the episode's model calls (empty for scripted policies)."""
    decision_latencies_s: tuple[float, ...] = ()
    pose_error: dict[str, Any] | None = None
    """Per role, its localisation error over its decisions (``mean_m``, ``max_m``, ``degraded_share``);
    None with exact localisation."""
    model_link: dict[str, Any] | None = None
    """The link to the model (``EpisodeRecord.model_link``); None with the model onboard."""
    """Wall-clock latency of each traced decision (model-backed policies), re-asks and retries included."""

    @classmethod
    def from_valid(cls, d: _SummaryIn) -> EpisodeSummary:
        """From a line already validated against the summary schema."""
        return cls(
            d["episode_id"], d["difficulty"], d["success"], d["ground_observed"], d["n_confirm"],
            d["ugv_path_length_m"], d.get("shortest_path_length_m"), d["final_distance_m"], d["uav_budget"],
            d["uav_first_visible_step"],
            tuple(CandidateSummary(c["distance_to_polygon_m"], c["center_error_m"], c.get("status"))
                  for c in d["candidates"]),
            d["decisions_uav"], d["decisions_ugv"], d.get("status", "finished"), d.get("termination"),
            d.get("town_id"), d.get("run_id"), d.get("link"), (d.get("tools") or {}).get("candidates", True),
            d.get("config_hash"), d.get("config"), _usage(d),
            tuple(t["latency_s"] for t in d.get("decision_traces", ())), d.get("pose_error") or None,
            d.get("model_link"))

    @classmethod
    def model_validate(cls, data: dict[str, Any]) -> EpisodeSummary:
        """Validate a dict (raises pydantic's ValidationError)."""
        return cls.from_valid(_SUMMARY.validate_python(data))


def _field_error(exc: ValidationError) -> str:
    err = exc.errors()[0]
    field = ".".join(str(p) for p in err["loc"]) or "<line>"
    return f"field '{field}': {err['msg']}"


def parse_summary_line(line: bytes | str, *, where: str) -> EpisodeSummary:
    try:
        return EpisodeSummary.from_valid(_SUMMARY.validate_json(line))
    except ValidationError as exc:
        if exc.errors()[0]["type"] == "json_invalid":
            raise SummaryError(f"{where}: not valid JSON ({exc.errors()[0]['msg']})") from None
        raise SummaryError(f"{where}: {_field_error(exc)}") from None


def read_jsonl(path: Path) -> list[EpisodeSummary]:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SummaryError(f"{path}: cannot read ({exc.strerror})") from None
    return [parse_summary_line(line, where=f"{path}:{lineno}")
            for lineno, line in enumerate(data.splitlines(), start=1) if line.strip()]


def read_run(path: Path) -> list[EpisodeSummary]:
    """Summaries from a run directory (``results.sqlite``), a SQLite file, or a JSONL file."""
    from agos.evaluator.store import ResultStore

    if path.is_dir():
        path = path / "results.sqlite"
    if not path.exists():
        raise SummaryError(f"{path}: no such file or run directory")
    if path.suffix in (".sqlite", ".db"):
        import sqlite3

        try:
            store = ResultStore(path, create=False)
        except sqlite3.Error as exc:
            raise SummaryError(f"{path}: cannot open as a results database ({exc})") from None
        with store:
            try:
                rows = store.raw_records()
            except sqlite3.Error as exc:
                raise SummaryError(f"{path}: not an agos results database ({exc})") from None
        return [parse_summary_line(raw, where=f"{path}:{eid}") for eid, raw in rows]
    return read_jsonl(path)
