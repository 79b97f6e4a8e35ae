"""The recording commands' parsers (deploy/recording/): ``agos record``, ``agos view`` and the
``--record`` flags of ``agos eval`` and ``agos demo``. Parsing only; each calls its module.

    agos record --connect EP --run RUN --out DIR [--full] [--format rrd|mcap]   the recorder process
                                                            (deploy/recording/recorder.py; mcap: mcap_episode.py)
    agos view FILE.rrd                                      the rerun viewer on a recording
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from agos.deploy.cli.common import Command, with_settings
from agos.runtime.settings import AgosConfig

if TYPE_CHECKING:
    from agos.deploy.run.local import Recording

FORMATS = ("rrd", "mcap")
"""Recording formats (deploy/recording/recorder.py's ``FORMATS``; the parser imports no recorder)."""


def add_record_flags(p: argparse.ArgumentParser) -> None:
    """``--record DIR``, ``--record-full`` and ``--record-format`` of ``agos eval`` and ``agos demo``."""
    p.add_argument("--record", type=Path, metavar="DIR",
                   help="start a recorder: one rerun file (.rrd) per episode in DIR (agos view FILE opens one)")
    p.add_argument("--record-full", action="store_true",
                   help="with --record: full-resolution images instead of the visualisation stream's thumbnails")
    p.add_argument("--record-format", choices=FORMATS, default=None,
                   help="with --record: rerun files (rrd, the default) or MCAP files with ROS 2 message schemas "
                        "(mcap: the robotics extra, pip install 'agos[robotics]')")


def recording_of(args: argparse.Namespace) -> Recording | None:
    """The :class:`~agos.deploy.run.local.Recording` the flags ask for, or None."""
    fmt = getattr(args, "record_format", None)
    if getattr(args, "record", None) is None:
        for flag, given in (("--record-full", getattr(args, "record_full", False)), ("--record-format", fmt)):
            if given:
                print(f"agos: {flag} needs --record DIR", file=sys.stderr)
                raise SystemExit(2)
        return None
    if fmt == "mcap" and _mcap_missing("agos"):  # before the run starts
        raise SystemExit(2)
    from agos.deploy.run.local import Recording

    return Recording(args.record, full=args.record_full, fmt=fmt or "rrd")


def _mcap_missing(command: str) -> bool:
    """Whether the MCAP libraries (the robotics extra) are missing; if so, one line says what to install."""
    from agos.deploy.recording.mcap_episode import missing_library

    missing = missing_library()
    if missing is not None:
        print(f"{command}: {missing}", file=sys.stderr)
    return missing is not None


def _add_record(sub: Any) -> None:
    record = sub.add_parser("record", help="record a run's visualisation stream: one rerun (or MCAP) file per episode")
    record.add_argument("--config", type=Path)
    record.add_argument("--connect", help="zenoh router endpoint, e.g. tcp/127.0.0.1:7447")
    record.add_argument("--run", dest="run_id", help="the run to record")
    record.add_argument("--out", type=Path, required=True, help="directory of the .rrd/.mcap files (and recorder.json)")
    record.add_argument("--full", action="store_true",
                        help="full-resolution images (the worlds send them while a recorder asks) instead of thumbnails")
    record.add_argument("--format", choices=FORMATS, default="rrd", dest="fmt",
                        help="rrd: rerun files (agos view); mcap: MCAP files with ROS 2 message schemas, for Foxglove "
                             "and ROS 2 tools (the robotics extra: pip install 'agos[robotics]')")


def _record(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from agos.deploy.recording import recorder

    if not cfg.zenoh.connect:
        print("agos record: give --connect EP (or [zenoh] connect)", file=sys.stderr)
        return 2
    if args.fmt == "mcap" and _mcap_missing("agos record"):
        return 2
    return recorder.main(cfg, args.out, full=args.full, fmt=args.fmt)


def _add_view(sub: Any) -> None:
    view = sub.add_parser("view", help="open a recording (.rrd) in the rerun viewer, or say how to")
    view.add_argument("file", type=Path)
    view.add_argument("--web", action="store_true",
                      help="serve rerun's web viewer on loopback instead of opening a window (no display needed)")
    view.add_argument("--web-port", type=int, default=9090, help="port of the web viewer's page (with --web)")
    view.add_argument("--grpc-port", type=int, default=9876,
                      help="port the web viewer reads the recording from (with --web)")


def _view(args: argparse.Namespace) -> int:
    from agos.deploy.recording.view import main as view_main

    return view_main(args.file, web=args.web, web_port=args.web_port, grpc_port=args.grpc_port)


RECORD = Command(("record",), _add_record, with_settings(_record))
VIEW = Command(("view",), _add_view, _view)
