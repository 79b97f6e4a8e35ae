"""``agos plot``: the paper's representative-trajectory figures, from a run's stored records.

    agos plot episode RUN EPISODE --out FILE.png
    agos plot compare RUN_A RUN_B EPISODE --out FILE.png

Contract: a panel shows one episode of one run: the town around the episode region from above
(north up, axes in world metres), the region, the UAV's searchable waypoints, the UAV's and the
UGV's paths from their starts (the UGV's along the roads it drove), every candidate polygon
coloured by its final status, the target (ground truth), and where the UGV confirmed or rejected;
the title gives the policies and the outcome. ``compare`` draws two runs' panels on one map extent,
side by side. Data: deploy/reports/plot_data.py (the record's step log); map: deploy/reports/episode_map.py.
"""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Any

from agos.deploy.reports.episode_map import EpisodeMap, episode_map
from agos.deploy.reports.plot_data import EpisodeView, PlotError, first_finished, load_episode

__all__ = ["COLOURS", "PlotError", "plot_compare", "plot_episode"]

COLOURS = {
    "uav": "#0096ff", "ugv": "#e600c8", "target": "#ff2000", "region": "#1e1ec8", "area": "#303030",
    "pending": "#ffbe00", "arrived": "#ff7800", "rejected": "#6e6e6e", "confirmed": "#00b43c", "false_confirm": "#c80000",
}
"""Hex colours of what a figure draws (the tests look for the two paths' colours)."""
MAP_PX = 1024


def plot_episode(run: Path, episode_id: str | None, out: Path) -> Path:
    """One episode of one run as a PNG at ``out`` (None: the run's first finished episode)."""
    view = load_episode(run, episode_id or first_finished([run]))
    emap = episode_map(view.spec, MAP_PX, around_world_m=view.bounds_world_m())
    fig, axes = _figure(1)
    _panel(axes[0], view, emap)
    return _save(fig, out)


def plot_compare(run_a: Path, run_b: Path, episode_id: str | None, out: Path, labels: list[str] | None = None) -> Path:
    """The same episode in two runs (two policies), side by side on one map extent (None: the first
    episode both runs finished)."""
    episode_id = episode_id or first_finished([run_a, run_b])
    views = [load_episode(run_a, episode_id), load_episode(run_b, episode_id)]
    if views[0].spec.asset_sha256 != views[1].spec.asset_sha256 or views[0].spec.target != views[1].spec.target:
        raise PlotError(f"{episode_id} is not the same episode in {views[0].run_dir.name} and {views[1].run_dir.name}")
    bounds = [v.bounds_world_m() for v in views]
    around = (min(b[0] for b in bounds), min(b[1] for b in bounds), max(b[2] for b in bounds), max(b[3] for b in bounds))
    emap = episode_map(views[0].spec, MAP_PX, around_world_m=around)
    fig, axes = _figure(2)
    for k, (ax, view) in enumerate(zip(axes, views, strict=True)):
        _panel(ax, view, emap, title=labels[k] if labels else None)
    return _save(fig, out)


def _figure(panels: int) -> tuple[Any, list[Any]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, panels, figsize=(6.4 * panels, 7.0), dpi=150, squeeze=False)
    return fig, list(axes[0])


