"""The episode summary: what every metric is computed from (DESIGN.md §7, a contract).

One JSON object per episode. :class:`~agos.runtime.schemas.EpisodeRecord` (what the world
submits and the evaluator stores) carries every field, so a run directory and a JSONL file of
summaries are read the same way. Extra fields are allowed and ignored.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError


class SummaryError(ValueError):
    """A bad summary line or run directory; the text names the file, the line and the field."""


class CandidateSummary(BaseModel):
    model_config = ConfigDict(strict=True, extra="ignore", frozen=True)

    distance_to_polygon_m: float = Field(ge=0)
    """d_{e,j}: target centre to the j-th candidate polygon, 0 when inside."""
    center_error_m: float = Field(ge=0)
    """Candidate centre to target centre (CErr)."""
    status: str | None = None
    """``pending``, ``arrived``, ``rejected``, ``confirmed`` or ``false_confirm`` (optional)."""


class EpisodeSummary(BaseModel):
    model_config = ConfigDict(strict=True, extra="ignore", frozen=True, use_attribute_docstrings=True)

    episode_id: str
    difficulty: Literal["easy", "mid", "hard"]
    success: bool
    """C_e."""
    ground_observed: bool
    """O_e (the osr flag)."""
    n_confirm: int = Field(ge=0)
    ugv_path_length_m: float = Field(ge=0)
    """P_e."""
    shortest_path_length_m: float | None = Field(default=None, ge=0)
    """L_e; may be null when the world could not find a verifying pose."""
    final_distance_m: float | None = Field(ge=0)
    """UGV-to-target distance at the end (NE); null when unknown."""
    uav_budget: int = Field(gt=0)
    """T_e."""
    uav_first_visible_step: int | None = Field(ge=1)
    """tau_e, 1-based; null if the target never became oracle-visible from the air."""
    candidates: list[CandidateSummary]
    """In annotation order (rank j = 1, 2, ...)."""
    decisions_uav: int = Field(ge=0)
    decisions_ugv: int = Field(ge=0)
    status: str = "finished"
    """Only ``finished`` episodes are scored; others are counted apart."""
    termination: str | None = None
    town_id: str | None = None
    run_id: str | None = None
    link: dict[str, Any] | None = None
    """Link statistics of degraded messaging (optional)."""


def _field_error(exc: ValidationError) -> str:
    err = exc.errors()[0]
    field = ".".join(str(p) for p in err["loc"]) or "<line>"
    return f"field '{field}': {err['msg']}"


def parse_summary_line(line: bytes | str, *, where: str) -> EpisodeSummary:
    try:
        return EpisodeSummary.model_validate_json(line)
    except ValidationError as exc:
        if exc.errors()[0]["type"] == "json_invalid":
            raise SummaryError(f"{where}: not valid JSON ({exc.errors()[0]['msg']})") from None
        raise SummaryError(f"{where}: {_field_error(exc)}") from None


def read_jsonl(path: Path) -> list[EpisodeSummary]:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise SummaryError(f"{path}: cannot read ({exc.strerror})") from None
    out = []
    for lineno, line in enumerate(data.splitlines(), start=1):
        if line.strip():
            out.append(parse_summary_line(line, where=f"{path}:{lineno}"))
    return out


def read_run(path: Path) -> list[EpisodeSummary]:
    """Summaries from a run directory (``results.sqlite``), a SQLite file, or a JSONL file."""
    from agos.evaluator.store import ResultStore

    if path.is_dir():
        path = path / "results.sqlite"
    if not path.exists():
        raise SummaryError(f"{path}: no such file or run directory")
    if path.suffix in (".sqlite", ".db"):
        store = ResultStore(path, create=False)
        try:
            return [parse_summary_line(raw, where=f"{path}:{eid}") for eid, raw in store.raw_records()]
        finally:
            store.close()
    return read_jsonl(path)
