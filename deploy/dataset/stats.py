"""``agos dataset stats``: what an AGOS-Dataset directory holds, and the dataset's statistics figure.

    agos dataset stats DIR [--out FIGURE.png] [--markdown]

Contract: reads only what ``agos dataset build`` assembled (deploy/dataset/build.py): each
``DIR/episodes/<episode>/`` with ``episode.json``, ``files.sha256`` and per role ``decisions.jsonl``
and ``export.jsonl``, plus ``manifest.json`` for sizes when it lists the episode, and the sizes of
``DIR/export.jsonl`` (and its lines) and the run directory. Episodes still in ``.partial`` are not
counted; nothing is written but the figure. It prints one table, a column per difficulty and one overall (episodes,
towns, decisions per role, images per channel, views between decisions, export lines, disk, the
expert's t_f and t_arr, wrong-candidate episodes, distances), and draws the statistics figure
(``draw_figure``: four histograms per difficulty) to ``--out`` (default ``DIR/stats.png``). A
directory that is not a dataset raises :class:`StatsError` with one line naming it and what to do
(the command exits 2).

"Distance", as the figure draws it (the paper names a distance distribution without saying which):
the UGV's start-to-target distance by road, L_e of SPL (the road distance from the UGV's start to
the nearest place it can confirm the target from; the episode record's ``shortest_path_length_m``),
beside the lengths the expert travelled in its (truncated) trajectories: the UGV's driven length
(the record's ``ugv_path_length_m``) and the UAV's flown length (its straight legs between decision
points).
"""

from __future__ import annotations

import json
import math
import os
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agos.agents.dataset.writer import EPISODES
from agos.deploy.dataset.build import EPISODE_FILE, EXPORT, HASHES, MANIFEST
from agos.runtime.keys import ROLES
from agos.runtime.schemas import DIFFICULTIES

DEFAULT_FIGURE = "stats.png"
BAR_FROM = 500
"""Datasets of this many episodes or more are read under a progress bar (on stderr)."""
CHANNELS = ("rgb", "depth", "semantic")
"""Image channels counted on their own; ``rgb`` includes the UAV's grid overlay (``rgb_grid``)."""
CHANNEL_OF = {"rgb": "rgb", "rgb_grid": "rgb", "depth": "depth", "semantic": "semantic"}
COLOURS = {"easy": "#1b9e77", "mid": "#d95f02", "hard": "#7570b3"}
"""One colour per difficulty (a colour-blind safe qualitative set), the same in every panel."""


class StatsError(ValueError):
    """The directory cannot be summarised; the message names it and says what to do."""


@dataclass(frozen=True)
class EpisodeStats:
    """One assembled episode, as counted from its files."""

    episode_id: str
    difficulty: str
    town_id: str
    decisions: dict[str, int]
    """Lines of each role's ``decisions.jsonl``."""
    images: dict[str, int]
    """Image files at decisions and between them, per channel (``CHANNELS``)."""
    passed_views: int
    """Views rendered between decisions (each an RGB, a depth and a semantic image)."""
    image_files: int
    """Every ``.jpg``/``.png`` in ``files.sha256``: the channels plus maps, references, request images."""
    export_lines: int
    bytes: int
    t_f_s: float
    t_arr_s: float
    finder: str
    wrong_candidates: int
    road_distance_m: float | None
    """L_e: the UGV's road distance from its start to the nearest pose that confirms the target."""
    ugv_path_m: float
    uav_path_m: float

    @property
    def total_decisions(self) -> int:
        return sum(self.decisions.values())


