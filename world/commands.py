"""``agos map ...`` and ``agos episodes ...``: town assets and episode files."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def add_parsers(sub: argparse._SubParsersAction) -> None:
    from agos.runtime.schemas import DIFFICULTIES
    from agos.runtime.settings import DEFAULT_TOWN

    maps = sub.add_parser("map", help="town assets: import OpenDRIVE maps, inspect, render")
    map_sub = maps.add_subparsers(dest="map_command", required=True)
    imp = map_sub.add_parser("import", help="build a frozen town asset from an OpenDRIVE .xodr file")
    imp.add_argument("file", type=Path)
    imp.add_argument("--out", type=Path, required=True, help="asset directory to write")
    imp.add_argument("--seed", type=int, default=0, help="seed for buildings, props and parked traffic")
    build = map_sub.add_parser("build", help="freeze a procedural town into an asset directory")
    build.add_argument("town", help="grid-s7, curved-s13, ... or <generator>-s<seed>")
    build.add_argument("--out", type=Path, required=True)
    info = map_sub.add_parser("info", help="graph statistics and hash of a town")
    info.add_argument("town", help="asset directory or procedural town id")
    info.add_argument("--json", action="store_true")
    render = map_sub.add_parser("render", help="top-down PNG of a town with its graphs and UAV grid")
    render.add_argument("town")
    render.add_argument("--out", type=Path, required=True)
    render.add_argument("--size", type=int, default=1600)
    render.add_argument("--region", type=float, nargs=4, metavar=("X0", "Y0", "X1", "Y1"))

    episodes = sub.add_parser("episodes", help="episode files")
    ep_sub = episodes.add_subparsers(dest="episodes_command", required=True)
    sample = ep_sub.add_parser("sample", help="sample solvable episodes on one town")
    sample.add_argument("--town", default=DEFAULT_TOWN, help="procedural town id, asset directory or .xodr file")
    sample.add_argument("--difficulty", choices=DIFFICULTIES, help="one difficulty (with -n)")
    sample.add_argument("-n", type=int, default=1, help="episodes of --difficulty")
    sample.add_argument("--per-difficulty", type=int, help="episodes of every difficulty instead")
    sample.add_argument("--seed", type=int, default=1)
    _add_look(sample)
    sample.add_argument("--out", type=Path, required=True)
    split = ep_sub.add_parser("split", help="train/val over five towns and test on a held-out town")
    split.add_argument("--out", type=Path, required=True, help="directory for train/val/test.jsonl and manifest.json")
    split.add_argument("--preset", choices=["paper"],
                       help="paper: the five CARLA towns Town01, 02, 04, 06, 07 (in --maps) for train/val; "
                            "needs --test-town")
    split.add_argument("--towns", help="train/val towns, comma-separated: procedural ids, asset directories or "
                                       ".xodr files (default: the five procedural train/val towns)")
    split.add_argument("--test-town", help="the held-out test town, not among the train/val towns (default parks-s23)")
    split.add_argument("--maps", type=Path, default=Path("../shared/maps/carla"),
                       help="where --preset paper finds the CARLA .xodr files (default ../shared/maps/carla)")
    split.add_argument("--train", type=int, default=5500, help="train episodes (default 5500, the paper's)")
    split.add_argument("--val", type=int, default=2200, help="validation episodes (default 2200)")
    split.add_argument("--test", type=int, default=210, help="test episodes, on the held-out town (default 210)")
    split.add_argument("--seed", type=int, default=1)
    _add_look(split)
    split.add_argument("--workers", type=int, default=2)
    subset = ep_sub.add_parser("subset", help="a stratified subset: N episodes of every town x difficulty cell, "
                                             "drawn by seed, the split's lines unchanged (docs/DATASET.md)")
    subset.add_argument("split", type=Path, help="the episode file to draw from (e.g. a split's val.jsonl)")
    subset.add_argument("--per-cell", type=int, required=True, metavar="N", help="episodes per town x difficulty cell")
    subset.add_argument("--seed", type=int, default=0, help="which episodes of each cell (default 0)")
    subset.add_argument("--out", type=Path, required=True, help="the subset's JSONL file")
    check = ep_sub.add_parser("check", help="validate an episode file as every command that reads one does: each "
                                           "line, no episode id twice, each town as this agos builds it")
    check.add_argument("file", type=Path)
    check.add_argument("--look", choices=["flat", "rich"],
                       help="also check that this look draws every vehicle (the flat look has no bus and no attributes)")


def _add_look(parser: argparse.ArgumentParser) -> None:
    """``--look``: the look the episodes are sampled and checked with (rich episodes differ); its
    default is the episode configuration's, so the files match what ``agos eval`` draws by default."""
    from agos.runtime.episode_config import DEFAULT_LOOK

    parser.add_argument("--look", choices=["flat", "rich"], default=DEFAULT_LOOK,
                        help=f"the look to sample and check with (default {DEFAULT_LOOK}, as [world] look)")


