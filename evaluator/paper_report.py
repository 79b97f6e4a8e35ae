"""Paper-style reports: the main table, the ablation table, failure outcomes, the stage-wise plot.

Main table (like the paper's): one row per run, columns Easy / Mid / Hard x SR, OSR, SPL, NE,
DS, with NE over successful episodes (``--`` without one); a run labelled with a leading ``+``
(e.g. ``+AGOS-Agent``) is an agent variant of the row above and is indented. Runs of the human
policy (the Human reference, evaluator/human_row.py) come first, as in the paper, set off by a rule
in LaTeX. Ablation table: one row per run and difficulty with every metric, the all-episode final
distance FD and CErr, then the run's ``total`` row as the paper's ablation table makes it
(:func:`~agos.evaluator.metrics.ablation_total`: GVA, NE, FD and CErr pooled over episodes, the
rest averaged over the levels). Rates are printed in %, distances in metres, DS in decisions;
undefined is ``--``. The stage-wise chart shows the macro overall of each run, as the paper's figure.

Each SR cell of the main table carries its Wilson 95 % interval (evaluator/comparison.py::wilson_interval:
md and tex in brackets after the rate, csv in two columns of its own). The cost table gives, per run
and difficulty and for the run's total, the tokens, their cost at the run's prices, the cost per
success and the decisions' latency p50/p95 (evaluator/cost.py); the card of each run
(evaluator/card_reader.py) goes to ``card.md``.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from agos.evaluator.attribution import OUTCOMES, outcome_counts
from agos.evaluator.comparison import wilson_interval
from agos.evaluator.cost import CostSummary, PriceTable, cost_by_group
from agos.evaluator.metrics import DIFFICULTY_ORDER, Summary, ablation_total, aggregate
from agos.evaluator.summary import EpisodeSummary

MAIN_METRICS = ("SR", "OSR", "SPL", "NE", "DS")
ABLATION_METRICS = ("SR", "OSR", "SPL", "NE", "FD", "ASE", "ACG", "GVA", "GVA_support", "DS", "CErr")
PERCENT = {"SR", "OSR", "SPL", "ASE", "ACG", "GVA"}
UNDEFINED = "--"
"""How an undefined value is printed (the paper's "--" for an undefined NE)."""
TOTAL = "total"
"""The ablation table's last row of a run (the paper's "Total")."""


@dataclass
class RunResults:
    label: str
    episodes: list[EpisodeSummary]
    human: bool = False
    """A person played both roles (the Human reference row)."""
    prices: PriceTable | None = None
    """What the run's tokens cost (None: cost is undefined, ``--``)."""
    card: list[str] | None = None
    """The run's card as lines (evaluator/card_reader.py); None: none to show."""

    @property
    def indented(self) -> bool:
        return self.label.startswith("+")

    @property
    def name(self) -> str:
        return self.label.lstrip("+").strip()

    def summaries(self) -> dict[str, Summary]:
        """Per difficulty and the macro ``overall`` (the main table, the stage-wise chart)."""
        return aggregate(self.episodes, "difficulty")

    def costs(self) -> dict[str, CostSummary]:
        """Per difficulty present and the run's ``total``: tokens, cost, latency."""
        present = [d for d in DIFFICULTY_ORDER if any(e.difficulty == d for e in self.episodes)]
        return cost_by_group(self.episodes, self.prices, present, lambda e: e.difficulty)

    def sr_intervals(self) -> dict[str, tuple[float, float] | None]:
        """Per difficulty: the Wilson 95 % interval of SR over the scored episodes."""
        out: dict[str, tuple[float, float] | None] = {}
        for level in DIFFICULTY_ORDER:
            scored = [e for e in self.episodes if e.difficulty == level and e.status == "finished"]
            out[level] = wilson_interval(sum(e.success for e in scored), len(scored))
        return out

    def ablation_summaries(self) -> dict[str, Summary]:
        """Per difficulty and the ``total`` row of the ablation table."""
        levels = {k: v for k, v in self.summaries().items() if k != "overall"}
        return {**levels, TOTAL: ablation_total(self.episodes)}


def fmt(metric: str, value: float | int | None) -> str:
    if value is None:
        return UNDEFINED
    if metric == "GVA_support":
        return str(int(value))
    return f"{100 * value:.1f}" if metric in PERCENT else f"{value:.1f}"


def fmt_interval(interval: tuple[float, float] | None) -> str:
    """A rate's interval in %, ``[12.1, 48.2]``; ``--`` when undefined."""
    return UNDEFINED if interval is None else f"[{100 * interval[0]:.1f}, {100 * interval[1]:.1f}]"


def main_rows(runs: Sequence[RunResults], *, ci: str = "cell") -> tuple[list[str], list[list[str]]]:
    """The main table. ``ci``: ``cell`` puts SR's Wilson interval in its cell (md, tex, the console),
    ``columns`` in two columns after it (csv: numbers stay numbers)."""
    header = ["Method"]
    for d in DIFFICULTY_ORDER:
        for m in MAIN_METRICS:
            header.append(f"{d.capitalize()} {m}")
            if m == "SR" and ci == "columns":
                header += [f"{d.capitalize()} SR CI low", f"{d.capitalize()} SR CI high"]
    rows = []
    for run in runs:
        s, intervals = run.summaries(), run.sr_intervals()
        row = [run.label]
        for d in DIFFICULTY_ORDER:
            for m in MAIN_METRICS:
                value = fmt(m, getattr(s[d], m)) if d in s else "-"
                interval = intervals[d]
                if m == "SR" and ci == "columns":
                    row += [value, *(fmt("SR", v) for v in (interval or (None, None)))]
                elif m == "SR" and interval is not None:
                    row.append(f"{value} {fmt_interval(interval)}")
                else:
                    row.append(value)
        rows.append(row)
    return header, rows


def sr_rows(runs: Sequence[RunResults]) -> tuple[list[str], list[list[str]]]:
    """The console's success-rate table: per run, each difficulty's SR with its Wilson interval, the
    overall (macro) SR and the episodes scored, not scored, and of those the infra errors (no answer
    from the model endpoint in any attempt)."""
    header = ["Method", *(f"{d.capitalize()} SR % [95% CI]" for d in DIFFICULTY_ORDER), "Overall SR %", "scored",
              "not scored", "infra err"]
    rows = []
    for run in runs:
        s, intervals = run.summaries(), run.sr_intervals()
        cells = [f"{fmt('SR', s[d].SR)} {fmt_interval(intervals[d])}" if d in s and s[d].n else "-"
                 for d in DIFFICULTY_ORDER]
        overall = s["overall"]
        rows.append([run.label, *cells, fmt("SR", overall.SR), str(overall.n), str(overall.excluded),
                     str(overall.infra_errors)])
    return header, rows


COST_HEADER = ["Method", "Difficulty", "episodes", "decisions", "prompt tok", "completion tok", "tok/decision",
               "tok/episode", "cost USD", "USD/success", "p50 latency s", "p95 latency s"]
"""The cost table's columns (tokens are the endpoint's counts; latency is per traced decision)."""


def fmt_usd(value: float | None) -> str:
    """Dollars to four significant figures at least to the cent (``0.0123``, ``12.35``); ``--`` undefined."""
    if value is None:
        return UNDEFINED
    return f"{value:.2f}" if value >= 10 else f"{value:.4g}" if value else "0"


def cost_cells(c: CostSummary) -> list[str]:
    """The cost table's cells after Method and Difficulty (``--`` where undefined)."""
    def num(v: float | None, spec: str) -> str:
        return UNDEFINED if v is None else format(v, spec)

    return [str(c.episodes), str(c.decisions), f"{c.prompt_tokens:,}", f"{c.completion_tokens:,}",
            num(c.tokens_per_decision, ",.0f"), num(c.tokens_per_episode, ",.0f"), fmt_usd(c.cost_usd),
            fmt_usd(c.cost_per_success_usd), num(c.latency_p50_s, ".3f"), num(c.latency_p95_s, ".3f")]


def cost_rows(runs: Sequence[RunResults]) -> tuple[list[str], list[list[str]]]:
    """Per run, one row per difficulty and its ``total``: tokens, cost, cost per success, latency."""
    rows = []
    for run in runs:
        for level, c in run.costs().items():
            rows.append([run.name, level, *cost_cells(c)])
    return COST_HEADER, rows


def cards_markdown(runs: Sequence[RunResults]) -> str:
    """Every run's card, one fenced block each."""
    return "\n".join(f"```\n{chr(10).join(run.card)}\n```\n" for run in runs if run.card)


def _ablation_rows(runs: Sequence[RunResults]) -> tuple[list[str], list[list[str]]]:
    header = ["Condition", "Difficulty", *ABLATION_METRICS]
    rows = []
    for run in runs:
        for level, s in run.ablation_summaries().items():
            rows.append([run.name, level] + [fmt(m, getattr(s, m)) for m in ABLATION_METRICS])
    return header, rows


def _markdown(header: list[str], rows: list[list[str]], indent_col0: Sequence[bool] = ()) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] + ["---:"] * (len(header) - 1)) + "|"]
    for k, row in enumerate(rows):
        first = ("&nbsp;&nbsp;" + row[0].lstrip("+")) if k < len(indent_col0) and indent_col0[k] else row[0]
        lines.append("| " + " | ".join([first, *row[1:]]) + " |")
    return "\n".join(lines) + "\n"