@dataclass
class DatasetStats:
    """Every assembled episode of a dataset directory, and the directory's other files."""

    root: Path
    episodes: list[EpisodeStats]
    export_lines: int | None
    """Lines of ``DIR/export.jsonl`` (None: absent)."""
    other_bytes: dict[str, int] = field(default_factory=dict)
    """Bytes outside ``episodes/``: the export, the run directory, the manifest."""

    def groups(self) -> list[tuple[str, list[EpisodeStats]]]:
        """(difficulty, its episodes) in easy, mid, hard order (others after), then ("overall", all)."""
        found = sorted({e.difficulty for e in self.episodes},
                       key=lambda d: (DIFFICULTIES.index(d) if d in DIFFICULTIES else len(DIFFICULTIES), d))
        return [(d, [e for e in self.episodes if e.difficulty == d]) for d in found] + [("overall", self.episodes)]


# ----- reading --------------------------------------------------------------------------------
def read_dataset(root: Path, *, progress: Callable[[list[Path]], Iterable[Path]] | None = None) -> DatasetStats:
    """Count every assembled episode under ``root`` (module docstring); :class:`StatsError` if it is
    not a dataset directory or holds no assembled episode. ``progress`` wraps the episode directories
    as they are read (a progress bar)."""
    if not root.is_dir():
        raise StatsError(f"{root} is not a directory; give the --out directory of agos dataset build")
    ep_dirs = sorted(p.parent for p in (root / EPISODES).glob(f"*/{EPISODE_FILE}"))
    manifest = _read_json(root / MANIFEST) if (root / MANIFEST).is_file() else None
    if manifest is None and not ep_dirs:
        raise StatsError(f"{root} is not an AGOS-Dataset directory (no {MANIFEST}, no {EPISODES}/<episode>/{EPISODE_FILE}); "
                         "give the --out directory of agos dataset build")
    if not ep_dirs:
        raise StatsError(f"{root} holds no assembled episode yet; build or resume it with agos dataset build --split FILE "
                         f"--out {root}")
    sizes = {name: e.get("bytes") for name, e in (manifest or {}).get("episodes", {}).items()}
    episodes = [_episode(d, sizes.get(d.name)) for d in (progress(ep_dirs) if progress else ep_dirs)]
    export = root / EXPORT
    other = {EXPORT: export.stat().st_size if export.is_file() else 0,
             "run": sum(_tree_bytes(p) for p in root.glob("dataset-*") if p.is_dir()),
             MANIFEST: (root / MANIFEST).stat().st_size if (root / MANIFEST).is_file() else 0}
    return DatasetStats(root, episodes, _count_lines(export) if export.is_file() else None, other)


