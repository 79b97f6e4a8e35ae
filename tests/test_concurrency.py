"""``agos eval --workers auto``: the concurrency rule (deploy/run/concurrency.py), the latencies policy
names carry, and how bench/bench_eval.py counts decision rounds. No wall-clock figures here."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import pytest

from agos.agents.names import known_latency_s, parse_standin
from agos.deploy.cli import build_parser
from agos.deploy.run.concurrency import CPU_PER_ROUND_S, HEADROOM, auto_workers, run_latency_s
from agos.runtime.schemas import Pose, StepEvent


def test_enough_workers_to_keep_the_cores_busy_while_the_model_thinks() -> None:
    # One worker is busy c / (c + L) of the time: cores x (c + L) / c of them fill the cores if their
    # bursts never collide; HEADROOM times that because they do.
    def n(latency: float, cores: int, headroom: float) -> int:
        return auto_workers(latency_s=latency, cores=cores, episodes=10_000, cpu_per_round_s=0.1, headroom=headroom).workers

    assert n(1.0, 2, 1.0) == 22
    assert n(0.3, 4, 1.0) == 16
    assert n(1.0, 2, 1.5) == 33
    assert auto_workers(latency_s=1.0, cores=2, episodes=10_000).workers == math.ceil(
        HEADROOM * 2 * (CPU_PER_ROUND_S + 1.0) / CPU_PER_ROUND_S)


def test_no_latency_or_an_unknown_one_means_one_worker_per_core() -> None:
    assert auto_workers(latency_s=0.0, cores=4, episodes=100).workers == 4
    unknown = auto_workers(latency_s=None, cores=2, episodes=100)
    assert unknown.workers == 2
    assert "--model-latency" in unknown.why


def test_more_latency_or_more_cores_never_means_fewer_workers() -> None:
    def n(latency: float, cores: int) -> int:
        return auto_workers(latency_s=latency, cores=cores, episodes=10_000).workers

    latencies = [0.0, 0.05, 0.2, 0.5, 1.0, 2.0, 5.0]
    for cores in (1, 2, 8):
        counts = [n(latency, cores) for latency in latencies]
        assert counts == sorted(counts)
    for latency in latencies:
        counts = [n(latency, cores) for cores in (1, 2, 4, 16)]
        assert counts == sorted(counts)


def test_capped_by_episodes_memory_and_the_model_endpoint() -> None:
    assert auto_workers(latency_s=1.0, cores=2, episodes=5).workers == 5
    memory = auto_workers(latency_s=1.0, cores=2, episodes=1000, available_mb=3000, worker_rss_mb=300)
    assert memory.workers == 5 and "memory" in memory.why  # half of the available memory
    model = auto_workers(latency_s=2.0, cores=2, episodes=1000, model_concurrency=8)
    assert model.workers == 8 and "model concurrency" in model.why
    assert auto_workers(latency_s=1.0, cores=2, episodes=0).workers == 1
    assert auto_workers(latency_s=1.0, cores=2, episodes=1000, available_mb=10).workers == 1


def test_workers_are_spread_evenly_over_the_waves() -> None:
    # 50 episodes with room for 37 at once would leave a second wave of 13 beside 24 idle workers:
    # two waves of 25 take as long with fewer processes.
    ideal = math.ceil(HEADROOM * 2 * (CPU_PER_ROUND_S + 1.0) / CPU_PER_ROUND_S)
    assert 25 < ideal < 50
    choice = auto_workers(latency_s=1.0, cores=2, episodes=50)
    assert choice.workers == 25
    assert "2 waves" in choice.why


def test_latency_from_policy_names() -> None:
    assert parse_standin("standin-200ms") == 0.2
    assert known_latency_s("standin-1000ms") == 1.0
    assert known_latency_s("heuristic:no_rgpp") == 0.0
    assert known_latency_s("oracle") == 0.0
    assert known_latency_s("agos-agent") is None and known_latency_s("baseline") is None
    assert run_latency_s({"uav": "standin-1000ms", "ugv": "standin-200ms"}) == 1.0  # roles asked together overlap
    assert run_latency_s({"uav": "agos-agent", "ugv": "heuristic"}) is None
    assert run_latency_s({"uav": "agos-agent", "ugv": "agos-agent"}, model_latency_s=2.5) == 2.5
    with pytest.raises(ValueError):
        known_latency_s("standin-fast")


def test_eval_takes_workers_auto_and_a_model_latency() -> None:
    args = build_parser().parse_args(["eval", "--workers", "auto", "--model-latency", "2"])
    assert args.workers == "auto" and args.model_latency == 2.0
    assert build_parser().parse_args(["eval", "--workers", "3"]).workers == 3
    with pytest.raises(SystemExit):
        build_parser().parse_args(["eval", "--workers", "many"])


def _bench_eval():
    """bench/bench_eval.py as a module (registered first: its dataclasses look their module up)."""
    if "bench_eval" not in sys.modules:
        bench_dir = Path(__file__).resolve().parents[1] / "bench"
        if str(bench_dir) not in sys.path:
            sys.path.insert(0, str(bench_dir))  # its sibling modules (figures), as when run as a script
        path = bench_dir / "bench_eval.py"
        spec = importlib.util.spec_from_file_location("bench_eval", path)
        assert spec is not None and spec.loader is not None
        sys.modules["bench_eval"] = module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    return sys.modules["bench_eval"]


def _step(step: int, role: str, sim_time: float) -> StepEvent:
    return StepEvent(run_id="r", episode_id="e", role=role, decision_index=step, episode_step=step,
                     sim_time_s=sim_time, requested=None, applied="WAIT", pose_after=Pose(position_world_m=(0, 0, 0), yaw_rad=0))


def test_decision_rounds_count_the_roles_asked_together_once() -> None:
    bench = _bench_eval()
    steps = [
        (1.0, _step(1, "uav", 0.0)), (1.01, _step(2, "ugv", 0.0)),  # both due at t=0: one round
        (2.0, _step(3, "uav", 4.0)),  # the UAV alone
        (3.0, _step(4, "ugv", 4.0)),  # the UGV at the same sim time but a latency later: woken, its own round
        (4.0, _step(5, "ugv", 6.0)), (4.01, _step(6, "uav", 6.0)),  # UGV then UAV: never one round
    ]
    assert bench.decision_rounds(steps, 1.0) == 5
    assert bench.decision_rounds(list(reversed(steps)), 1.0) == 5  # ordered by episode_step
    assert bench.model_floor([79, 60, 70], 1.0, 2) == (79.0, 104.5)


def test_stratified_sample_takes_each_difficulty_in_file_order() -> None:
    bench = _bench_eval()
    lines = [f'{{"difficulty": "{d}", "i": {i}}}' for d in ("easy", "mid", "hard") for i in range(5)]
    sample = bench.stratified_sample(lines, 7)
    assert [line.split('"')[3] for line in sample] == ["easy"] * 3 + ["mid"] * 2 + ["hard"] * 2
    assert sample[0].endswith('"i": 0}') and sample[2].endswith('"i": 2}')
