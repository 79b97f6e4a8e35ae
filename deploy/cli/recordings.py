"""The commands that look at episodes: ``agos record``, ``agos view``, ``agos plot`` (and the
``--record`` flags of ``agos eval`` and ``agos demo``). Parsing only; each calls its module.

    agos record --connect EP --run RUN --out DIR [--full]   the recorder process (deploy/record.py)
    agos view FILE.rrd                                      the rerun viewer on a recording
    agos plot episode RUN [EPISODE] --out FILE.png          one episode's trajectory figure (deploy/plot.py)
    agos plot compare RUN_A RUN_B [EPISODE] --out FILE.png  two runs' policies on one episode, side by side
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any


def add_record_flags(p: argparse.ArgumentParser) -> None:
    """``--record DIR`` and ``--record-full`` of ``agos eval`` and ``agos demo``."""
    p.add_argument("--record", type=Path, metavar="DIR",
                   help="start a recorder: one rerun file (.rrd) per episode in DIR (agos view FILE opens one)")
    p.add_argument("--record-full", action="store_true",
                   help="with --record: full-resolution images instead of the visualisation stream's thumbnails")


def recording_of(args: argparse.Namespace) -> Any:
    """The :class:`~agos.deploy.evaluate.Recording` the flags ask for, or None."""
    if getattr(args, "record", None) is None:
        if getattr(args, "record_full", False):
            print("agos: --record-full needs --record DIR", file=sys.stderr)
            raise SystemExit(2)
        return None
    from agos.deploy.evaluate import Recording

    return Recording(args.record, full=args.record_full)


def add_parsers(sub: Any) -> None:
    record = sub.add_parser("record", help="record a run's visualisation stream: one rerun file per episode")
    record.add_argument("--config", type=Path)
    record.add_argument("--connect", help="zenoh router endpoint, e.g. tcp/127.0.0.1:7447")
    record.add_argument("--run", dest="run_id", help="the run to record")
    record.add_argument("--out", type=Path, required=True, help="directory of the .rrd files (and recorder.json)")
    record.add_argument("--full", action="store_true",
                        help="full-resolution images (the worlds send them while a recorder asks) instead of thumbnails")

    view = sub.add_parser("view", help="open a recording (.rrd) in the rerun viewer, or say how to")
    view.add_argument("file", type=Path)
    view.add_argument("--web", action="store_true",
                      help="serve rerun's web viewer on loopback instead of opening a window (no display needed)")
    view.add_argument("--web-port", type=int, default=9090, help="port of the web viewer (with --web)")

    plot = sub.add_parser("plot", help="trajectory figures of episodes from a run's records")
    what = plot.add_subparsers(dest="plot_what", required=True)
    one = what.add_parser("episode", help="one episode: map, both paths, candidates, the target, CONFIRM/REJECT")
    one.add_argument("run", type=Path, help="run directory (runs/<run>) or its results.sqlite")
    one.add_argument("episode", nargs="?", help="episode id (default: the run's first episode with a finished record)")
    one.add_argument("--out", type=Path, required=True, help="PNG file")
    two = what.add_parser("compare", help="two runs (two policies) on the same episode, side by side")
    two.add_argument("run_a", type=Path)
    two.add_argument("run_b", type=Path)
    two.add_argument("episode", nargs="?", help="episode id (default: the first both runs finished)")
    two.add_argument("--out", type=Path, required=True)
    two.add_argument("--labels", nargs=2, metavar=("A", "B"), help="panel titles (default: each run's policies)")


def run_record(args: argparse.Namespace, cfg: Any) -> int:
    from agos.deploy import record

    if not cfg.zenoh.connect:
        print("agos record: give --connect EP (or [zenoh] connect)", file=sys.stderr)
        return 2
    return record.main(cfg, args.out, full=args.full)


def run(args: argparse.Namespace) -> int:
    """``agos view`` and ``agos plot``."""
    if args.command == "view":
        from agos.deploy.view import main as view_main

        return view_main(args.file, web=args.web, web_port=args.web_port)
    from agos.deploy.plot import PlotError, plot_compare, plot_episode

    try:
        if args.plot_what == "episode":
            out = plot_episode(args.run, args.episode, args.out)
        else:
            out = plot_compare(args.run_a, args.run_b, args.episode, args.out, labels=args.labels)
    except PlotError as exc:
        print(f"plot error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out}")
    return 0
