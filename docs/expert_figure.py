"""Draw one episode's expert plan (docs/DATASET.md): left, Stage 1 (the searchable ground, both roles'
waypoints, the IoU pairs and the raw mTSP trajectories Tra_0); right, Stage 2 (the trajectories
truncated at t_f, the handoff path, the candidates).

    .venv/bin/python docs/expert_figure.py --town parks-s23 --out docs/images/expert_plan.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np


def main(argv: list[str] | None = None) -> int:
    from agos.runtime.episode_config import EpisodeConfig, ToolConfig
    from agos.world.episodes.sampling import sample_episode
    from agos.world.expert.coverage import ground_raster
    from agos.world.expert.planner import plan_episode
    from agos.world.sim.engine import EpisodeRunner
    from agos.world.sim.options import shortest_path
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import open_town
    from agos.world.towns.roadgraph import RoadGraphs

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--town", default="parks-s23")
    ap.add_argument("--difficulty", default="hard")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("docs/images/expert_plan.png"))
    args = ap.parse_args(argv)
    town = open_town(args.town)
    with Scene(town.layout, look="flat") as scene:
        roads, grid = town.roads, town.uav_grid
        for index in range(12):  # the first episode with a wrong candidate, else the last tried
            spec = sample_episode(town, scene, args.difficulty, index, seed=args.seed, stream=2)
            runner = EpisodeRunner(scene, town, spec, run_id="fig", worker_id="fig",
                                   config=EpisodeConfig(look="flat", tools=ToolConfig(expert=True)))
            runner._setup()
            try:
                plan = plan_episode(runner.state)
            finally:
                runner.teardown()
            if plan.wrong_candidates or args.difficulty != "hard":
                break
    ground = ground_raster(town, spec.region_world_m)
    x0, y0, x1, y1 = spec.region_world_m
    img = np.ones((*ground.shape, 3))
    img[ground.offroad] = (0.80, 0.92, 0.78)
    img[ground.road] = (0.78, 0.78, 0.80)
    img[ground.covered] = (0.55, 0.55, 0.60)
    img[ground.blocked] = (0.90, 0.84, 0.76)
    cov = plan.coverage

    def node_xy(n: str) -> tuple[float, float]:
        p = grid.nodes[n].position_world_m
        return p[0], p[1]

    def anchor_xy(a: int) -> tuple[float, float]:
        p = roads.positions_world_m[a]
        return float(p[0]), float(p[1])

    def road_line(points) -> np.ndarray:
        ids = [RoadGraphs.parse_anchor_id(p.waypoint_id) for p in points]
        fine = [ids[0]]
        for a, b in zip(ids, ids[1:], strict=False):
            fine += shortest_path(roads, a, b)[1:]
        return roads.positions_world_m[fine]

    fig, axes = plt.subplots(1, 2, figsize=(15, 7.6))
    for ax in axes:
        ax.imshow(img, origin="lower", extent=(x0, x0 + ground.shape[1] * 2.0, y0, y0 + ground.shape[0] * 2.0))
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_aspect("equal")
        t = spec.target.position_world_m
        ax.plot(t[0], t[1], marker="*", color="gold", markeredgecolor="k", markersize=18, zorder=6, label="target")
        for d in spec.distractors:
            ax.plot(d.position_world_m[0], d.position_world_m[1], marker="X", color="orange", markeredgecolor="k",
                    markersize=11, zorder=6)
    ax = axes[0]
    paired_uav = {a for a, _ in cov.pairs}
    for n in cov.uav_nodes:
        ax.plot(*node_xy(n), "o", color="tab:purple" if n in paired_uav else "tab:blue", markersize=9, zorder=4)
    for g in cov.ugv_nodes:
        ax.plot(*anchor_xy(g), "s", color={"deck": "tab:orange", "start": "k"}.get(cov.ugv_reason[g], "tab:purple"),
                markersize=7, zorder=4)
    for a, g in cov.pairs:
        ax.plot(*zip(node_xy(a), anchor_xy(g), strict=True), "-", color="tab:purple", linewidth=1, zorder=3)
    uav_raw = np.array([node_xy(p.waypoint_id) for p in plan.raw["uav"]])
    ax.plot(uav_raw[:, 0], uav_raw[:, 1], "--", color="tab:blue", linewidth=1.6, zorder=2, label="UAV Tra_0")
    ugv_raw = road_line(plan.raw["ugv"])
    ax.plot(ugv_raw[:, 0], ugv_raw[:, 1], "--", color="tab:red", linewidth=1.6, zorder=2, label="UGV Tra_0")
    ax.plot([], [], "o", color="tab:blue", label="UAV waypoint (exclusive)")
    ax.plot([], [], "o", color="tab:purple", label="paired (IoU >= 0.8)")
    ax.plot([], [], "s", color="tab:orange", label="UGV waypoint under a deck")
    ax.set_title(f"Stage 1: {len(cov.uav_nodes)} UAV + {len(cov.ugv_nodes)} UGV waypoints, {len(cov.pairs)} pairs; "
                 f"makespan {plan.solutions[0].makespan_s:.0f} s")
    ax.legend(loc="lower left", fontsize=8)
    ax = axes[1]
    uav = np.array([node_xy(p.waypoint_id) for p in plan.trajectories["uav"]])
    ax.plot(uav[:, 0], uav[:, 1], "-o", color="tab:blue", linewidth=2.2, markersize=4, zorder=4, label="UAV Tra (to t_f)")
    ugv = road_line(plan.trajectories["ugv"])
    ax.plot(ugv[:, 0], ugv[:, 1], "-", color="tab:red", linewidth=2.2, zorder=4, label="UGV Tra (+ handoff to t_arr)")
    ax.plot(*anchor_xy(RoadGraphs.parse_anchor_id(plan.trajectories["ugv"][-1].waypoint_id)), "D", color="tab:red",
            markeredgecolor="k", markersize=10, zorder=5, label="STOP_OBSERVE + CONFIRM")
    ax.plot(*uav[-1], "v", color="tab:blue", markeredgecolor="k", markersize=12, zorder=5, label="UAV at t_f")
    ax.set_title(f"Stage 2: t_f {plan.t_f_s:.0f} s (found by the {plan.finder.upper()}), t_arr {plan.t_arr_s:.0f} s, "
                 f"{plan.decisions} decisions, {plan.wrong_candidates} wrong candidate(s)")
    ax.legend(loc="lower left", fontsize=8)
    fig.suptitle(f"{spec.episode_id}: the expert's plan")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out} ({spec.episode_id})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