def _csv(header: list[str], rows: list[list[str]]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf)
    writer.writerow(header)
    writer.writerows(rows)
    return buf.getvalue()


_TEX_SPECIAL = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
                "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}"}


def _tex_escape(text: str) -> str:
    return "".join(_TEX_SPECIAL.get(ch, ch) for ch in text)


def main_table_latex(runs: Sequence[RunResults]) -> str:
    _, rows = main_rows(runs)
    cols = "l" + ("r" * len(MAIN_METRICS)) * len(DIFFICULTY_ORDER)
    out = [r"\begin{tabular}{" + cols + "}", r"\toprule",
           " & " + " & ".join(rf"\multicolumn{{{len(MAIN_METRICS)}}}{{c}}{{{d.capitalize()}}}" for d in DIFFICULTY_ORDER)
           + r" \\",
           " ".join(rf"\cmidrule(lr){{{2 + k * len(MAIN_METRICS)}-{1 + (k + 1) * len(MAIN_METRICS)}}}"
                    for k in range(len(DIFFICULTY_ORDER))),
           "Method & " + " & ".join(list(MAIN_METRICS) * len(DIFFICULTY_ORDER)) + r" \\", r"\midrule"]
    for k, (run, row) in enumerate(zip(runs, rows, strict=True)):
        name = (r"\quad " if run.indented else "") + _tex_escape(run.name)
        cells = [cell.replace(" [", r" {\scriptsize[", 1) + "}" if " [" in cell else cell for cell in row[1:]]
        out.append(name + " & " + " & ".join(cells) + r" \\")
        if run.human and k + 1 < len(runs) and not runs[k + 1].human:
            out.append(r"\midrule")
    out += [r"\bottomrule", r"\end{tabular}"]
    return "\n".join(out) + "\n"


