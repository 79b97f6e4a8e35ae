"""The ``agos`` command line: parses arguments and calls each process's ``main``.

    agos demo                       the whole system on this machine
    agos router --listen EP         the zenoh router
    agos world --connect EP --run R world worker
    agos agent --role uav|ugv ...   agent service
    agos human --role uav|ugv|both  a person plays in the browser (the Human reference); --spectate: watch
    agos evaluator --connect EP     result store and metrics
    agos episodes sample|split|check  episode files
    agos dataset build|stats|shard|merge  AGOS-Dataset: the expert's trajectories, actions, images, export
    agos map import|build|info|render town assets
    agos metrics PATH [--json]      every metric of a run (run dir, sqlite or JSONL summaries)
    agos compare RUN_A RUN_B        paired differences with bootstrap intervals and tests
    agos report RUN... --out DIR    paper-style tables and the stage-wise plot
    agos vlm-standin [--port 8000]  OpenAI-compatible stand-in VLM server (latency, injected faults)
    agos vlm-cache stats DIR        a cache of recorded model calls: hits, misses, tokens, size
    agos health KIND                is that process's liveliness token on the bus? (healthchecks)
    agos record --out DIR ...       the recorder: one rerun file per episode (eval/demo --record DIR)
    agos view FILE.rrd              the rerun viewer on a recording
    agos plot episode|compare ...   trajectory figures from a run's records
    agos certs --out DIR            a CA and per-identity certificates for a secured bus
    agos ros2 bridge --connect EP   a run as ROS 2 topics over rmw_zenoh; --drive ROLE from ROS 2

Each command's parser lives in one module, by command group: runs (demo, eval, sweep, check),
services (router, world, agent, human, evaluator, watch), recordings (record, view and the
``--record`` flags), reports (plot, metrics, compare, report, vlm-cache), datasets (dataset) and ops (health,
certs), ros2 (the ROS 2 bridge). Two groups keep their parsers in their own layer, beside the code that runs them:
``agos map``/``agos episodes`` in world/commands.py, and ``agos vlm-standin`` in agents/vlm/standin/command.py,
whose own ``main`` needs it. :data:`COMMANDS` is the table that dispatches a parsed command.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys

try:  # a second or two of imports: Ctrl-C here is the same exit 130 as later, without a traceback
    from agos.deploy.cli import datasets, ops, recordings, reports, ros2, runs, services
    from agos.deploy.cli.common import Command
    from agos.runtime.bus import RouterUnreachable
    from agos.runtime.deaths import ChildDied
    from agos.runtime.process import enable_fault_handler
    from agos.runtime.settings import ConfigError
except KeyboardInterrupt:
    raise SystemExit(130) from None


def _add_world_parsers(sub: argparse._SubParsersAction) -> None:
    from agos.world.commands import add_parsers

    add_parsers(sub)


def _world_cli(args: argparse.Namespace) -> int:
    from agos.world import commands as world_commands

    return world_commands.run(args)


def _add_standin_parser(sub: argparse._SubParsersAction) -> None:
    from agos.agents.vlm.standin.command import add_parser

    add_parser(sub)


def _standin(args: argparse.Namespace) -> int:
    from agos.agents.vlm.standin import command as standin_command

    return standin_command.run(args)


COMMANDS: tuple[Command, ...] = (
    runs.DEMO, runs.EVAL, datasets.DATASET, runs.SWEEP, services.WATCH, recordings.RECORD, recordings.VIEW, reports.PLOT,
    services.ROUTER, services.WORLD, services.AGENT, services.HUMAN, services.EVALUATOR,
    Command(("map", "episodes"), _add_world_parsers, _world_cli),
    reports.METRICS, reports.COMPARE, reports.REPORT, runs.CHECK, ops.HEALTH, ops.CERTS,
    Command(("vlm-standin",), _add_standin_parser, _standin), reports.VLM_CACHE, ros2.ROS2,
)
"""Every ``agos`` command, in the order ``agos --help`` lists them."""
_BY_NAME = {name: command for command in COMMANDS for name in command.names}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="agos", description="Air-ground cooperative object search benchmark runtime")
    sub = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one ``agos`` command; its exit status. Ctrl-C at any moment is 130 (a command that stops its
    own children and keeps its finished work says so before). A fatal signal writes the Python
    traceback of every thread to stderr (runtime/process.py: :func:`enable_fault_handler`)."""
    enable_fault_handler()
    try:
        args = build_parser().parse_args(argv)
    except KeyboardInterrupt:
        return 130
    try:
        code = _dispatch(args)
        sys.stdout.flush()  # here, where a reader that left (BrokenPipeError) is caught, not at exit
        return code
    except ConfigError as exc:
        print(str(exc), file=sys.stderr)
        return 2
    except RouterUnreachable as exc:
        print(f"agos {args.command}: {exc}", file=sys.stderr)
        return 2
    except ChildDied as exc:  # a worker of a process pool (runtime/process.py): a command that can says more
        print(f"agos {args.command}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `agos metrics --json | head`: the reader left; not an error worth a traceback
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # so the exit flush does not fail too
        return 141


def _dispatch(args: argparse.Namespace) -> int:
    """Run the parsed command through :data:`COMMANDS`; a bad episode file is one line, exit 2."""
    from agos.world.episodes.files import EpisodeFileError

    try:
        return _BY_NAME[args.command].run(args)
    except EpisodeFileError as exc:
        print(f"episode file error: {exc}", file=sys.stderr)
        return 2
