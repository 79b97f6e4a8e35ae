"""The expert's mTSP solvers (issue 19, performance goals): on small instances the fast solver's
makespan against the exact MILP's optimum (median and max ratio; goal median <= 1.02, none above
1.10), and solve times of full-size instances (the mid and hard regions) on one core (goal <= 10 s).

Instances are real: episodes sampled on each town (as ``agos episodes sample`` does), each turned
into the expert's first mTSP (world/expert/instance.py: waypoints, pairs, metric closures; no
rendering). Small instances are random sub-instances of those (the start and up to ``--small-uav``
UAV and ``--small-ugv`` UGV waypoints, the pairs among them). CP-SAT runs with one worker, HiGHS
with one thread.

    .venv/bin/python bench/bench_expert.py --towns grid-s7 parks-s23 Town10HD --per-cell 3 --out /tmp/bench-expert

``--quick`` (``make bench``): grid-s7, one episode per difficulty, 5 small instances each. ``--json``: also one
machine-readable line per figure (bench/figures.py). Exit status 1 when a goal is missed.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import numpy as np
from figures import Figures
from rich.console import Console
from rich.table import Table

ROOT = Path(__file__).resolve().parents[1]
CARLA = ROOT.parent / "shared" / "maps" / "carla"


def _town(name: str):
    from agos.world.towns.asset import freeze, open_town
    from agos.world.towns.imported import imported_layout

    if (CARLA / f"{name}.xodr").exists() and name.startswith("Town"):
        return freeze(imported_layout(CARLA / f"{name}.xodr"))
    return open_town(name)


def _sub_instance(inst, rng: np.random.Generator, n_uav: int, n_ugv: int):
    """The start and up to ``n_uav`` / ``n_ugv`` other nodes of each vehicle, with the pairs among them."""
    from agos.world.expert.mtsp import MtspInstance

    na, ng = inst.sizes
    keep_a = [0, *sorted(rng.choice(np.arange(1, na), size=min(n_uav, na - 1), replace=False).tolist())] if na > 1 else [0]
    keep_g = [0, *sorted(rng.choice(np.arange(1, ng), size=min(n_ugv, ng - 1), replace=False).tolist())] if ng > 1 else [0]
    pairs = tuple((keep_a.index(a), keep_g.index(g)) for a, g in inst.pairs if a in keep_a and g in keep_g)
    return MtspInstance(inst.uav_times_s[np.ix_(keep_a, keep_a)], inst.ugv_times_s[np.ix_(keep_g, keep_g)], pairs)


def main(argv: list[str] | None = None) -> int:
    from agos.runtime.episode_config import EpisodeConfig
    from agos.world.episodes.sampling import sample_episode
    from agos.world.expert.fast import solve_fast
    from agos.world.expert.instance import first_problem
    from agos.world.expert.milp import solve_milp
    from agos.world.expert.mtsp import check_solution
    from agos.world.sim.scene import Scene

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--towns", nargs="*", default=["grid-s7", "parks-s23", "deck-s19", "Town10HD", "Town01"])
    ap.add_argument("--per-cell", type=int, default=3, help="episodes per town and difficulty (mid, hard)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--small-per-episode", type=int, default=2)
    ap.add_argument("--small-uav", type=int, default=7)
    ap.add_argument("--small-ugv", type=int, default=4)
    ap.add_argument("--deterministic-time", type=float, default=5.0, help="CP-SAT's work limit (deterministic units)")
    ap.add_argument("--milp-full-limit", type=float, default=0.0,
                    help="also solve each full-size instance with the MILP, this many seconds at most (0: no)")
    ap.add_argument("--out", type=Path, default=None, help="write bench_expert.json here")
    ap.add_argument("--quick", action="store_true", help="grid-s7, one episode per difficulty, 5 small instances each")
    ap.add_argument("--json", action="store_true", help="also print each figure as a BENCH-FIGURE line")
    args = ap.parse_args(argv)
    if args.quick:
        args.towns, args.per_cell, args.small_per_episode = ["grid-s7"], 1, 5
    console = Console(width=160)
    cfg = EpisodeConfig()
    rng = np.random.default_rng(args.seed)
    full: list[dict] = []
    small: list[dict] = []
    for name in args.towns:
        town = _town(name)
        with Scene(town.layout, look="flat") as scene:
            for d, difficulty in ((1, "mid"), (2, "hard")):
                for index in range(args.per_cell):
                    spec = sample_episode(town, scene, difficulty, index, seed=args.seed, stream=d)  # type: ignore[arg-type]
                    _, problem = first_problem(town, spec, cfg)
                    inst = problem.instance
                    sol = solve_fast(inst, deterministic_time=args.deterministic_time)
                    assert not check_solution(inst, sol), check_solution(inst, sol)
                    row = {"episode": spec.episode_id, "difficulty": difficulty, "uav": inst.sizes[0], "ugv": inst.sizes[1],
                           "pairs": len(inst.pairs), "makespan_s": sol.makespan_s, "solve_s": sol.solve_wall_s,
                           "proved_optimal": sol.optimal}
                    if args.milp_full_limit > 0:
                        exact = solve_milp(inst, time_limit_s=args.milp_full_limit)
                        row.update(milp_makespan_s=exact.makespan_s, milp_solve_s=exact.solve_wall_s, milp_optimal=exact.optimal)
                    full.append(row)
                    for _ in range(args.small_per_episode):
                        sub = _sub_instance(inst, rng, args.small_uav, args.small_ugv)
                        exact = solve_milp(sub)
                        fast = solve_fast(sub, deterministic_time=args.deterministic_time)
                        assert not check_solution(sub, exact) and not check_solution(sub, fast)
                        small.append({"episode": spec.episode_id, "uav": sub.sizes[0], "ugv": sub.sizes[1],
                                      "pairs": len(sub.pairs), "milp_s": exact.makespan_s, "milp_optimal": exact.optimal,
                                      "milp_solve_s": exact.solve_wall_s, "fast_s": fast.makespan_s,
                                      "fast_solve_s": fast.solve_wall_s,
                                      "ratio": fast.makespan_s / exact.makespan_s if exact.makespan_s > 0 else 1.0})
                    console.print(f"{spec.episode_id}: {inst.sizes[0]} UAV + {inst.sizes[1]} UGV waypoints, "
                                  f"{len(inst.pairs)} pairs, "
                                  f"makespan {sol.makespan_s:.1f} s, CP-SAT {sol.solve_wall_s:.2f} s")
    ratios = [s["ratio"] for s in small]
    table = Table(title=f"small instances: CP-SAT vs the MILP optimum ({len(small)} instances)")
    for col in ("instances", "UAV nodes", "UGV nodes", "MILP proved", "ratio median", "ratio max", "> 1.02",
                "MILP s (median / max)"):
        table.add_column(col, justify="right")
    table.add_row(str(len(small)), f"{min(s['uav'] for s in small)}-{max(s['uav'] for s in small)}",
                  f"{min(s['ugv'] for s in small)}-{max(s['ugv'] for s in small)}", f"{sum(s['milp_optimal'] for s in small)}",
                  f"{statistics.median(ratios):.4f}", f"{max(ratios):.4f}", str(sum(r > 1.02 for r in ratios)),
                  f"{statistics.median(s['milp_solve_s'] for s in small):.2f} / {max(s['milp_solve_s'] for s in small):.2f}")
    console.print(table)
    table = Table(title="full-size instances: CP-SAT solve time on one core")
    milp = args.milp_full_limit > 0
    for col in ("difficulty", "instances", "UAV nodes", "UGV nodes", "pairs", "solve s median", "solve s max", "proved optimal",
                *(("MILP s median", "MILP s max", "MILP proved", "CP-SAT / MILP max") if milp else ())):
        table.add_column(col, justify="right")
    for difficulty in ("mid", "hard"):
        rows = [f for f in full if f["difficulty"] == difficulty]
        if rows:
            table.add_row(difficulty, str(len(rows)), f"{min(r['uav'] for r in rows)}-{max(r['uav'] for r in rows)}",
                          f"{min(r['ugv'] for r in rows)}-{max(r['ugv'] for r in rows)}",
                          f"{min(r['pairs'] for r in rows)}-{max(r['pairs'] for r in rows)}",
                          f"{statistics.median(r['solve_s'] for r in rows):.2f}", f"{max(r['solve_s'] for r in rows):.2f}",
                          f"{sum(r['proved_optimal'] for r in rows)}/{len(rows)}",
                          *((f"{statistics.median(r['milp_solve_s'] for r in rows):.2f}",
                             f"{max(r['milp_solve_s'] for r in rows):.2f}",
                             f"{sum(r['milp_optimal'] for r in rows)}/{len(rows)}",
                             f"{max(r['makespan_s'] / r['milp_makespan_s'] for r in rows):.4f}") if milp else ()))
    console.print(table)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "bench_expert.json").write_text(json.dumps({"small": small, "full": full}, indent=1))
    ok = statistics.median(ratios) <= 1.02 and max(ratios) <= 1.10 and max(f["solve_s"] for f in full) <= 10.0
    figures, slowest = Figures(args.json), max(f["solve_s"] for f in full)
    figures.add(f"CP-SAT vs MILP optimum, median of {len(small)} small instances", statistics.median(ratios),
                f"{statistics.median(ratios):.4f}", "<= 1.02", statistics.median(ratios) <= 1.02)
    figures.add(f"CP-SAT vs MILP optimum, worst of {len(small)} small instances", max(ratios), f"{max(ratios):.4f}",
                "<= 1.10", max(ratios) <= 1.10)
    figures.add(f"CP-SAT full-size solve, slowest of {len(full)}, one core", slowest, f"{slowest:.2f} s", "<= 10 s",
                slowest <= 10.0)
    console.print("goals met" if ok else "[red]goals missed")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