def ablation_table_latex(runs: Sequence[RunResults]) -> str:
    header, rows = _ablation_rows(runs)
    out = [r"\begin{tabular}{ll" + "r" * len(ABLATION_METRICS) + "}", r"\toprule",
           " & ".join(_tex_escape(h) for h in header) + r" \\", r"\midrule"]
    previous = None
    for row in rows:
        if previous is not None and row[0] != previous:
            out.append(r"\midrule")
        out.append(" & ".join([_tex_escape(row[0]) if row[0] != previous else "", *row[1:]]) + r" \\")
        previous = row[0]
    out += [r"\bottomrule", r"\end{tabular}"]
    return "\n".join(out) + "\n"


def outcome_rows(runs: Sequence[RunResults]) -> tuple[list[str], list[list[str]]]:
    header = ["Run", *OUTCOMES]
    return header, [[run.name] + [str(v) for v in outcome_counts(run.episodes).values()] for run in runs]


def comms_rows(runs: Sequence[RunResults]) -> tuple[list[str], list[list[str]]]:
    """Link statistics beside SR: delivery rate, delays, information age and drops per run
    (means over scored episodes that carry link statistics)."""
    header = ["Run", "SR", "profile", "delivered %", "mean delay s", "max delay s", "info age UAV s", "info age UGV s",
              "dropped", "candidates lost"]
    rows = []
    for run in runs:
        scored = [e for e in run.episodes if e.status == "finished"]
        links = [e.link for e in scored if e.link]

        def mean(values: list) -> str:
            vals = [v for v in values if v is not None]
            return f"{sum(vals) / len(vals):.2f}" if vals else "-"

        dropped: dict[str, int] = {}
        for link in links:
            for reason, n in (link.get("dropped") or {}).items():
                dropped[reason] = dropped.get(reason, 0) + n
        profiles = sorted({str(link.get("profile")) for link in links}) or ["-"]
        sr = run.summaries()["overall"].SR
        rows.append([run.name, fmt("SR", sr), "/".join(profiles),
                     mean([None if link.get("delivery_rate") is None else 100 * link["delivery_rate"] for link in links]),
                     mean([link.get("mean_delay_s") for link in links]), mean([link.get("max_delay_s") for link in links]),
                     mean([(link.get("mean_info_age_s") or {}).get("uav") for link in links]),
                     mean([(link.get("mean_info_age_s") or {}).get("ugv") for link in links]),
                     ", ".join(f"{k} {v}" for k, v in sorted(dropped.items())) or "0",
                     str(sum(int(link.get("candidates_lost", 0)) for link in links))])
    return header, rows


def sensing_rows(runs: Sequence[RunResults]) -> tuple[list[str], list[list[str]]]:
    """What the robots did not know or paid to ask, beside SR, CErr and ACG: each role's localisation error
    (mean over episodes of its mean, and the largest), the UGV's share of decisions in the degraded zone,
    the link to the model (time and bytes up per model-backed decision, exchanges lost), and messages the
    robot link duplicated or garbled."""
    header = ["Run", "SR", "CErr", "ACG", "pose error UAV m (max)", "pose error UGV m (max)", "UGV degraded %",
              "model link s/decision", "kB up/decision", "model link failed", "duplicated", "corrupted"]
    return header, [_sensing_row(run) for run in runs]


