"""The service processes' parsers: each command starts one process of a run and calls its ``main``.

    agos router --listen EP         the zenoh router (--peer EP: a mesh of routers)
    agos world --connect EP --run R world worker
    agos agent --role uav|ugv ...   agent service
    agos human --role uav|ugv|both  a person plays in the browser (the Human reference); --spectate: watch
    agos evaluator --connect EP     result store and metrics
    agos watch                      print the run's visualisation stream (a read-only observer)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from agos.deploy.cli.common import Command, connection_flags, vlm_flags, with_settings
from agos.deploy.run.children import AGENT_CONCURRENCY
from agos.runtime.keys import ROLES
from agos.runtime.settings import DEFAULT_POLICY, DEFAULTS, AgosConfig


def _add_watch(sub: Any) -> None:
    what = ("print the visualisation stream of every run, one line a message (steps, coordination, frames, episode "
            "specs and records; not the full-resolution frames): a read-only observer. --key 'agos/**' prints "
            "every message instead; --episode EP only the messages of one episode")
    watch = sub.add_parser("watch", help="print the runs' visualisation stream (a read-only observer)", description=what)
    watch.add_argument("--connect", help="zenoh router endpoint (default tcp/127.0.0.1:7447, or from settings)")
    watch.add_argument("--config", type=Path)
    watch.add_argument("--key", help="key expression to watch instead of the visualisation stream, e.g. 'agos/**'")
    watch.add_argument("--episode", metavar="EP",
                       help="print only the messages that name this episode (their episode_id: keys name world "
                            "workers, whose episodes follow each other on the same keys)")


def _watch(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from agos.runtime import observer

    return observer.main(cfg.zenoh, args.key, args.episode)


def _add_router(sub: Any) -> None:
    router = sub.add_parser("router", help="zenoh router")
    router.add_argument("--config", type=Path)
    router.add_argument("--listen", help="endpoint to listen on (default tcp/127.0.0.1:7447)")
    router.add_argument("--peer", action="append", dest="peers", metavar="EP",
                        help="another router to connect to, making a mesh (repeat; docs/DEPLOY.md 'Router mesh')")


def _router(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from agos.runtime import router

    return router.main(cfg.zenoh)


def _add_world(sub: Any) -> None:
    world = sub.add_parser("world", help="world worker: simulates leased episodes")
    connection_flags(world)
    world.add_argument("--worker-id")
    world.add_argument("--agent-wait", type=float,
                       help=f"seconds to wait for both agent services (default {DEFAULTS.run.agent_wait_s:g})")


def _world(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from agos.world import expert
    from agos.world.sim import worker

    expert.install()  # episodes of runs whose policy is `expert` carry its plan (world/expert/)
    return worker.main(cfg, worker_id=args.worker_id)


def _add_agent(sub: Any) -> None:
    agent = sub.add_parser("agent", help="agent service for one role")
    connection_flags(agent)
    agent.add_argument("--role", choices=ROLES, required=True)
    agent.add_argument("--policy", help=f"policy name (default from config: {DEFAULT_POLICY}), one registered in the "
                       "agos.policies entry points, or package.module:Class (docs/AGENTS.md)")
    agent.add_argument("--concurrency", type=int, default=AGENT_CONCURRENCY,
                       help=f"decisions answered at once (default {AGENT_CONCURRENCY})")
    agent.add_argument("--dataset-out", type=Path,
                       help="with --policy expert: also write every decision for AGOS-Dataset here (agos dataset build)")
    vlm_flags(agent)


def _agent(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from agos.agents import agent_service
    from agos.agents.registry import make_policy

    try:
        make_policy(args.policy or (cfg.run.policy_uav if args.role == "uav" else cfg.run.policy_ugv), args.role,
                    vlm=cfg.vlm, dataset_out=args.dataset_out)
    except ValueError as exc:
        print(f"agent error: {exc}", file=sys.stderr)
        return 2
    return agent_service.main(cfg, role=args.role, policy_name=args.policy, concurrency=args.concurrency,
                              dataset_out=args.dataset_out)


def _add_human(sub: Any) -> None:
    human = sub.add_parser("human", help="a person plays a role in the browser (the Human reference), or --spectate "
                                         "a run read-only (docs/HUMAN.md)")
    connection_flags(human)
    play = human.add_mutually_exclusive_group(required=True)
    play.add_argument("--role", choices=[*ROLES, "both"], help="the role(s) the person plays")
    play.add_argument("--spectate", action="store_true", help="a read-only view of the run's visualisation stream")
    human.add_argument("--host", default="127.0.0.1",
                       help="interface the page is served on (default loopback; 0.0.0.0: every interface)")
    human.add_argument("--port", type=int, help="port of the page (default 8765; spectating 8766)")
    human.add_argument("--player", default="person", help="the player's name, stored in every decision trace")
    human.add_argument("--trace", type=Path, help="also append every decision (what was shown, the choice) to this JSONL file")


def _human(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from agos.agents.human import human_service
    from agos.deploy.run.human import CONSOLE_PORT, SPECTATOR_PORT
    from agos.runtime.schemas import Role

    if args.spectate:
        return human_service.spectate(cfg, run_id=args.run_id, host=args.host, port=args.port or SPECTATOR_PORT)
    roles: tuple[Role, ...] = ROLES if args.role == "both" else (args.role,)
    return human_service.main(cfg, roles=roles, host=args.host, port=args.port or CONSOLE_PORT, player=args.player,
                              trace_file=args.trace)


def _add_evaluator(sub: Any) -> None:
    evaluator = sub.add_parser("evaluator", help="stores episode records of every run and reports metrics")
    evaluator.add_argument("--config", type=Path)
    evaluator.add_argument("--connect", help="zenoh router endpoint, e.g. tcp/127.0.0.1:7447")
    evaluator.add_argument("--runs-dir", type=Path)
    evaluator.add_argument("--run", dest="run_id",
                           help="declare the evaluator's liveliness token under this run at start (its healthcheck); "
                                "it stores every run either way")


def _evaluator(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from agos.evaluator import evaluator_service

    return evaluator_service.main(cfg)


WATCH = Command(("watch",), _add_watch, with_settings(_watch))
ROUTER = Command(("router",), _add_router, with_settings(_router))
WORLD = Command(("world",), _add_world, with_settings(_world))
AGENT = Command(("agent",), _add_agent, with_settings(_agent))
HUMAN = Command(("human",), _add_human, with_settings(_human))
EVALUATOR = Command(("evaluator",), _add_evaluator, with_settings(_evaluator))
