"""The dataset commands' parser (deploy/dataset/; docs/DATASET.md).

    agos dataset build --split FILE --out DIR ...   the expert's trajectories, actions, messages and images
    agos dataset stats DIR                          counts and the statistics figure (reads files only)
    agos dataset shard --split FILE --shards N --out DIR   the split as N shard files, one build each (Slurm array)
    agos dataset merge DIR --out OUT                the shards' builds as one dataset, a one-host build's files
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from agos.deploy.cli.common import Command, by_subcommand, with_settings
from agos.deploy.dataset import DEFAULT_CAPTURE_EVERY_M
from agos.runtime.episode_config import DEFAULT_LOOK
from agos.runtime.settings import AgosConfig


def _add_dataset(sub: Any) -> None:
    ds = sub.add_parser("dataset", help="AGOS-Dataset: expert trajectories, actions, messages and images (docs/DATASET.md)")
    ds_sub = ds.add_subparsers(dest="dataset_command", required=True)
    dsb = ds_sub.add_parser("build", help="build (or resume) the dataset of an episode split with leased world workers")
    dsb.add_argument("--config", type=Path)
    dsb.add_argument("--split", type=Path, required=True, help="JSONL episode file (e.g. a split's train.jsonl)")
    dsb.add_argument("--out", type=Path, required=True, help="dataset directory (run the command again to resume)")
    dsb.add_argument("--workers", type=int, default=1, help="local world worker processes (default 1)")
    dsb.add_argument("--look", choices=["rich", "flat"], default=DEFAULT_LOOK,
                     help=f"how the world draws the episodes (default {DEFAULT_LOOK}: the textured city the dataset is for)")
    dsb.add_argument("--capture-every", type=float, default=DEFAULT_CAPTURE_EVERY_M, metavar="M",
                     help=f"also render each role's camera every M metres between decisions (default {DEFAULT_CAPTURE_EVERY_M:g})")
    dsb.add_argument("--connect", help="attach to a router and processes started by hand (agents with --dataset-out DIR)")
    dsb.add_argument("--run", dest="run_id", help="run id (with --connect)")
    dsb.add_argument("--port", type=int)
    dss = ds_sub.add_parser("stats", help="counts per difficulty and the dataset's statistics figure (reads files only)")
    dss.add_argument("dir", type=Path, help="dataset directory (the --out of agos dataset build)")
    dss.add_argument("--out", type=Path, help="figure PNG (default DIR/stats.png)")
    dss.add_argument("--markdown", action="store_true", help="print the table as markdown (to paste)")
    dsh = ds_sub.add_parser("shard", help="split an episode split into N shard files, each built on its own "
                                          "(a Slurm array task), then merged with agos dataset merge")
    dsh.add_argument("--split", type=Path, required=True, help="JSONL episode file (e.g. a split's train.jsonl)")
    dsh.add_argument("--shards", type=int, required=True, metavar="N", help="how many shards (round-robin)")
    dsh.add_argument("--out", type=Path, required=True,
                     help="shard directory: DIR/shards.json, DIR/splits/<k>.jsonl; the builds go to DIR/shards/<k>")
    dsm = ds_sub.add_parser("merge", help="merge the builds of agos dataset shard's shards into one dataset, the "
                                          "files a one-host build of the split writes")
    dsm.add_argument("dir", type=Path, help="shard directory (the --out of agos dataset shard)")
    dsm.add_argument("--out", type=Path, required=True, help="dataset directory to write (run again to finish a merge)")
    dsm.add_argument("--link", action="store_true",
                     help="hard-link the episodes' files instead of copying them (same filesystem; leave both read-only)")


def _build(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from agos.deploy.dataset import build
    from agos.deploy.run.plan import RunDirError
    from agos.world.episodes.files import read_split

    if args.connect and not args.run_id:
        print("dataset error: --connect needs --run RUN (the run id the attached processes serve)", file=sys.stderr)
        return 2
    if args.capture_every <= 0:
        print(f"dataset error: --capture-every {args.capture_every}: give a distance in metres above 0", file=sys.stderr)
        return 2
    try:
        read_split(args.split, look=args.look)  # a bad split fails here, before any process starts
        return build.build(cfg, args.split, args.out, workers=args.workers, capture_every_m=args.capture_every,
                           look=args.look, attach=args.connect is not None, port=args.port, config_path=args.config)
    except (build.DatasetError, RunDirError) as exc:
        print(f"dataset error: {exc}", file=sys.stderr)
        return 2


def _stats(args: argparse.Namespace) -> int:
    """``agos dataset stats``: reads files only, no settings."""
    from agos.deploy.dataset import stats

    return stats.main(args.dir, args.out, markdown=args.markdown)


def _shard(args: argparse.Namespace) -> int:
    """``agos dataset shard``: reads and writes files only, no settings."""
    from agos.deploy.dataset import shards

    try:
        plan = shards.shard(args.split, args.shards, args.out)
    except shards.ShardError as exc:
        print(f"dataset error: {exc}", file=sys.stderr)
        return 2
    print(shards.next_steps(plan, args.out))
    return 0


def _merge(args: argparse.Namespace) -> int:
    """``agos dataset merge``: reads and writes files only, no settings."""
    from agos.deploy.dataset import shards

    try:
        return shards.merge(args.dir, args.out, link=args.link)
    except shards.ShardError as exc:
        print(f"dataset error: {exc}", file=sys.stderr)
        return 2


DATASET = Command(("dataset",), _add_dataset, by_subcommand("dataset_command", {"build": with_settings(_build),
                                                                             "stats": _stats, "shard": _shard,
                                                                             "merge": _merge}))
