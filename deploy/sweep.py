"""``agos sweep``: how a link parameter changes cooperation.

A grid of values of one comm-profile parameter (``loss.p``, ``latency.mean_s``,
``bandwidth.bits_per_s``, ``range.max_range_m`` ...) times link seeds, each point run on the same
episodes. Episodes run in parallel worker processes with the policies called in-process (the link
model lives in the world, so this measures exactly what `agos eval` would, without a router;
the same seed gives the same numbers). Writes ``points/*.jsonl`` (episode records), ``sweep.csv``,
``sweep.md`` and one PNG per metric (SR, SPL, DS) with 95 % bootstrap intervals over episodes.
"""

from __future__ import annotations

import csv
import hashlib
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agos.runtime.codec import from_json, to_json
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.links import CommProfile
from agos.runtime.process import interruptible_imap
from agos.runtime.schemas import EpisodeRecord

METRICS = ("SR", "SPL", "DS")


def with_param(profile: CommProfile, param: str, value: float) -> CommProfile:
    """A copy of ``profile`` with a dotted parameter set (``loss.p`` also switches Bernoulli loss on)."""
    data = profile.model_dump()
    section, _, key = param.partition(".")
    if section not in data or not isinstance(data[section], dict) or key not in data[section]:
        raise ValueError(f"sweep parameter {param!r}: not a field of a comm profile (e.g. loss.p, latency.mean_s)")
    data[section][key] = value
    if param == "loss.p" and data["loss"]["model"] == "none":
        data["loss"]["model"] = "bernoulli"
    data["name"] = f"{profile.name}[{param}={value:g}]"
    return CommProfile.model_validate(data)


@dataclass(frozen=True)
class Point:
    value: float
    seed: int


_CACHE: dict[str, Any] = {}


def _run_point_episode(args: tuple[str, str, list[str], str]) -> tuple[int, str]:
    """Worker process: one episode under one point's episode configuration; returns (point, record JSON)."""
    config_json, episode_json, policies, point = args
    from agos.agents.inprocess import InProcessAgents
    from agos.agents.registry import make_policy
    from agos.runtime.episode_config import EpisodeConfig
    from agos.runtime.schemas import EpisodeSpec
    from agos.world.sim.engine import EpisodeRunner
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import town_for

    spec = from_json(episode_json, EpisodeSpec)
    key = spec.asset_sha256
    if key not in _CACHE:
        town = town_for(spec.town.generator, spec.town.seed, spec.asset_sha256, town_id=spec.town.town_id)
        _CACHE[key] = (town, Scene(town.layout))
    town, scene = _CACHE[key]
    config = EpisodeConfig.model_validate_json(config_json)
    agents = InProcessAgents({"uav": make_policy(policies[0], "uav"), "ugv": make_policy(policies[1], "ugv")})
    record = EpisodeRunner(scene, town, spec, run_id="sweep", worker_id="sweep",
                           config=config).run(agents)
    return int(point), to_json(record).decode()


def run_sweep(episodes_file: Path, out_dir: Path, *, config: EpisodeConfig, param: str, values: list[float],
              seeds: list[int], policies: tuple[str, str], workers: int,
              progress: Callable[[], None] | None = None) -> list[dict]:
    """Run every episode at every (value, link seed) point: ``config`` (from
    :func:`agos.deploy.configure.episode_config`) with its comm profile's ``param`` set to the value
    and ``link_seed`` to the seed."""
    from agos.world.episodes.sampling import read_episodes

    episodes = read_episodes(episodes_file)
    points = [Point(v, s) for v in values for s in seeds]
    point_configs = [config.model_copy(update={"comm": with_param(config.comm, param, p.value), "link_seed": p.seed})
                     for p in points]
    # Each finished episode is appended to its point's file in OUT/.episodes at once, so Ctrl-C loses
    # only the episodes in flight and the next run of the same sweep plays only what is missing.
    # A file's name carries the hash of everything that shapes its records (never reused wrongly).
    done_dir = out_dir / ".episodes"
    done_dir.mkdir(parents=True, exist_ok=True)
    done_files = [done_dir / f"{i}-{_point_key(point_configs[i].model_dump_json(), policies)}.jsonl" for i in range(len(points))]
    results: dict[int, list[str]] = {i: (f.read_text().splitlines() if f.exists() else []) for i, f in enumerate(done_files)}
    finished = {(i, from_json(line, EpisodeRecord).episode_id) for i, lines in results.items() for line in lines}
    jobs = [(point_configs[i].model_dump_json(), to_json(e).decode(), list(policies), str(i))
            for i in range(len(points)) for e in episodes if (i, e.episode_id) not in finished]
    for _ in range(len(finished)):
        if progress:
            progress()
    for i, line in interruptible_imap(_run_point_episode, jobs, workers):  # Ctrl-C: finished ones are on disk
        with done_files[i].open("a") as fh:
            fh.write(line + "\n")
        results[i].append(line)
        if progress:
            progress()
    (out_dir / "points").mkdir(parents=True, exist_ok=True)
    rows = []
    for i, point in enumerate(points):
        lines = sorted(results[i])
        (out_dir / "points" / f"{param}={point.value:g}_seed{point.seed}.jsonl").write_text("\n".join(lines) + "\n")
        rows.append({"value": point.value, "seed": point.seed, "records": lines})
    table = summarize(rows, out_dir, param)
    shutil.rmtree(done_dir, ignore_errors=True)
    return table


