"""The run commands' parsers (deploy/run/): what each parses, then the run it calls.

    agos demo                       the whole system on this machine
    agos eval --split FILE ...      policies on an episode file: leases, fault tolerance, resume
    agos sweep --split FILE ...     a comm-profile parameter grid x link seeds
    agos check agent ...            a short conformance episode against attached agent services
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from agos.deploy.cli.common import Command, by_subcommand, connection_flags, price_flags, vlm_flags, with_settings
from agos.deploy.cli.recordings import add_record_flags, recording_of
from agos.deploy.run.orchestrator import STUCK_AFTER_S
from agos.runtime.settings import DEFAULT_POLICY, DEFAULT_TOWN, DEFAULTS, AgosConfig


def _duration(value: str) -> float:
    from agos.deploy.run.human import parse_duration

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


def _cap(kind: type) -> Any:
    """``--max-cost-usd`` / ``--max-tokens``: a positive number, or ``none`` (a resume lifts the cap)."""

    def parse(value: str) -> float | int | str:
        if value == "none":
            return value
        try:
            number = kind(value)
        except ValueError:
            number = None
        if number is None or not number > 0 or number == float("inf"):
            raise argparse.ArgumentTypeError(f"{value!r}: give a number above 0, or none")
        return number

    return parse


def _add_demo(sub: Any) -> None:
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


def _demo(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from agos.deploy.run import demo
    from agos.deploy.run.exits import refused

    try:
        return demo.main(cfg, config_path=args.config, port=args.port, attach=args.connect is not None,
                         secure=args.secure, recording=recording_of(args))
    except ValueError as exc:  # a policy or profile name, a run directory: before any process starts
        return refused("demo", exc)


MODEL_LINK_HELP = ("where the model of VLM policies runs: onboard (default: no link), edge, lte, satellite "
                   "(deploy/model_link) or a TOML file; its requests and replies then take simulated time (docs/COMMS.md)")
POSE_ERROR_HELP = ("each role's localisation error: exact (default), gnss-2m, gnss-5m, gnss-10m, urban-gnss "
                   "(deploy/sensing) or a TOML file (docs/COMMS.md)")
POLICY_HELP = "a name (docs/AGENTS.md), one registered in the agos.policies entry points, or package.module:Class"


def _add_eval(sub: Any) -> None:
    ev = sub.add_parser("eval", help="evaluate policies on an episode file: leases, fault tolerance, resume")
    ev.add_argument("--config", type=Path)
    ev.add_argument("--split", type=Path, help="JSONL episode file (e.g. a split's val.jsonl); default: generate")
    ev.add_argument("--policy", help=f"policy of both roles (default {DEFAULT_POLICY}): {POLICY_HELP}")
    ev.add_argument("--policy-uav", help="the UAV's policy (default --policy)")
    ev.add_argument("--policy-ugv", help="the UGV's policy (default --policy)")
    ev.add_argument("--comm", default=DEFAULTS.world.comm.name, help="comm profile name (deploy/comm) or TOML file")
    ev.add_argument("--timing", choices=["lockstep", "realtime"], default=DEFAULTS.world.timing_mode)
    ev.add_argument("--model-link", metavar="PLACEMENT", help=MODEL_LINK_HELP)
    ev.add_argument("--pose-error", metavar="PROFILE", help=POSE_ERROR_HELP)
    ev.add_argument("--uav-verification", choices=["frozen", "active"],
                    help="the UAV while the UGV verifies its candidate: frozen (asked nothing; the paper's method "
                         "section) or active (may move or wait, with a message; its prompt appendix). Default [world] "
                         "uav_during_verification, frozen (docs/AGENTS.md)")
    ev.add_argument("--workers", type=_workers, help="local world worker processes (default 1), or auto: as many "
                    "episodes at once as keep the cores busy while the model thinks (deploy/run/concurrency.py)")
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
    ev.add_argument("--stuck-after", type=float, default=STUCK_AFTER_S,
                    help="re-lease an episode without progress for this long (s)")
    add_record_flags(ev)
    ev.add_argument("--decision-timeout", type=_duration, metavar="DURATION",
                    help="how long the world waits for each decision before it applies WAIT: 90, 30m, 2h "
                         "(default [world] decision_timeout_s, 60 s; a person playing needs minutes or hours)")
    vlm_flags(ev)
    ev.add_argument("--vlm-standin", nargs="?", const="", metavar="FAULTS",
                    help="start the offline stand-in VLM server for this run (optionally with faults, "
                         "e.g. 429=0.1,500=0.05); VLM policies then use it")
    ev.add_argument("--max-cost-usd", type=_cap(float), metavar="USD",
                    help="stop before the next episode could take the run's model calls past USD (needs prices); "
                         "with --resume a new cap, or none (deploy/run/budget.py)")
    ev.add_argument("--max-tokens", type=_cap(int), metavar="N",
                    help="stop before the next episode could take the run's prompt + completion tokens past N")
    price_flags(ev)  # kept in run.json: agos metrics and report use them


def _eval(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from agos.deploy.run import evaluate
    from agos.deploy.run.eval_plan import eval_plan, eval_workers
    from agos.deploy.run.exits import REFUSED, refused

    recording = recording_of(args)  # a bad flag fails before a run directory is made
    try:
        plan = eval_plan(cfg, resume=args.resume, run_dir=args.run_dir, run_id=args.run_id, attach=bool(args.connect),
                         comm=args.comm, timing_mode=args.timing, vlm_standin=args.vlm_standin, workers=args.workers,
                         model_link=args.model_link, pose_error=args.pose_error, max_cost_usd=args.max_cost_usd,
                         max_tokens=args.max_tokens, prices_file=args.prices, price_in=args.price_in,
                         price_out=args.price_out)
    except REFUSED as exc:
        return refused("eval", exc)
    workers, why = eval_workers(cfg, plan, args.workers, attach=bool(args.connect), model_latency_s=args.model_latency)
    if why is not None:
        print(f"world workers: {workers} ({why})")
    return evaluate.run(cfg, plan, workers=workers, attach=args.connect is not None, port=args.port,
                        config_path=args.config, stuck_after_s=args.stuck_after, secure=args.secure,
                        recording=recording)


def _add_sweep(sub: Any) -> None:
    sw = sub.add_parser("sweep", help="a comm-profile parameter grid x link seeds: table and plots with CIs")
    sw.add_argument("--config", type=Path, help="TOML settings file: its [world] section shapes the episodes")
    sw.add_argument("--split", type=Path, required=True, help="JSONL episode file")
    sw.add_argument("--comm", default=DEFAULTS.world.comm.name, help="base profile")
    sw.add_argument("--model-link", metavar="PLACEMENT", help=MODEL_LINK_HELP)
    sw.add_argument("--pose-error", metavar="PROFILE", help=POSE_ERROR_HELP)
    sw.add_argument("--param", default="loss.p",
                    help="dotted profile field (loss.p, latency.mean_s, bandwidth.bits_per_s, range.max_range_m, "
                         "loss.p_bad_to_good, corruption.char_error_rate ...), beacon_s, loss.burst_len / "
                         "blackouts.duration_s, or a profile axis: pose_error, model_link (docs/COMMS.md)")
    sw.add_argument("--values", default="0,0.1,0.2,0.3,0.4,0.5",
                    help="comma-separated values (profile names or TOML files for pose_error, model_link)")
    sw.add_argument("--seeds", default="0,1", help="comma-separated link seeds")
    sw.add_argument("--policy", default=DEFAULT_POLICY, help=f"policy of both roles (default {DEFAULT_POLICY}): {POLICY_HELP}")
    sw.add_argument("--policy-uav", help="the UAV's policy (default --policy)")
    sw.add_argument("--policy-ugv", help="the UGV's policy (default --policy)")
    sw.add_argument("--workers", type=int, default=2)
    sw.add_argument("--out", type=Path, required=True)
    vlm_flags(sw)
    sw.add_argument("--vlm-standin", nargs="?", const="", metavar="FAULTS",
                    help="start the offline stand-in VLM server for the sweep (optionally with faults); "
                         "VLM policies then use it")


def _sweep(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from agos.deploy.run.configure import run_episode_config
    from agos.deploy.run.exits import SWEEP_STOPS, sweep_exit
    from agos.deploy.run.sweep import check_sweep_endpoint, point_config, run_sweep
    from agos.world.episodes.files import read_split

    try:  # everything that can be wrong with the command fails here, before the progress bar
        values = [v.strip() for v in args.values.split(",")]
        seeds = [int(v) for v in args.seeds.split(",")]
        policies = {"uav": args.policy_uav or args.policy, "ugv": args.policy_ugv or args.policy}
        config = run_episode_config(cfg, policies=policies, comm=args.comm, model_link=args.model_link,
                                    pose_error=args.pose_error)
        for value in values:
            point_config(config, args.param, value)  # an unknown --param, or a value it cannot take
        check_sweep_endpoint(policies.values(), cfg.vlm, args.vlm_standin)  # the model endpoint answers /models
        total = len(values) * len(seeds) * len(read_split(args.split, look=config.look))
        with Progress(TextColumn("[bold]sweep"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn()) as bar:
            task = bar.add_task("episodes", total=total)
            table = run_sweep(args.split, args.out, config=config, param=args.param, values=values, seeds=seeds,
                              policies=(policies["uav"], policies["ugv"]), workers=args.workers,
                              progress=lambda: bar.advance(task), vlm=cfg.vlm, vlm_standin=args.vlm_standin)
    except SWEEP_STOPS as exc:  # a bad flag or profile, a replay lacking a call, no model answer, a worker died
        return sweep_exit(exc)
    print((args.out / "sweep.md").read_text())
    print(f"{len(table)} points -> {args.out}/sweep.csv, sweep.md, sweep.png")
    return 0


def _add_check(sub: Any) -> None:
    check = sub.add_parser("check", help="conformance checks")
    check_sub = check.add_subparsers(dest="check_what", required=True)
    check_agent = check_sub.add_parser("agent", help="a short conformance episode against attached agent services")
    connection_flags(check_agent)
    check_agent.add_argument("--budget", type=int, default=16, help="decisions in the check episode (default 16)")
    check_agent.add_argument("--town", default=DEFAULT_TOWN, help="procedural town of the check episode")
    check_agent.add_argument("--policy", default=DEFAULT_POLICY,
                             help="policy the agents run, for the world's tools (baseline: no candidates; ablations; "
                                  "package.module:Class: every tool)")
    check_agent.add_argument("--policy-uav", help="the UAV agent's policy, for the world's tools (default --policy)")
    check_agent.add_argument("--policy-ugv", help="the UGV agent's policy, for the world's tools (default --policy)")
    check_agent.add_argument("--agent-wait", type=float,
                             help=f"seconds to wait for each role's service (default {DEFAULTS.run.agent_wait_s:g})")


def _check_agent(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from agos.deploy.run.check import run_check
    from agos.deploy.run.exits import refused

    policies = {"uav": args.policy_uav or args.policy, "ugv": args.policy_ugv or args.policy}
    try:
        return run_check(cfg, budget=args.budget, town_name=args.town, policies=policies)
    except ValueError as exc:  # a policy name that names none: before the bus is opened
        return refused("check", exc)


DEMO = Command(("demo",), _add_demo, with_settings(_demo))
EVAL = Command(("eval",), _add_eval, with_settings(_eval))
SWEEP = Command(("sweep",), _add_sweep, with_settings(_sweep))
CHECK = Command(("check",), _add_check, by_subcommand("check_what", {"agent": with_settings(_check_agent)}))