def run(args: argparse.Namespace) -> int:
    from agos.world.towns.asset import AssetError, AssetMismatch

    try:
        if args.command == "map":
            return _map(args)
        return _episodes(args)
    except (AssetError, AssetMismatch, ValueError) as exc:
        print(f"{args.command} error: {exc}", file=sys.stderr)
        return 2


def map_info(town) -> dict:
    import networkx as nx
    import numpy as np

    roads = town.roads
    fine_len = [d["length_m"] for _, _, d in roads.fine.edges(data=True)]
    dec_len = [e.length_m for e in roads.decision_edges.values()]
    scc = max(nx.strongly_connected_components(roads.fine), key=len) if roads.fine.number_of_nodes() else set()
    kinds: dict[str, int] = {}
    for kind in roads.anchors.values():
        kinds[kind] = kinds.get(kind, 0) + 1
    return {
        "asset_id": town.town_id, "sha256": town.sha256, "lanes": len(town.layout.network.lanes),
        "fine_nodes": roads.fine.number_of_nodes(), "fine_edges": roads.fine.number_of_edges(),
        "decision_nodes": roads.decision.number_of_nodes(), "decision_edges": roads.decision.number_of_edges(),
        "uav_nodes": len(town.uav_grid.nodes),
        "median_fine_edge_m": round(float(np.median(fine_len)), 3) if fine_len else None,
        "median_decision_edge_m": round(float(np.median(dec_len)), 3) if dec_len else None,
        "largest_scc_fraction": round(len(scc) / max(1, roads.fine.number_of_nodes()), 4),
        "anchor_kinds": dict(sorted(kinds.items())), "buildings": len(town.layout.buildings),
        "trees": len(town.layout.trees), "decks": len(town.layout.decks), "parking_slots": len(town.layout.slots),
        "parked_vehicles": len(town.layout.parked), "warnings": len(town.layout.network.warnings),
    }


def _map(args: argparse.Namespace) -> int:
    from agos.world.towns.asset import cache_town, freeze, open_town, save_town

    if args.map_command == "import":
        from agos.world.towns.imported import imported_layout

        started = time.monotonic()
        layout = imported_layout(args.file, seed=args.seed)
        town = freeze(layout)
        save_town(town, args.out)
        cache_town(town)
        for warning in layout.network.warnings[:20]:
            print(f"warning: {warning}", file=sys.stderr)
        if len(layout.network.warnings) > 20:
            print(f"warning: ... and {len(layout.network.warnings) - 20} more (see manifest)", file=sys.stderr)
        info = map_info(town)
        print(f"imported {args.file.name} as {town.town_id} in {time.monotonic() - started:.1f} s: {info['lanes']} lanes, "
              f"{info['fine_nodes']} fine nodes, {info['decision_nodes']} anchors, {info['uav_nodes']} UAV nodes, "
              f"sha256 {town.sha256[:16]} -> {args.out}")
        return 0
    if args.map_command == "build":
        town = open_town(args.town)
        save_town(town, args.out)
        print(f"{town.town_id}: sha256 {town.sha256[:16]} -> {args.out}")
        return 0
    town = open_town(args.town)
    if args.map_command == "info":
        info = map_info(town)
        if args.json:
            print(json.dumps(info, indent=2))
        else:
            for key, value in info.items():
                print(f"{key:24s} {value}")
        return 0
    if args.map_command == "render":
        import cv2

        from agos.world.towns.topdown import debug_map

        nodes = [n.position_world_m for n in town.uav_grid.nodes.values()]
        image = debug_map(town.layout, town.roads, nodes, size_px=args.size, region=tuple(args.region) if args.region else None)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(args.out), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        print(args.out)
        return 0
    raise AssertionError(args.map_command)