def _point_key(config_json: str, policies: tuple[str, str]) -> str:
    return hashlib.sha256((config_json + "|" + "|".join(policies)).encode()).hexdigest()[:12]


def _bootstrap_ci(values: np.ndarray, rng: np.random.Generator, resamples: int = 2000) -> tuple[float, float]:
    if len(values) < 2:
        return float(values.mean()), float(values.mean())
    means = values[rng.integers(0, len(values), size=(resamples, len(values)))].mean(axis=1)
    low, high = np.percentile(means, [2.5, 97.5])
    return float(low), float(high)


def summarize(rows: list[dict], out_dir: Path, param: str) -> list[dict]:
    from agos.evaluator.metrics import decision_steps, spl, success
    from agos.evaluator.summary import EpisodeSummary

    rng = np.random.default_rng(0)
    by_value: dict[float, list] = {}
    for row in rows:
        eps = [EpisodeSummary.from_valid(__import__("json").loads(line)) for line in row["records"]]
        by_value.setdefault(row["value"], []).extend(eps)
    table = []
    for value in sorted(by_value):
        eps = [e for e in by_value[value] if e.status == "finished"]
        entry: dict[str, Any] = {"value": value, "episodes": len(eps)}
        for name, fn in (("SR", success), ("SPL", spl), ("DS", decision_steps)):
            arr = np.array([fn(e) for e in eps], dtype=float)
            low, high = _bootstrap_ci(arr, rng)
            entry[name], entry[f"{name}_low"], entry[f"{name}_high"] = float(arr.mean()), low, high
        rates = [e.link["delivery_rate"] for e in eps if e.link and e.link.get("delivery_rate") is not None]
        entry["delivery_rate"] = float(np.mean(rates)) if rates else None
        table.append(entry)
    with (out_dir / "sweep.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(table[0]))
        writer.writeheader()
        writer.writerows(table)
    lines = [f"| {param} | episodes | delivered % | SR % [95% CI] | SPL % [95% CI] | DS [95% CI] |",
             "|---:|---:|---:|---|---|---|"]
    for t in table:
        delivered = "-" if t["delivery_rate"] is None else f"{100 * t['delivery_rate']:.1f}"
        lines.append(f"| {t['value']:g} | {t['episodes']} | {delivered} | {100 * t['SR']:.1f} [{100 * t['SR_low']:.1f}, "
                     f"{100 * t['SR_high']:.1f}] | {100 * t['SPL']:.1f} [{100 * t['SPL_low']:.1f}, {100 * t['SPL_high']:.1f}] "
                     f"| {t['DS']:.1f} [{t['DS_low']:.1f}, {t['DS_high']:.1f}] |")
    (out_dir / "sweep.md").write_text("\n".join(lines) + "\n")
    _plots(table, out_dir, param)
    return table


def _plots(table: list[dict], out_dir: Path, param: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [t["value"] for t in table]
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.2), dpi=140)
    for ax, name in zip(axes, METRICS, strict=True):
        scale = 1.0 if name == "DS" else 100.0
        y = [scale * t[name] for t in table]
        lo = [scale * (t[name] - t[f"{name}_low"]) for t in table]
        hi = [scale * (t[f"{name}_high"] - t[name]) for t in table]
        ax.errorbar(x, y, yerr=[lo, hi], marker="o", capsize=3)
        ax.set_xlabel(param)
        ax.set_ylabel(name + ("" if name == "DS" else " (%)"))
        ax.set_title(f"{name} vs {param} (95% CI)", fontsize=9)
        ax.grid(alpha=0.3)
        if name != "DS":
            ax.set_ylim(0, 105)
    fig.tight_layout()
    fig.savefig(out_dir / "sweep.png")
    plt.close(fig)
