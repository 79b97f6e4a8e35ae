"""``agos ros2``'s parser: the ROS 2 side of a run (deploy/ros2/; docs/DEPLOY.md, "ROS 2 (rmw_zenoh)").

    agos ros2 bridge --connect EP --run R [--worker W] [--drive ugv|uav|both]   a run as ROS 2 topics
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from typing import Any

from agos.deploy.cli.common import Command, by_subcommand, connection_flags, with_settings
from agos.runtime.keys import ROLES
from agos.runtime.settings import AgosConfig


def _add(sub: Any) -> None:
    ros2 = sub.add_parser("ros2", help="the run on a ROS 2 graph (rmw_zenoh): topics, and a role driven from ROS 2")
    groups = ros2.add_subparsers(dest="ros2_command", required=True)
    what = ("republish a run's observations (poses, camera images and info, the decision asked) and coordination "
            "state as ROS 2 topics in rmw_zenoh's key layout and CDR encoding, on the run's router; with --drive, "
            "answer a role's decisions with what a ROS 2 node publishes on ROLE/action (docs/DEPLOY.md)")
    bridge = groups.add_parser("bridge", help="a run as ROS 2 topics; --drive: a role driven from ROS 2", description=what)
    connection_flags(bridge)
    bridge.add_argument("--worker", metavar="W", help="only this world worker's slot (default: every worker's)")
    bridge.add_argument("--drive", choices=[*ROLES, "both"],
                        help="serve this role's decisions from the ROS 2 topic ROLE/action (instead of an agos agent)")
    bridge.add_argument("--namespace", default="", metavar="NS", help="prefix of every topic, e.g. /agos_run (default none)")
    bridge.add_argument("--domain-id", type=int, help="ROS domain id (default $ROS_DOMAIN_ID, else 0)")
    bridge.add_argument("--ros-connect", metavar="EP",
                        help="put the ROS 2 node on this router instead of the run's (a ROS graph's own rmw_zenohd)")
    bridge.add_argument("--node-name", default="agos_bridge", help="the ROS 2 node's name (default agos_bridge)")


def _bridge(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from agos.deploy.ros2 import bridge
    from agos.runtime import keys

    try:
        if args.worker is not None:
            keys.check_chunk(args.worker, what="worker id")
        domain = args.domain_id if args.domain_id is not None else int(os.environ.get("ROS_DOMAIN_ID") or 0)
        if not 0 <= domain <= 232:
            raise ValueError(f"ROS domain id {domain} is not in 0..232")
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", args.node_name):
            raise ValueError(f"{args.node_name!r} is not a ROS node name (letters, digits and '_')")
    except ValueError as exc:
        print(f"agos ros2 bridge: {exc}", file=sys.stderr)
        return 2
    drive = keys.ROLES if args.drive == "both" else (args.drive,) if args.drive else ()
    return bridge.main(cfg, drive=drive, worker=args.worker, ns=args.namespace, domain=domain,
                       ros_connect=args.ros_connect, node_name=args.node_name)


ROS2 = Command(("ros2",), _add, by_subcommand("ros2_command", {"bridge": with_settings(_bridge)}))