def _pose_error_cell(scored: Sequence[EpisodeSummary], role: str) -> str:
    stats = [e.pose_error[role] for e in scored if e.pose_error and role in e.pose_error]
    if not stats:
        return "-"
    return f"{sum(s['mean_m'] for s in stats) / len(stats):.2f} ({max(s['max_m'] for s in stats):.1f})"


def _sensing_row(run: RunResults) -> list[str]:
    scored = [e for e in run.episodes if e.status == "finished"]
    overall = run.summaries()["overall"]
    ugv = [e.pose_error["ugv"]["degraded_share"] for e in scored if e.pose_error and "ugv" in e.pose_error]
    links = [e.model_link for e in scored if e.model_link and e.model_link.get("decisions")]
    decisions = sum(m["decisions"] for m in links)
    faults = [e.link for e in scored if e.link]
    return [run.name, fmt("SR", overall.SR), fmt("CErr", overall.CErr), fmt("ACG", overall.ACG),
            _pose_error_cell(scored, "uav"), _pose_error_cell(scored, "ugv"),
            f"{100 * sum(ugv) / len(ugv):.0f}" if ugv else "-",
            f"{sum(m['link_time_s'] for m in links) / decisions:.2f}" if decisions else "-",
            f"{sum(m['bytes_up'] for m in links) / decisions / 1000:.0f}" if decisions else "-",
            str(sum(m.get("failed", 0) for m in links)) if links else "-",
            str(sum(int(link.get("duplicated", 0)) for link in faults)),
            str(sum(int(link.get("corrupted", 0)) for link in faults))]


def stage_chart(runs: Sequence[RunResults], path: Path) -> None:
    """Grouped bars of ASE, ACG and GVA (overall, %) per run, with GVA support annotated."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    metrics = ("ASE", "ACG", "GVA")
    overall = [run.summaries()["overall"] for run in runs]
    x = np.arange(len(runs))
    width = 0.26
    fig, ax = plt.subplots(figsize=(max(5.0, 1.6 * len(runs) + 2), 3.6), dpi=150)
    for k, metric in enumerate(metrics):
        values = [100 * (getattr(s, metric) or 0.0) for s in overall]
        bars = ax.bar(x + (k - 1) * width, values, width, label=metric)
        for bar, s in zip(bars, overall, strict=True):
            value = getattr(s, metric)
            text = "n/a" if value is None else f"{100 * value:.0f}"
            if metric == "GVA":
                text += f"\n(n={s.GVA_support})"
            ax.annotate(text, (bar.get_x() + bar.get_width() / 2, bar.get_height()), ha="center", va="bottom",
                        fontsize=7, xytext=(0, 2), textcoords="offset points")
    ax.set_xticks(x, [run.name for run in runs])
    ax.set_ylabel("overall (%)")
    ax.set_ylim(0, 119)
    ax.set_title("Stage-wise: ASE (search), ACG (handoff), GVA (verify)", fontsize=10)
    ax.legend(ncols=3, loc="upper right", fontsize=8, frameon=False)
    ax.spines[["top", "right"]].set_visible(False)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def write_report(runs: Sequence[RunResults], out_dir: Path) -> list[Path]:
    """Write every table (md, csv, tex), the cost table, the outcome counts, the stage-wise PNG and,
    for runs with one, the cards (``card.md``) to ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    runs = [r for r in runs if r.human] + [r for r in runs if not r.human]  # the Human reference first
    written: list[Path] = []

    def put(name: str, text: str) -> None:
        path = out_dir / name
        path.write_text(text)
        written.append(path)

    if any(r.card for r in runs):
        put("card.md", cards_markdown(runs))
    header, rows = main_rows(runs)
    put("main.md", _markdown(header, rows, [r.indented for r in runs]))
    put("main.csv", _csv(*main_rows(runs, ci="columns")))
    put("main.tex", main_table_latex(runs))
    def put_table(name: str, table: tuple[list[str], list[list[str]]]) -> None:
        put(f"{name}.md", _markdown(*table))
        put(f"{name}.csv", _csv(*table))

    put_table("cost", cost_rows(runs))
    put_table("ablation", _ablation_rows(runs))
    put("ablation.tex", ablation_table_latex(runs))
    put_table("outcomes", outcome_rows(runs))
    put_table("comms", comms_rows(runs))
    put_table("sensing", sensing_rows(runs))
    stage_chart(runs, out_dir / "stagewise.png")
    written.append(out_dir / "stagewise.png")
    return written