def _panel(ax: Any, view: EpisodeView, emap: EpisodeMap, title: str | None = None) -> None:
    from matplotlib.patches import Polygon, Rectangle

    spec, record = view.spec, view.record
    x0, y0, x1, y1 = emap.frame.extent_world_m
    if emap.rgb is not None:
        ax.imshow(emap.rgb, extent=(x0, x1, y0, y1), origin="upper", interpolation="bilinear", zorder=0)
    else:
        ax.text(0.5, 0.01, textwrap.fill(f"no town map here: {emap.missing}", 80), transform=ax.transAxes, fontsize=6,
                ha="center", va="bottom", color="#555555")
    rx0, ry0, rx1, ry1 = spec.region_world_m
    ax.add_patch(Rectangle((rx0, ry0), rx1 - rx0, ry1 - ry0, fill=False, ls="--", lw=1.2, ec=COLOURS["region"],
                           zorder=2, label="episode region"))
    if emap.search_area_world_m:
        xs, ys = zip(*emap.search_area_world_m, strict=True)
        ax.scatter(xs, ys, s=6, c=COLOURS["area"], marker="+", lw=0.6, zorder=2, label="UAV waypoints (searchable)")
    for cid, polygon in sorted(view.candidates.items()):
        status = next((c.status for c in record.candidates if c.candidate_id == cid), "pending")
        ax.add_patch(Polygon(polygon, closed=True, fc=COLOURS[status], ec=COLOURS[status], alpha=0.35, lw=1.5, zorder=3,
                             label=f"candidate: {status}"))
        cx, top = sum(p[0] for p in polygon) / len(polygon), max(p[1] for p in polygon)
        cell = next((c.cell for c in record.candidates if c.candidate_id == cid), "")
        ax.annotate(f"{cid} {cell}", (cx, top), xytext=(0, 3), textcoords="offset points", fontsize=7, ha="center",
                    va="bottom", zorder=6,
                    bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.7})
    for role, path in (("ugv", view.ugv_path_world_m), ("uav", view.uav_path_world_m)):
        start = emap.starts_world_m.get(role)  # type: ignore[call-overload]
        points = ([start] if start else []) + path
        if points:
            xs, ys = zip(*points, strict=True)
            ax.plot(xs, ys, color=COLOURS[role], lw=2.4 if role == "ugv" else 1.8, zorder=4, solid_capstyle="round",
                    marker="o" if role == "uav" else None, ms=3.5, label=f"{role.upper()} path")
            if start:  # where it started is known from the town only
                ax.scatter([xs[0]], [ys[0]], s=70, marker="s", c=COLOURS[role], edgecolors="black", lw=0.8, zorder=5,
                           label=f"{role.upper()} start")
    tx, ty = spec.target.position_world_m[:2]
    ax.scatter([tx], [ty], s=240, marker="*", c=COLOURS["target"], edgecolors="black", lw=0.8, zorder=7,
               label=f"target ({spec.target.colour} {spec.target.model})")
    for event in view.ugv_events:
        ok = event.action == "CONFIRM" and record.success
        colour = COLOURS["confirmed"] if ok else COLOURS["false_confirm"] if event.action == "CONFIRM" else COLOURS["rejected"]
        marker = "P" if event.action == "CONFIRM" else "X"
        ax.scatter([event.xy_world_m[0]], [event.xy_world_m[1]], s=130, marker=marker, c=colour, edgecolors="black",
                   lw=0.8, zorder=8, label=f"{event.action}" + (" (accepted)" if ok else " (refused)" if event.action ==
                                                                   "CONFIRM" else ""))
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.tick_params(labelsize=7)
    outcome = f"{record.termination} ({'success' if record.success else 'failure'})"
    ax.set_title(f"{title or view.label}: {outcome}\n{spec.episode_id} · decisions UAV {record.decisions_uav}, "
                 f"UGV {record.decisions_ugv} · UGV path {record.ugv_path_length_m:.0f} m"
                 + (f" (shortest {record.shortest_path_length_m:.0f} m)" if record.shortest_path_length_m else ""),
                 fontsize=9)


def _save(fig: Any, out: Path) -> Path:
    """Lay out, add one legend under the panels (each label once, from every panel) and write."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    seen: dict[str, Any] = {}
    for axis in fig.axes:
        for handle, label in zip(*axis.get_legend_handles_labels(), strict=True):
            seen.setdefault(label, handle)
    below = min(axis.get_position().y0 for axis in fig.axes)
    fig.legend(list(seen.values()), list(seen), loc="upper center", bbox_to_anchor=(0.5, below - 0.06),
               ncol=3 if len(fig.axes) == 1 else 5, fontsize=8, frameon=False)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, bbox_inches="tight", pad_inches=0.1)
    plt.close(fig)
    return out