def _episodes(args: argparse.Namespace) -> int:
    if args.episodes_command == "check":
        from agos.world.episodes.files import read_split

        episodes = read_split(args.file, look=args.look)
        towns = sorted({s.town.town_id for s in episodes})
        print(f"{args.file}: {len(episodes)} valid episodes on {', '.join(towns)}"
              + (f" ({args.look} look)" if args.look else ""))
        return 0
    if args.episodes_command == "subset":
        from agos.world.episodes.subset import write_subset

        print(write_subset(args.split, args.out, per_cell=args.per_cell, seed=args.seed).summary(args.per_cell, args.seed))
        return 0
    if args.episodes_command == "sample":
        return _sample(args)
    if args.episodes_command == "split":
        return _split(args)
    raise AssertionError(args.episodes_command)


def _sample(args: argparse.Namespace) -> int:
    """``agos episodes sample``, resumable (world/episodes/resumable_sampling.py): Ctrl-C leaves what is
    in ``OUT.partial`` and says so (exit 130); the same command again goes on from there."""
    from agos.world.episodes.resumable_sampling import ResumableSampling, SamplingInterrupted, sample_plan
    from agos.world.episodes.splits import resolve_town
    from agos.world.towns.asset import open_town

    # the plan before the town is built: a wrong count costs nothing
    plan = sample_plan(difficulty=args.difficulty, n=args.n, per_difficulty=args.per_difficulty)
    town = open_town(resolve_town(args.town).source)
    job = ResumableSampling(town, plan, args.out, seed=args.seed, look=args.look)
    if job.kept:
        print(f"going on from {job.partial}: {job.kept} of {job.total} episodes sampled before", flush=True)
    try:
        job.run()
    except SamplingInterrupted as stop:
        print(f"interrupted: {stop.kept} of {job.total} episodes kept in {job.partial}; run the same command "
              "again to go on", file=sys.stderr, flush=True)
        raise
    print(f"wrote {job.total} solvable episodes on {town.town_id} (asset {town.sha256[:12]}, {args.look} look) "
          f"to {args.out}")
    return 0


def _split(args: argparse.Namespace) -> int:
    """``agos episodes split``: resolve and check the towns (a bad one is one line, exit 2, before
    any sampling), then sample with a progress bar."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from agos.world.episodes.splits import PAPER_TRAINVAL_MAPS, SplitPlan, build_split, check_disjoint, paper_towns, resolve_town
    from agos.world.towns.procedural import TEST_TOWNS, TOWNS

    if args.preset == "paper":
        if args.towns:
            raise ValueError("--preset paper names the train/val towns itself: leave out --towns")
        if not args.test_town:
            raise ValueError(f"--preset paper needs --test-town T: the held-out test town, any procedural or imported "
                             f"town but {', '.join(PAPER_TRAINVAL_MAPS)} (e.g. parks-s23)")
        names = paper_towns(args.maps)
    elif args.towns:
        names = [n.strip() for n in args.towns.split(",") if n.strip()]
    else:
        names = [t for t in TOWNS if t not in TEST_TOWNS]
    trainval = tuple(resolve_town(n) for n in names)
    test_towns = tuple(resolve_town(n) for n in ([args.test_town] if args.test_town else TEST_TOWNS))
    check_disjoint(trainval, test_towns)
    for label, towns in (("train/val", trainval), ("test", test_towns)):
        print(f"{label}: " + ", ".join(f"{t.town_id} ({t.sha256[:12]})" for t in towns))
    plan = SplitPlan(trainval, test_towns, train=args.train, val=args.val, test=args.test, seed=args.seed,
                     look=args.look, preset=args.preset)
    total = sum(j.count for j in plan.jobs())
    with Progress(TextColumn("[bold]sampling"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn()) as bar:
        task = bar.add_task("episodes", total=total)
        manifest = build_split(args.out, plan, workers=args.workers, progress=lambda n: bar.advance(task, n))
    print(f"{args.out}: " + ", ".join(f"{k} {v}" for k, v in manifest["counts"].items())
          + f" ({args.look} look; manifest.json has the towns' and files' sha256)")
    return 0
