"""The results table printed at the end of a run (rates in %, NE in metres, DS in decisions)."""

from __future__ import annotations

from rich.table import Table

from agos.evaluator.metrics import Summary


def _pct(v: float | None) -> str:
    return "n/a" if v is None else f"{100 * v:.1f}"


def _num(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.1f}"


def results_table(summaries: dict[str, Summary], *, title: str = "") -> Table:
    table = Table(title=title or None)
    for col in ("difficulty", "episodes", "SR %", "OSR %", "SPL %", "NE m", "DS", "not scored"):
        table.add_column(col, justify="left" if col == "difficulty" else "right")
    for level, s in summaries.items():
        table.add_row(level, str(s.n), _pct(s.SR), _pct(s.OSR), _pct(s.SPL), _num(s.NE), _num(s.DS), str(s.excluded),
                      end_section=level == "hard")
    return table


def results_markdown(summaries: dict[str, Summary]) -> str:
    lines = ["| difficulty | episodes | SR % | OSR % | SPL % | NE m | DS |", "|---|---:|---:|---:|---:|---:|---:|"]
    for level, s in summaries.items():
        lines.append(f"| {level} | {s.n} | {_pct(s.SR)} | {_pct(s.OSR)} | {_pct(s.SPL)} | {_num(s.NE)} | {_num(s.DS)} |")
    return "\n".join(lines)
