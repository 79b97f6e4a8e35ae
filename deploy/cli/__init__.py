"""The ``agos`` command line: parses arguments and calls each process's ``main``.

    agos demo                       the whole system on this machine
    agos router --listen EP         the zenoh router
    agos world --connect EP --run R world worker
    agos agent --role uav|ugv ...   agent service
    agos human --role uav|ugv|both  a person plays in the browser (the Human reference); --spectate: watch
    agos evaluator --connect EP     result store and metrics
    agos episodes sample|split|check  episode files
    agos dataset build|stats        AGOS-Dataset: the expert's trajectories, actions, images, export
    agos map import|build|info|render town assets
    agos metrics PATH [--json]      every metric of a run (run dir, sqlite or JSONL summaries)
    agos compare RUN_A RUN_B        paired differences with bootstrap intervals and tests
    agos report RUN... --out DIR    paper-style tables and the stage-wise plot
    agos vlm-standin [--port 8000]  OpenAI-compatible stand-in VLM server (latency, injected faults)
    agos health KIND                is that process's liveliness token on the bus? (healthchecks)
    agos record --out DIR ...       the recorder: one rerun file per episode (eval/demo --record DIR)
    agos view FILE.rrd              the rerun viewer on a recording
    agos plot episode|compare ...   trajectory figures from a run's records
    agos certs --out DIR            a CA and one certificate per identity of a secured bus
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from pathlib import Path

from agos.deploy.cli_look import add_parsers as add_look_parsers
from agos.deploy.cli_look import add_record_flags, recording_of
from agos.runtime.bus import RouterUnreachable
from agos.runtime.health import HEALTH_KINDS
from agos.runtime.settings import AgosConfig, ConfigError, load_config


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, help="TOML settings file (see deploy/configs/demo.toml)")
    p.add_argument("--connect", help="zenoh router endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--run", dest="run_id", help="run id (the <run> in agos/<run>/...)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="agos", description="Air-ground cooperative object search benchmark runtime")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="run router, evaluator, agents and world workers locally")
    demo.add_argument("--config", type=Path)
    demo.add_argument("--workers", type=int, help="world worker processes (default 1)")
    demo.add_argument("--port", type=int, help="router port (default 7447, or a free one)")
    demo.add_argument("--episodes", type=Path, help="JSONL episode file instead of generated episodes")
    demo.add_argument("--per-difficulty", type=int, help="generated episodes per difficulty (default 2)")
    demo.add_argument("--runs-dir", type=Path)
    demo.add_argument("--connect", help="attach to this router and only orchestrate: processes were started by hand")
    demo.add_argument("--run", dest="run_id", help="run id of the hand-started processes (with --connect)")
    demo.add_argument("--secure", action="store_true",
                      help="mutual TLS and default-deny access control on the bus, with a CA made for this run")
    add_record_flags(demo)

    ev = sub.add_parser("eval", help="evaluate policies on an episode file: leases, fault tolerance, resume")
    ev.add_argument("--config", type=Path)
    ev.add_argument("--split", type=Path, help="JSONL episode file (e.g. a split's val.jsonl); default: generate")
    ev.add_argument("--policy", help="policy of both roles (default heuristic)")
    ev.add_argument("--policy-uav")
    ev.add_argument("--policy-ugv")
    ev.add_argument("--comm", default="ideal", help="comm profile name (deploy/comm) or TOML file")
    ev.add_argument("--timing", choices=["lockstep", "realtime"], default="lockstep")
    ev.add_argument("--workers", type=_workers, help="local world worker processes (default 1), or auto: as many "
                    "episodes at once as keep the cores busy while the model thinks (deploy/concurrency.py)")
    ev.add_argument("--model-latency", type=float, metavar="S",
                    help="seconds per decision of the run's model, for --workers auto (VLM policies; "
                         "standin-<N>ms and scripted policies say theirs)")
    ev.add_argument("--run-dir", type=Path, help="run directory (default <runs-dir>/<run>-<UTC time>)")
    ev.add_argument("--runs-dir", type=Path, help="parent of run directories (default runs)")
    ev.add_argument("--resume", type=Path, metavar="DIR", help="continue a run directory, skipping stored episodes")
    ev.add_argument("--connect", help="attach to a router and processes started by hand instead of starting them")
    ev.add_argument("--run", dest="run_id", help="run id (with --connect; default: the run directory's name)")
    ev.add_argument("--port", type=int)
    ev.add_argument("--secure", action="store_true",
                    help="mutual TLS and default-deny access control on the bus, with a CA made for this run "
                         "(with --connect: use your AGOS_ZENOH__* credentials and a tls/ endpoint instead)")
    ev.add_argument("--stuck-after", type=float, default=180.0, help="re-lease an episode without progress for this long (s)")
    add_record_flags(ev)
    ev.add_argument("--decision-timeout", type=_duration, metavar="DURATION",
                    help="how long the world waits for each decision before it applies WAIT: 90, 30m, 2h "
                         "(default [world] decision_timeout_s, 60 s; a person playing needs minutes or hours)")
    _vlm_flags(ev)
    ev.add_argument("--vlm-standin", nargs="?", const="", metavar="FAULTS",
                    help="start the offline stand-in VLM server for this run (optionally with faults, "
                         "e.g. 429=0.1,500=0.05); VLM policies then use it")

    ds = sub.add_parser("dataset", help="AGOS-Dataset: expert trajectories, actions, messages and images (docs/DATASET.md)")
    ds_sub = ds.add_subparsers(dest="dataset_command", required=True)
    dsb = ds_sub.add_parser("build", help="build (or resume) the dataset of an episode split with leased world workers")
    dsb.add_argument("--config", type=Path)
    dsb.add_argument("--split", type=Path, required=True, help="JSONL episode file (e.g. a split's train.jsonl)")
    dsb.add_argument("--out", type=Path, required=True, help="dataset directory (run the command again to resume)")
    dsb.add_argument("--workers", type=int, default=1, help="local world worker processes (default 1)")
    dsb.add_argument("--look", choices=["rich", "flat"], default="rich",
                     help="how the world draws the episodes (default rich: the textured city the dataset is for)")
    dsb.add_argument("--capture-every", type=float, default=10.0, metavar="M",
                     help="also render each role's camera every M metres between decisions (default 10)")
    dsb.add_argument("--connect", help="attach to a router and processes started by hand (agents with --dataset-out DIR)")
    dsb.add_argument("--run", dest="run_id", help="run id (with --connect)")
    dsb.add_argument("--port", type=int)
    dss = ds_sub.add_parser("stats", help="counts per difficulty and the dataset's statistics figure (reads files only)")
    dss.add_argument("dir", type=Path, help="dataset directory (the --out of agos dataset build)")
    dss.add_argument("--out", type=Path, help="figure PNG (default DIR/stats.png)")
    dss.add_argument("--markdown", action="store_true", help="print the table as markdown (to paste)")

    sw = sub.add_parser("sweep", help="a comm-profile parameter grid x link seeds: table and plots with CIs")
    sw.add_argument("--config", type=Path, help="TOML settings file: its [world] section shapes the episodes")
    sw.add_argument("--split", type=Path, required=True, help="JSONL episode file")
    sw.add_argument("--comm", default="ideal", help="base profile")
    sw.add_argument("--param", default="loss.p",
                    help="dotted profile field (loss.p, latency.mean_s, bandwidth.bits_per_s, range.max_range_m, "
                         "loss.p_bad_to_good ...), beacon_s, or loss.burst_len / blackouts.duration_s (docs/COMMS.md)")
    sw.add_argument("--values", default="0,0.1,0.2,0.3,0.4,0.5", help="comma-separated values")
    sw.add_argument("--seeds", default="0,1", help="comma-separated link seeds")
    sw.add_argument("--policy", default="heuristic")
    sw.add_argument("--workers", type=int, default=2)
    sw.add_argument("--out", type=Path, required=True)
    _vlm_flags(sw)
    sw.add_argument("--vlm-standin", nargs="?", const="", metavar="FAULTS",
                    help="start the offline stand-in VLM server for the sweep (optionally with faults); "
                         "VLM policies then use it")

    watch = sub.add_parser("watch", help="print every message under agos/** (a read-only observer)")
    watch.add_argument("--connect", help="zenoh router endpoint (default tcp/127.0.0.1:7447, or from settings)")
    watch.add_argument("--config", type=Path)
    watch.add_argument("--key", help="key expression to watch instead of the visualisation stream, e.g. 'agos/**'")
    add_look_parsers(sub)

    router = sub.add_parser("router", help="zenoh router")
    router.add_argument("--config", type=Path)
    router.add_argument("--listen", help="endpoint to listen on (default tcp/127.0.0.1:7447)")

    world = sub.add_parser("world", help="world worker: simulates leased episodes")
    _common(world)
    world.add_argument("--worker-id")
    world.add_argument("--agent-wait", type=float, help="seconds to wait for both agent services (default 30)")

    agent = sub.add_parser("agent", help="agent service for one role")
    _common(agent)
    agent.add_argument("--role", choices=["uav", "ugv"], required=True)
    agent.add_argument("--policy", help="policy name (default from config: heuristic)")
    agent.add_argument("--concurrency", type=int, default=32, help="decisions answered at once (default 32)")
    agent.add_argument("--dataset-out", type=Path,
                       help="with --policy expert: also write every decision for AGOS-Dataset here (agos dataset build)")
    _vlm_flags(agent)

    human = sub.add_parser("human", help="a person plays a role in the browser (the Human reference), or --spectate "
                                         "a run read-only (docs/HUMAN.md)")
    _common(human)
    play = human.add_mutually_exclusive_group(required=True)
    play.add_argument("--role", choices=["uav", "ugv", "both"], help="the role(s) the person plays")
    play.add_argument("--spectate", action="store_true", help="a read-only view of the run's visualisation stream")
    human.add_argument("--host", default="127.0.0.1",
                       help="interface the page is served on (default loopback; 0.0.0.0: every interface)")
    human.add_argument("--port", type=int, help="port of the page (default 8765; spectating 8766)")
    human.add_argument("--player", default="person", help="the player's name, stored in every decision trace")
    human.add_argument("--trace", type=Path, help="also append every decision (what was shown, the choice) to this JSONL file")

    evaluator = sub.add_parser("evaluator", help="stores episode records of every run and reports metrics")
    evaluator.add_argument("--config", type=Path)
    evaluator.add_argument("--connect", help="zenoh router endpoint, e.g. tcp/127.0.0.1:7447")
    evaluator.add_argument("--runs-dir", type=Path)
    evaluator.add_argument("--run", dest="run_id",
                           help="declare the evaluator's liveliness token under this run at start (its healthcheck); "
                                "it stores every run either way")

    from agos.world.cli import add_parsers as add_world_parsers

    add_world_parsers(sub)

    metrics = sub.add_parser("metrics", help="every metric of a run per difficulty (or town)")
    metrics.add_argument("path", type=Path, help="runs/<run>, a results.sqlite, or a JSONL file of episode summaries")
    metrics.add_argument("--json", action="store_true", help="print JSON (rates as fractions, distances in m)")
    metrics.add_argument("--allow-mixed", action="store_true",
                        help="pool episodes run under different episode configurations (refused by default)")
    metrics.add_argument("--by", choices=["difficulty", "town"], default="difficulty")

    comp = sub.add_parser("compare", help="paired comparison of two runs on their shared episodes")
    comp.add_argument("run_a", type=Path)
    comp.add_argument("run_b", type=Path)
    comp.add_argument("--resamples", type=int, default=10_000)
    comp.add_argument("--seed", type=int, default=0)
    comp.add_argument("--allow-mixed", action="store_true",
                        help="pool episodes run under different episode configurations (refused by default)")
    comp.add_argument("--json", action="store_true")

    report = sub.add_parser("report", help="paper-style tables (md, csv, tex), outcomes and the stage-wise PNG")
    report.add_argument("runs", type=Path, nargs="+")
    report.add_argument("--out", type=Path, required=True)
    report.add_argument("--allow-mixed", action="store_true",
                        help="pool episodes run under different episode configurations (refused by default)")
    report.add_argument("--labels", nargs="+", help="one label per run; a leading '+' marks an agent variant row")

    check = sub.add_parser("check", help="conformance checks")
    check_sub = check.add_subparsers(dest="check_what", required=True)
    check_agent = check_sub.add_parser("agent", help="a short conformance episode against attached agent services")
    _common(check_agent)
    check_agent.add_argument("--budget", type=int, default=16, help="decisions in the check episode (default 16)")
    check_agent.add_argument("--town", default="grid-s7", help="procedural town of the check episode")
    check_agent.add_argument("--policy", default="heuristic",
                             help="policy the agents run, for the world's tools (baseline: no candidates; ablations)")
    check_agent.add_argument("--agent-wait", type=float, help="seconds to wait for each role's service (default 30)")

    health = sub.add_parser("health", help="exit 0 if a process's liveliness token is on the bus (compose healthchecks)")
    health.add_argument("kind", choices=HEALTH_KINDS)
    health.add_argument("--id", dest="ident", help="the process id (default: what the process of that kind here announced)")
    health.add_argument("--config", type=Path)
    health.add_argument("--connect", help="zenoh router endpoint (default from settings)")
    health.add_argument("--run", dest="run_id", help="run id (default: the one the process announced, else settings)")
    health.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for the answer (default 3)")

    certs = sub.add_parser("certs", help="make a CA and per-identity certificates for a secured bus (mutual TLS)")
    certs.add_argument("--out", type=Path, required=True, help="directory to write (created, mode 0700)")
    certs.add_argument("--router-host", action="append", dest="router_hosts", metavar="HOST",
                       help="a name or address clients reach the router by (repeat; default localhost, 127.0.0.1)")
    certs.add_argument("--days", type=int, default=365, help="validity (default 365)")
    certs.add_argument("--force", action="store_true", help="replace an existing CA and every certificate")

    from agos.agents.vlm.standin.cli import add_parser as add_standin_parser

    add_standin_parser(sub)
    return parser


def _vlm_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--vlm-base-url", help="OpenAI-compatible endpoint of VLM policies, e.g. http://HOST:8000/v1")
    p.add_argument("--model", help="model name at that endpoint")
    p.add_argument("--vlm-api-key-env", help="environment variable holding the API key (default OPENAI_API_KEY)")
    p.add_argument("--vlm-timeout", type=float, help="seconds per HTTP attempt (default 60)")
    p.add_argument("--vlm-max-retries", type=int, help="HTTP retries per request (default 4)")
    p.add_argument("--vlm-no-structured", action="store_true", help="do not send a JSON schema (servers that mishandle it)")
    p.add_argument("--vlm-trace", type=Path, help="also append every decision trace to this JSONL file")


def _duration(value: str) -> float:
    from agos.deploy.human import parse_duration

    try:
        return parse_duration(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _workers(value: str) -> int | str:
    """``--workers``: a number, or ``auto``."""
    if value == "auto":
        return value
    try:
        return int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{value!r}: give a number of workers or auto") from None


def _int_or_none(value: object) -> int | None:
    return value if isinstance(value, int) else None


def _config(args: argparse.Namespace) -> AgosConfig:
    overrides = {
        "vlm": {"base_url": getattr(args, "vlm_base_url", None), "model": getattr(args, "model", None),
                "api_key_env": getattr(args, "vlm_api_key_env", None), "timeout_s": getattr(args, "vlm_timeout", None),
                "max_retries": getattr(args, "vlm_max_retries", None),
                "structured": False if getattr(args, "vlm_no_structured", False) else None,
                "trace_file": getattr(args, "vlm_trace", None)},
        "zenoh": {"connect": getattr(args, "connect", None), "listen": getattr(args, "listen", None)},
        "world": {"decision_timeout_s": getattr(args, "decision_timeout", None)},
        "run": {"run_id": getattr(args, "run_id", None), "runs_dir": getattr(args, "runs_dir", None),
                "workers": _int_or_none(getattr(args, "workers", None)), "agent_wait_s": getattr(args, "agent_wait", None),
                "episodes_file": getattr(args, "episodes", None) or getattr(args, "split", None),
                "per_difficulty": getattr(args, "per_difficulty", None),
                "policy_uav": getattr(args, "policy_uav", None) or getattr(args, "policy", None),
                "policy_ugv": getattr(args, "policy_ugv", None) or getattr(args, "policy", None)},
    }
    return load_config(getattr(args, "config", None), overrides=overrides)


CONFIG_COMMANDS = ("demo", "eval", "dataset", "sweep", "router", "world", "agent", "human", "evaluator", "check", "health", "watch",
                   "record")
"""The commands that read the settings (``--config`` and the flags that override it)."""


def _reads_config(args: argparse.Namespace) -> bool:
    """Whether the command reads the settings: CONFIG_COMMANDS but ``dataset stats``, which reads files only."""
    return args.command in CONFIG_COMMANDS and not (args.command == "dataset" and args.dataset_command == "stats")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cfg = _config(args) if _reads_config(args) else None
        code = _dispatch(args, cfg)
        sys.stdout.flush()  # here, where a reader that left (BrokenPipeError) is caught, not at exit
        return code
    except ConfigError as exc:
        print(str(exc), file=sys.stderr)
        return 2
    except RouterUnreachable as exc:
        print(f"agos {args.command}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `agos metrics --json | head`: the reader left; not an error worth a traceback
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # so the exit flush does not fail too
        return 141


def _dispatch(args: argparse.Namespace, cfg: AgosConfig | None) -> int:
    """Run the command; ``cfg`` is the loaded settings for a command of CONFIG_COMMANDS, else None."""
    from agos.world.episodes.sampling import EpisodeFileError

    try:
        return _run_configured(args, cfg) if cfg is not None else _run_unconfigured(args)
    except EpisodeFileError as exc:
        print(f"episode file error: {exc}", file=sys.stderr)
        return 2


def _run_configured(args: argparse.Namespace, cfg: AgosConfig) -> int:
    """The commands of CONFIG_COMMANDS."""
    if args.command == "demo":
        from agos.deploy import demo

        try:
            return demo.main(cfg, config_path=args.config, port=args.port, attach=args.connect is not None,
                             secure=args.secure, recording=recording_of(args))
        except ValueError as exc:  # a policy or profile name, a run directory: before any process starts
            print(f"demo error: {exc}", file=sys.stderr)
            return 2
    if args.command == "dataset":
        return _dataset(args, cfg)
    if args.command == "eval":
        return _eval(args, cfg)
    if args.command == "sweep":
        return _sweep(args, cfg)
    if args.command == "router":
        from agos.runtime import router

        return router.main(cfg.zenoh)
    if args.command == "world":
        from agos.world import expert
        from agos.world.sim import worker

        expert.install()  # episodes of runs whose policy is `expert` carry its plan (world/expert/)
        return worker.main(cfg, worker_id=args.worker_id)
    if args.command == "agent":
        from agos.agents import service
        from agos.agents.registry import make_policy

        try:
            make_policy(args.policy or (cfg.run.policy_uav if args.role == "uav" else cfg.run.policy_ugv), args.role,
                        vlm=cfg.vlm, dataset_out=args.dataset_out)
        except ValueError as exc:
            print(f"agent error: {exc}", file=sys.stderr)
            return 2
        return service.main(cfg, role=args.role, policy_name=args.policy, concurrency=args.concurrency,
                            dataset_out=args.dataset_out)
    if args.command == "human":
        return _human(args, cfg)
    if args.command == "check":
        from agos.deploy.check import run_check

        return run_check(cfg, budget=args.budget, town_name=args.town, policy=args.policy)
    if args.command == "evaluator":
        from agos.evaluator import service as evaluator_service

        return evaluator_service.main(cfg)
    if args.command == "record":
        from agos.deploy.cli_look import run_record

        return run_record(args, cfg)
    if args.command == "watch":
        from agos.runtime import observer

        return observer.main(cfg.zenoh, args.key)
    if args.command == "health":
        from agos.deploy.health import main as health_main

        return health_main(cfg, args.kind, ident=args.ident, run=args.run_id, timeout_s=args.timeout)
    raise AssertionError(args.command)


def _run_unconfigured(args: argparse.Namespace) -> int:
    """The commands that do not read the settings."""
    if args.command == "dataset":  # dataset stats (build reads the settings)
        from agos.deploy import dataset_stats

        return dataset_stats.main(args.dir, args.out, markdown=args.markdown)
    if args.command in ("episodes", "map"):
        from agos.world import cli as world_cli

        return world_cli.run(args)
    if args.command in ("view", "plot"):
        from agos.deploy import cli_look

        return cli_look.run(args)
    if args.command in ("metrics", "compare", "report"):
        from agos.evaluator import cli as evaluator_cli

        return evaluator_cli.run(args)
    if args.command == "vlm-standin":
        from agos.agents.vlm.standin import cli as standin_cli

        return standin_cli.run(args)
    if args.command == "certs":
        from agos.deploy.certs import main as certs_main

        return certs_main(args.out, router_hosts=args.router_hosts, days=args.days, force=args.force)
    raise AssertionError(args.command)


def _human(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from agos.agents.human import service as human_service
    from agos.deploy.human import CONSOLE_PORT, SPECTATOR_PORT
    from agos.runtime.keys import ROLES
    from agos.runtime.schemas import Role

    if args.spectate:
        return human_service.spectate(cfg, run_id=args.run_id, host=args.host, port=args.port or SPECTATOR_PORT)
    roles: tuple[Role, ...] = ROLES if args.role == "both" else (args.role,)
    return human_service.main(cfg, roles=roles, host=args.host, port=args.port or CONSOLE_PORT, player=args.player,
                              trace_file=args.trace)


def _sweep(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from agos.deploy.configure import episode_config
    from agos.deploy.sweep import run_sweep
    from agos.runtime.links import ProfileError
    from agos.world.episodes.sampling import read_episodes

    try:
        values = [float(v) for v in args.values.split(",")]
        seeds = [int(v) for v in args.seeds.split(",")]
        total = len(values) * len(seeds) * len(read_episodes(args.split))
        config = episode_config(cfg, policies={"uav": args.policy, "ugv": args.policy}, comm=args.comm)
        with Progress(TextColumn("[bold]sweep"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn()) as bar:
            task = bar.add_task("episodes", total=total)
            table = run_sweep(args.split, args.out, config=config, param=args.param, values=values, seeds=seeds,
                              policies=(args.policy, args.policy), workers=args.workers,
                              progress=lambda: bar.advance(task), vlm=cfg.vlm, vlm_standin=args.vlm_standin)
    except (ProfileError, ValueError) as exc:
        print(f"sweep error: {exc}", file=sys.stderr)
        return 2
    print((args.out / "sweep.md").read_text())
    print(f"{len(table)} points -> {args.out}/sweep.csv, sweep.md, sweep.png")
    return 0


def _dataset(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from agos.deploy import dataset, evaluate
    from agos.world.episodes.sampling import read_episodes

    if args.connect and not args.run_id:
        print("dataset error: --connect needs --run RUN (the run id the attached processes serve)", file=sys.stderr)
        return 2
    if args.capture_every <= 0:
        print(f"dataset error: --capture-every {args.capture_every}: give a distance in metres above 0", file=sys.stderr)
        return 2
    try:
        read_episodes(args.split)  # a bad split fails here, before any process starts
        return dataset.build(cfg, args.split, args.out, workers=args.workers, capture_every_m=args.capture_every,
                             look=args.look, attach=args.connect is not None, port=args.port, config_path=args.config)
    except (dataset.DatasetError, evaluate.RunDirError) as exc:
        print(f"dataset error: {exc}", file=sys.stderr)
        return 2


def _eval(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from agos.deploy import evaluate
    from agos.runtime.links import ProfileError

    recording = recording_of(args)  # a bad flag fails before a run directory is made
    try:
        if args.resume:
            plan = evaluate.resume_plan(args.resume)
        else:
            run_dir = args.run_dir
            if run_dir is None and args.connect and args.run_id:
                run_dir = cfg.run.runs_dir / args.run_id
            plan = evaluate.new_plan(cfg, run_dir=run_dir, comm=args.comm, timing_mode=args.timing, stamp=True,
                                     vlm_standin=args.vlm_standin, workers=args.workers)
    except (evaluate.RunDirError, ProfileError, ValueError) as exc:
        print(f"eval error: {exc}", file=sys.stderr)
        return 2
    if args.resume and args.workers is None:  # a resumed run keeps the worker count it was started with
        args.workers = plan.workers
    workers = args.workers if isinstance(args.workers, int) else cfg.run.workers
    if args.workers == "auto" and not args.connect:
        from agos.agents.names import needs_vlm
        from agos.deploy.concurrency import choose_workers

        to_run = len(plan.episodes) - len(evaluate.stored_episodes(plan.run_dir))
        asks_model = any(needs_vlm(p) for p in plan.policies.values())  # at most [vlm] concurrency requests at once
        choice = choose_workers(plan.policies, to_run, model_latency_s=args.model_latency,
                                model_concurrency=cfg.vlm.concurrency if asks_model else None)
        workers = choice.workers
        print(f"world workers: {workers} ({choice.why})")
    return evaluate.run(cfg, plan, workers=workers, attach=args.connect is not None, port=args.port,
                        config_path=args.config, stuck_after_s=args.stuck_after, secure=args.secure,
                        recording=recording)


if __name__ == "__main__":
    sys.exit(main())