def _episode(ep_dir: Path, manifest_bytes: int | None) -> EpisodeStats:
    doc = _read_json(ep_dir / EPISODE_FILE)
    try:
        expert, outcome = doc["expert"], doc["outcome"]
        decisions: dict[str, int] = {}
        channels: Counter[str] = Counter()
        passed = export_lines = 0
        for role in ROLES:
            lines = _jsonl(ep_dir / role / "decisions.jsonl")
            decisions[role] = len(lines)
            for line in lines:
                channels.update(CHANNEL_OF.get(i["kind"], "other") for i in line["images"])
                for view in line["passed"]:
                    channels.update(CHANNEL_OF.get(i["kind"], "other") for i in view["images"])
                passed += len(line["passed"])
            export_lines += _count_lines(ep_dir / role / EXPORT)
        listed = (ep_dir / HASHES).read_text().splitlines() if (ep_dir / HASHES).is_file() else []
        road = outcome.get("shortest_path_length_m")
        return EpisodeStats(
            episode_id=doc["episode_id"], difficulty=doc["difficulty"], town_id=doc["town_id"], decisions=decisions,
            images={c: channels[c] for c in CHANNELS}, passed_views=passed,
            image_files=sum(1 for line in listed if line.endswith((".jpg", ".png"))), export_lines=export_lines,
            bytes=manifest_bytes if manifest_bytes is not None else _tree_bytes(ep_dir),
            t_f_s=float(expert["t_f_s"]), t_arr_s=float(expert["t_arr_s"]), finder=str(expert["finder"]),
            wrong_candidates=int(expert["wrong_candidates"]), road_distance_m=None if road is None else float(road),
            ugv_path_m=float(outcome["ugv_path_length_m"]), uav_path_m=_polyline_m(expert["trajectory"]["uav"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise StatsError(f"{ep_dir}: unreadable episode files ({type(exc).__name__}: {exc}); rebuild it with "
                         "agos dataset build (delete the episode's directory first)") from None


def _polyline_m(points: Sequence[dict[str, Any]]) -> float:
    """Length of the straight legs between a trajectory's decision points (the UAV flies straight)."""
    xy = [p["position_world_m"][:2] for p in points]
    return sum(math.dist(a, b) for a, b in zip(xy, xy[1:], strict=False))


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise StatsError(f"{path}: cannot be read ({exc}); is this directory a finished agos dataset build?") from None


def _jsonl(path: Path) -> list[dict[str, Any]]:
    try:
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    except (OSError, ValueError) as exc:
        raise StatsError(f"{path}: cannot be read ({exc}); rebuild the episode with agos dataset build") from None


def _count_lines(path: Path) -> int:
    if not path.is_file():
        return 0
    with path.open("rb") as f:
        return sum(chunk.count(b"\n") for chunk in iter(lambda: f.read(1 << 20), b""))


def _tree_bytes(root: Path) -> int:
    total = 0
    for dirpath, _dirs, files in os.walk(root):
        for name in files:
            total += os.stat(os.path.join(dirpath, name)).st_size
    return total


# ----- the table --------------------------------------------------------------------------------
def _mean(values: Iterable[float]) -> float | None:
    v = list(values)
    return sum(v) / len(v) if v else None


def _median(values: Iterable[float]) -> float | None:
    v = sorted(values)
    if not v:
        return None
    mid = len(v) // 2
    return v[mid] if len(v) % 2 else (v[mid - 1] + v[mid]) / 2


def _num(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:,.{digits}f}"


def table_rows(stats: DatasetStats) -> tuple[list[str], list[tuple[str, list[str]]]]:
    """The table as text: the column headers and (quantity, one cell per column) rows."""
    groups = stats.groups()
    headers = [name for name, _ in groups]

    def row(label: str, cell: Any) -> tuple[str, list[str]]:
        return label, [cell(eps) for _, eps in groups]

    def dec(role: str) -> Any:
        return lambda eps: f"{sum(e.decisions[role] for e in eps):,}"

    def total(attr: str) -> Any:
        return lambda eps: f"{sum(getattr(e, attr) for e in eps):,}"

    rows = [
        row("episodes", lambda eps: f"{len(eps):,}"),
        row("towns", lambda eps: f"{len({e.town_id for e in eps})}"),
        row("decisions UAV", dec("uav")),
        row("decisions UGV", dec("ugv")),
        row("decisions/episode, mean", lambda eps: _num(_mean(e.total_decisions for e in eps))),
        row("decisions/episode, range", lambda eps: f"{min(e.total_decisions for e in eps)}-"
            f"{max(e.total_decisions for e in eps)}"),
        row("image files", total("image_files")),
        row("  RGB (with UAV grid)", lambda eps: f"{sum(e.images['rgb'] for e in eps):,}"),
        row("  depth", lambda eps: f"{sum(e.images['depth'] for e in eps):,}"),
        row("  semantic", lambda eps: f"{sum(e.images['semantic'] for e in eps):,}"),
        row("  maps, refs, requests", lambda eps: f"{sum(e.image_files - sum(e.images.values()) for e in eps):,}"),
        row("views between decisions", total("passed_views")),
        row("export lines", total("export_lines")),
        row("disk MB", lambda eps: _num(sum(e.bytes for e in eps) / 1e6)),
        row("disk/episode MB, mean", lambda eps: _num(_mean(e.bytes / 1e6 for e in eps), 2)),
        row("expert t_f s, mean", lambda eps: _num(_mean(e.t_f_s for e in eps))),
        row("expert t_arr s, mean", lambda eps: _num(_mean(e.t_arr_s for e in eps))),
        row("UAV finds first", lambda eps: f"{sum(e.finder == 'uav' for e in eps):,}"),
        row("wrong-candidate episodes", lambda eps: f"{sum(e.wrong_candidates > 0 for e in eps):,}"),
        row("UGV-target road m, median", lambda eps: _num(_median(
            e.road_distance_m for e in eps if e.road_distance_m is not None), 0)),
        row("UGV driven m, median", lambda eps: _num(_median(e.ugv_path_m for e in eps), 0)),
        row("UAV flown m, median", lambda eps: _num(_median(e.uav_path_m for e in eps), 0)),
    ]
    return headers, rows


def markdown_table(stats: DatasetStats) -> str:
    """The table as GitHub markdown (for pasting into a paper's notes or an issue)."""
    headers, rows = table_rows(stats)
    lines = ["| quantity | " + " | ".join(headers) + " |", "|---|" + "---:|" * len(headers)]
    lines += [f"| {label.strip()} | " + " | ".join(cells) + " |" for label, cells in rows]
    return "\n".join(lines)


def rich_table(stats: DatasetStats) -> Any:
    from rich.table import Table

    headers, rows = table_rows(stats)
    table = Table(title=f"AGOS-Dataset {stats.root}", title_justify="left")
    table.add_column("quantity")
    for h in headers:
        table.add_column(h, justify="right", style="bold" if h == "overall" else None)
    for label, cells in rows:
        table.add_row(label, *cells)
    return table


def notes(stats: DatasetStats) -> list[str]:
    """Lines printed under the table: the towns, the directory's other files, and mismatches."""
    towns = Counter(e.town_id for e in stats.episodes)
    out = ["towns: " + ", ".join(f"{t} ({n})" for t, n in sorted(towns.items()))]
    episodes_b = sum(e.bytes for e in stats.episodes)
    total = episodes_b + sum(stats.other_bytes.values())
    out.append(f"directory: {total / 1e6:,.1f} MB (episodes {episodes_b / 1e6:,.1f}, {EXPORT} "
               f"{stats.other_bytes.get(EXPORT, 0) / 1e6:,.1f}, run {stats.other_bytes.get('run', 0) / 1e6:,.1f})")
    per_episode = sum(e.export_lines for e in stats.episodes)
    if stats.export_lines is None:
        out.append(f"{EXPORT} is missing: the build writes it at its end (run agos dataset build again to write it)")
    elif stats.export_lines != per_episode:
        out.append(f"{EXPORT} has {stats.export_lines:,} lines, the episodes {per_episode:,}: it predates the last "
                   "assembled episodes (run agos dataset build again to rewrite it)")
    return out


# ----- the figure -------------------------------------------------------------------------------
PANELS: tuple[tuple[str, str, str], ...] = (
    ("road_distance_m", "UGV start to target, by road (m)", "(a) distance to the target"),
    ("ugv_path_m", "UGV driven by the expert (m)", "(b) expert UGV path length"),
    ("uav_path_m", "UAV flown by the expert (m)", "(c) expert UAV path length"),
    ("total_decisions", "decisions per episode (UAV + UGV)", "(d) decision count"),
)
"""(EpisodeStats attribute, x label, panel title) of the figure's four panels."""


def draw_figure(stats: DatasetStats, out: Path) -> Path:
    """The statistics figure as a PNG at ``out``: per panel (``PANELS``) a histogram with the
    difficulties' bars side by side on shared bins, each difficulty's median a dashed line (its value
    in the legend); the title gives the episodes per difficulty and the towns."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = [(d, eps) for d, eps in stats.groups() if d != "overall"]
    colours = [COLOURS.get(d, "#666666") for d, _ in groups]
    fig, axes = plt.subplots(2, 2, figsize=(10, 7.2), constrained_layout=True)
    for ax, (attr, xlabel, title) in zip(axes.flat, PANELS, strict=True):
        values = [[float(v) for e in eps if (v := getattr(e, attr)) is not None] for _, eps in groups]
        integer = attr == "total_decisions"
        bins = _bins([v for vs in values for v in vs], integer=integer)
        unit = "" if integer else " m"
        drawn = [(d, vs, c) for (d, _), vs, c in zip(groups, values, colours, strict=True) if vs]
        if drawn:
            ax.hist([vs for _, vs, _ in drawn], bins=bins, color=[c for _, _, c in drawn], alpha=0.85,
                    label=[f"{d}  {_median(vs):.0f}{unit}" for d, vs, _ in drawn], rwidth=0.9)
            for _, vs, colour in drawn:
                ax.axvline(_median(vs), color=colour, linestyle="--", linewidth=1.2)
        ax.set_ylim(0, ax.get_ylim()[1] * 1.25)  # room for the legend above the bars
        ax.set_title(title, loc="left", fontsize=11)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("episodes")
        ax.yaxis.get_major_locator().set_params(integer=True)
        ax.grid(axis="y", alpha=0.3)
        ax.set_axisbelow(True)
        if drawn:
            ax.legend(fontsize=8, loc="upper right", framealpha=0.9, title="median (dashed)", title_fontsize=8)
    towns = sorted({e.town_id for e in stats.episodes})
    town_text = ", ".join(towns) if len(towns) <= 6 else f"{len(towns)} towns"
    per = ", ".join(f"{d} {len(eps):,}" for d, eps in groups)
    fig.suptitle(f"AGOS-Dataset statistics: {len(stats.episodes):,} episodes ({per}) on {town_text}", fontsize=12)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out


def _bins(values: list[float], *, integer: bool) -> Any:
    """Shared bin edges for one panel: 10-25 bins over the pooled range, on round numbers (whole
    numbers for counts)."""
    import numpy as np

    if not values:
        return 10
    lo, hi = min(values), max(values)
    n = int(min(25, max(10, round(math.sqrt(len(values)) * 2))))
    if integer:
        width = max(1, math.ceil((hi - lo + 1) / n))
        return np.arange(math.floor(lo) - 0.5, hi + width + 0.5, width)
    if hi - lo < 1e-9:
        return np.array([lo - 1.0, hi + 1.0])
    step = _nice_step((hi - lo) / n)
    return np.arange(math.floor(lo / step) * step, hi + step, step)


def _nice_step(raw: float) -> float:
    """The smallest of 1, 2, 2.5, 5 x 10^k at or above ``raw``, so bin edges are round numbers."""
    power = 10.0 ** math.floor(math.log10(raw))
    return next(m * power for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * power >= raw - 1e-12)


# ----- the command ------------------------------------------------------------------------------
def main(root: Path, out: Path | None = None, *, markdown: bool = False) -> int:
    """``agos dataset stats``: print the table and notes, draw the figure; the exit code (2, one line
    on stderr, when ``root`` is not a dataset)."""
    import sys

    from rich.console import Console
    from rich.progress import track

    def bar(dirs: list[Path]) -> Iterable[Path]:  # about 6 ms an episode: the full 7,700 take most of a minute
        if len(dirs) < BAR_FROM:
            return dirs
        return track(dirs, description="reading episodes", transient=True, console=Console(stderr=True))

    try:
        stats = read_dataset(root, progress=bar)
    except StatsError as exc:
        print(f"agos dataset stats: {exc}", file=sys.stderr)
        return 2
    console = Console()
    if markdown:
        print(markdown_table(stats))
    else:
        console.print(rich_table(stats))
    for line in notes(stats):
        console.print(line, highlight=False, soft_wrap=True)
    figure = draw_figure(stats, out if out is not None else root / DEFAULT_FIGURE)
    console.print(f"figure: {figure}", highlight=False, soft_wrap=True)
    return 0
