"""The results table printed at the end of a run (rates in %, NE and FD in metres, DS in decisions;
undefined is ``--``, as in the paper's tables)."""

from __future__ import annotations

from rich.table import Table

from agos.evaluator.metrics import Summary

UNDEFINED = "--"


def _pct(v: float | None) -> str:
    return UNDEFINED if v is None else f"{100 * v:.1f}"


def _num(v: float | None) -> str:
    return UNDEFINED if v is None else f"{v:.1f}"


def results_table(summaries: dict[str, Summary], *, title: str = "") -> Table:
    table = Table(title=title or None)
    for col in ("difficulty", "episodes", "SR %", "OSR %", "SPL %", "NE m", "FD m", "DS", "not scored", "infra err"):
        table.add_column(col, justify="left" if col == "difficulty" else "right")
    for level, s in summaries.items():
        table.add_row(level, str(s.n), _pct(s.SR), _pct(s.OSR), _pct(s.SPL), _num(s.NE), _num(s.FD), _num(s.DS),
                      str(s.excluded), str(s.infra_errors), end_section=level == "hard")
    return table


def metrics_table(summaries: dict[str, Summary], *, title: str = "", group: str = "difficulty") -> Table:
    """Every metric per group: rates in %, NE, FD and CErr in metres, DS in decisions."""
    table = Table(title=title or None)
    for col in (group, "n", "SR", "OSR", "SPL", "NE", "FD", "ASE", "ACG", "GVA (support)", "DS", "DS UAV", "DS UGV", "CErr",
                "not scored", "infra err"):
        table.add_column(col, justify="left" if col == group else "right")
    for name, s in summaries.items():
        table.add_row(name, str(s.n), _pct(s.SR), _pct(s.OSR), _pct(s.SPL), _num(s.NE), _num(s.FD), _pct(s.ASE), _pct(s.ACG),
                      f"{_pct(s.GVA)} ({s.GVA_support})", _num(s.DS), _num(s.DS_UAV), _num(s.DS_UGV), _num(s.CErr),
                      str(s.excluded), str(s.infra_errors),
                      end_section=name == list(summaries)[-2] if len(summaries) > 1 else False)
    return table


def comparison_table(comparison) -> Table:
    table = Table()
    for col in ("metric", "A", "B", "A - B", "95% CI", "p (perm.)"):
        table.add_column(col, justify="left" if col == "metric" else "right")
    for m in comparison.metrics:
        scale = 100.0 if m.metric in ("SR", "OSR", "SPL", "ASE", "ACG", "GVA") else 1.0
        unit = " pp" if scale == 100.0 else ""

        def f(v, s=scale):
            return "n/a" if v is None else f"{s * v:.1f}"

        ci = "n/a" if m.ci_low is None else f"[{scale * m.ci_low:.1f}, {scale * m.ci_high:.1f}]{unit}"
        table.add_row(m.metric, f(m.a), f(m.b), f(m.diff) + (unit if m.diff is not None else ""), ci,
                      "n/a" if m.p_value is None else f"{m.p_value:.4f}")
    return table


def rows_table(header: list[str], rows: list[list[str]], *, title: str = "", by_first: bool = False) -> Table:
    """A table of text cells (the first column and a ``Difficulty`` column left, the others right);
    with ``by_first``, a rule wherever the first column changes (one block per run)."""
    table = Table(title=title or None)
    for k, col in enumerate(header):
        table.add_column(col, justify="left" if k == 0 or col == "Difficulty" else "right")
    for k, row in enumerate(rows):
        table.add_row(*row, end_section=by_first and k + 1 < len(rows) and rows[k + 1][0] != row[0])
    return table
