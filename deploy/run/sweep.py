"""``agos sweep``: how a link parameter changes cooperation.

A grid of values of one comm-profile parameter times link seeds, each point run on the same
episodes. Episodes run in parallel worker processes with the policies called in-process (the link
model lives in the world, so this measures exactly what `agos eval` would, without a router;
the same seed gives the same numbers). VLM policies ask the endpoint of ``[vlm]`` (or a stand-in
server the sweep starts itself, ``vlm_standin``). Writes ``points/*.jsonl`` (episode records),
``sweep.csv``, ``sweep.md`` and ``sweep.png`` with 95 % bootstrap intervals over episodes. Each worker
process ``sweep-K`` logs to ``logs/sweep-K.log``; one that dies stops the sweep with
:class:`~agos.runtime.deaths.ChildDied` (how it died, the last lines of that log), its finished
episodes kept.

The parameter is any field of a profile section (``loss.p``, ``latency.mean_s``,
``bandwidth.bits_per_s``, ``bandwidth.queue_bytes``, ``range.max_range_m``, ``range.nlos_loss``,
the Gilbert-Elliott ``loss.p_good_to_bad`` ... on a Gilbert-Elliott base), ``beacon_s``, or one of
two derived axes: ``loss.burst_len`` (mean stay in the bad state, in transmissions, at the base
profile's share of time in the bad state, so the mean loss stays put while bursts lengthen) and
``blackouts.duration_s`` (every blackout of the base profile lasts this long from its start). Two
axes take profile names instead of numbers: ``pose_error`` (each role's localisation error,
deploy/sensing: ``exact,gnss-2m,gnss-5m``) and ``model_link`` (where the model runs, deploy/model_link:
``onboard,edge,lte,satellite``); their values may also be TOML files.

Besides SR, SPL and DS the table has CErr and ACG, the episode's simulated duration and the *handoff delay*: from
the UAV's first annotation to the UGV hearing of it, read from the ledger (the UAV's first sync or
beacon that carries a candidate, and the first of those that was delivered), with how many
episodes' first candidate never reached the UGV.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from agos.runtime.codec import from_json, to_json
from agos.runtime.episode_config import EpisodeConfig
from agos.runtime.links import CommProfile
from agos.runtime.process import interruptible_imap
from agos.runtime.schemas import EpisodeRecord
from agos.runtime.settings import VlmOptions

METRICS = ("SR", "SPL", "CErr", "ACG", "DS", "T", "handoff")
LABELS = {"SR": "SR (%)", "SPL": "SPL (%)", "CErr": "CErr (m)", "ACG": "ACG (%)", "DS": "DS", "T": "episode sim time (s)",
          "handoff": "handoff delay (s)"}
GILBERT_ELLIOTT = ("p_good_to_bad", "p_bad_to_good", "loss_good", "loss_bad")
DERIVED = ("loss.burst_len", "blackouts.duration_s")


PROFILE_AXES = ("pose_error", "model_link")
"""Axes whose values name profiles (or TOML files) rather than numbers."""


def point_config(config: EpisodeConfig, param: str, value: str) -> EpisodeConfig:
    """``config`` at one value of the sweep's axis: a pose-error profile, a model placement, or a number
    for a comm-profile parameter (:func:`with_param`). Raises ValueError (one line) for what cannot be."""
    if param == "pose_error":
        from agos.runtime.sensing import load_pose_error

        return config.model_copy(update={"pose_error": load_pose_error(value)})
    if param == "model_link":
        from agos.runtime.episode_config import with_model_link

        return with_model_link(config, value)
    try:
        number = float(value)
    except ValueError:
        raise ValueError(f"sweep parameter {param}: value {value!r} is not a number") from None
    return config.model_copy(update={"comm": with_param(config.comm, param, number)})


def value_label(param: str, value: str) -> str:
    """How a value is written in tables and file names (numbers as ``:g``)."""
    return value if param in PROFILE_AXES else f"{float(value):g}"


def point_file_name(param: str, label: str, seed: int) -> str:
    """``points/<param>=<value>_seed<seed>.jsonl``; a profile given as a TOML file is named by its stem
    (a number keeps its dots: ``loss.p=0.25``)."""
    value = Path(label).stem if param in PROFILE_AXES and label.endswith(".toml") else label
    return f"{param}={value}_seed{seed}.jsonl"


def with_param(profile: CommProfile, param: str, value: float) -> CommProfile:
    """A copy of ``profile`` with one parameter set (see the module; ``loss.p`` also switches Bernoulli loss on).

    Raises ValueError (one line) naming the parameter when it is not one, when the value is out of its
    range, or when the base profile lacks what it changes (a Gilbert-Elliott field on a profile without
    that loss model, a blackout length on a profile without blackouts)."""
    data = profile.model_dump()
    section, _, key = param.partition(".")
    if param == "beacon_s":
        data["beacon_s"] = value
    elif param == "loss.burst_len":
        _set_burst_len(profile, data["loss"], value)
    elif param == "blackouts.duration_s":
        if not profile.blackouts:
            raise ValueError(f"sweep parameter {param}: the base profile {profile.name!r} has no blackouts "
                             "(use e.g. --comm outage)")
        data["blackouts"] = [{"start_s": b.start_s, "end_s": b.start_s + value} for b in profile.blackouts]
    elif section not in data or not isinstance(data[section], dict) or key not in data[section]:
        raise ValueError(f"sweep parameter {param!r}: not a field of a comm profile (e.g. loss.p, latency.mean_s, "
                         f"beacon_s, {', '.join(DERIVED)})")
    elif section == "loss" and key in GILBERT_ELLIOTT and profile.loss.model != "gilbert_elliott":
        raise ValueError(f"sweep parameter {param}: the base profile {profile.name!r} has no Gilbert-Elliott loss "
                         "(use e.g. --comm bursty or --comm fading)")
    else:
        data[section][key] = value
        if param == "loss.p" and data["loss"]["model"] == "none":
            data["loss"]["model"] = "bernoulli"
    data["name"] = f"{profile.name}[{param}={value:g}]"
    try:
        return CommProfile.model_validate(data)
    except ValidationError as exc:  # one line, as every other refusal here (pydantic's own spans several)
        raise ValueError(f"sweep parameter {param}={value:g}: {exc.errors()[0]['msg']}") from None


def _set_burst_len(profile: CommProfile, loss: dict[str, Any], burst: float) -> None:
    """Gilbert-Elliott with a mean stay of ``burst`` transmissions in the bad state, keeping the base
    profile's stationary share of the bad state p_gb / (p_gb + p_bg) (hence its mean loss rate)."""
    if profile.loss.model != "gilbert_elliott":
        raise ValueError(f"sweep parameter loss.burst_len: the base profile {profile.name!r} has no Gilbert-Elliott "
                         "loss (use e.g. --comm bursty or --comm fading)")
    if burst < 1:
        raise ValueError(f"sweep parameter loss.burst_len: {burst:g} transmissions; a burst lasts at least 1")
    share = profile.loss.p_good_to_bad / (profile.loss.p_good_to_bad + profile.loss.p_bad_to_good)
    if share >= 1:
        raise ValueError(f"loss.burst_len: the base profile {profile.name!r} never leaves the bad state")
    loss["p_bad_to_good"] = 1.0 / burst
    loss["p_good_to_bad"] = share / (1 - share) / burst
    if loss["p_good_to_bad"] > 1:
        raise ValueError(f"loss.burst_len={burst:g}: with {share:.0%} of the time in the bad state, bursts this short "
                         "would need p_good_to_bad > 1")


@dataclass(frozen=True)
class Point:
    value: str
    seed: int


_CACHE: dict[tuple[str, str], Any] = {}


def _run_point_episode(args: tuple[str, str, list[str], str, str]) -> tuple[int, str]:
    """Worker process: one episode under one point's episode configuration, played by an
    :class:`agos.Env` on this process's scene of the town (illegal answers are the world's counted
    WAITs, as over the bus); returns (point, record JSON)."""
    config_json, episode_json, policies, point, vlm_json = args
    from agos.agents.registry import make_policy
    from agos.env import Env
    from agos.runtime.episode_config import EpisodeConfig
    from agos.runtime.schemas import EpisodeSpec
    from agos.runtime.settings import VlmOptions
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import town_for

    spec = from_json(episode_json, EpisodeSpec)
    config = EpisodeConfig.model_validate_json(config_json)
    key = (spec.asset_sha256, config.look)
    if key not in _CACHE:
        town = town_for(spec.town.generator, spec.town.seed, spec.asset_sha256, town_id=spec.town.town_id)
        _CACHE[key] = (town, Scene(town.layout, look=config.look))
    town, scene = _CACHE[key]
    vlm = VlmOptions.model_validate_json(vlm_json) if vlm_json else None
    with Env(spec, config, illegal="wait", run_id="sweep", worker_id="sweep", scene=scene, town=town) as env:
        record = env.play({"uav": make_policy(policies[0], "uav", vlm=vlm), "ugv": make_policy(policies[1], "ugv", vlm=vlm)})
    return int(point), to_json(record).decode()


def check_sweep_endpoint(policies: Iterable[str], vlm: VlmOptions, vlm_standin: str | None) -> None:
    """The endpoint a sweep's VLM policies will ask answers ``/models`` and lists the model
    (deploy/run/plan.py::check_endpoint; an EndpointError is one line); nothing to check without a
    VLM policy, with the stand-in the sweep starts itself, or without an endpoint (make_policy says)."""
    from agos.agents.names import needs_vlm
    from agos.deploy.run.plan import check_endpoint

    if vlm_standin is None and vlm.base_url and vlm.model and any(needs_vlm(p) for p in policies):
        check_endpoint(vlm, {"base_url": vlm.base_url, "model": vlm.model})


def run_sweep(episodes_file: Path, out_dir: Path, *, config: EpisodeConfig, param: str, values: list[str],
              seeds: list[int], policies: tuple[str, str], workers: int,
              progress: Callable[[], None] | None = None, vlm: VlmOptions | None = None,
              vlm_standin: str | None = None) -> list[dict]:
    """Run every episode at every (value, link seed) point: ``config`` (from
    :func:`agos.deploy.run.configure.run_episode_config`) at the axis value (:func:`point_config`) and
    ``link_seed`` at the seed. VLM policies ask ``vlm``'s endpoint, or, with ``vlm_standin`` (a
    fault string, "" for none), a stand-in server started here for the sweep's duration."""
    from agos.agents.names import needs_vlm

    for value in values:  # a bad parameter or value fails before anything runs
        point_config(config, param, value)
    options = (vlm or VlmOptions()) if any(needs_vlm(p) for p in policies) else None
    if options is None or vlm_standin is None:
        return _run_sweep(episodes_file, out_dir, config=config, param=param, values=values, seeds=seeds,
                          policies=policies, workers=workers, progress=progress, vlm=options)
    from agos.agents.vlm.standin.faults import parse_faults
    from agos.agents.vlm.standin.server import DEFAULT_MODELS, StandinServer

    with StandinServer(faults=parse_faults(vlm_standin)) as server:
        options = options.model_copy(update={"base_url": server.url, "model": DEFAULT_MODELS[0]})
        return _run_sweep(episodes_file, out_dir, config=config, param=param, values=values, seeds=seeds,
                          policies=policies, workers=workers, progress=progress, vlm=options,
                          key_extra=f"standin:{vlm_standin}")


def _run_sweep(episodes_file: Path, out_dir: Path, *, config: EpisodeConfig, param: str, values: list[str],
               seeds: list[int], policies: tuple[str, str], workers: int, progress: Callable[[], None] | None,
               vlm: VlmOptions | None, key_extra: str = "") -> list[dict]:
    from agos.agents.registry import make_policy
    from agos.world.episodes.files import read_episodes

    make_policy(policies[0], "uav", vlm=vlm)  # a missing endpoint fails here, not in a worker
    make_policy(policies[1], "ugv", vlm=vlm)
    vlm_json = vlm.model_dump_json() if vlm is not None else ""
    if vlm is not None and not key_extra:
        key_extra = f"{vlm.base_url}|{vlm.model}"
    if vlm is not None and (vlm.image_max_px, vlm.jpeg_quality) != (None, None):  # what the model is sent
        key_extra += f"|images:{vlm.image_max_px}:{vlm.jpeg_quality}"
    episodes = read_episodes(episodes_file)
    points = [Point(v, s) for v in values for s in seeds]
    point_configs = [point_config(config, param, p.value).model_copy(update={"link_seed": p.seed}) for p in points]
    # Each finished episode is appended to its point's file in OUT/.episodes at once, so Ctrl-C loses
    # only the episodes in flight and the next run of the same sweep plays only what is missing;
    # the store outlives the sweep, so a finished sweep given another value plays only that value.
    # A file's name is the hash of everything that shapes its records (never reused wrongly), and only
    # that: a point already played is found again when the next run lists other values beside it.
    done_dir = out_dir / ".episodes"
    done_dir.mkdir(parents=True, exist_ok=True)
    keys = [_point_key(c.model_dump_json(), policies, key_extra) for c in point_configs]
    if len(set(keys)) < len(keys):
        raise ValueError(f"sweep parameter {param}: a value is given twice, or two values make the same episodes")
    for i, key in enumerate(keys):  # what an earlier agos named by point index too
        if (legacy := done_dir / f"{i}-{key}.jsonl").exists():
            legacy.rename(done_dir / f"{key}.jsonl")
    done_files = [done_dir / f"{key}.jsonl" for key in keys]
    results: dict[int, list[str]] = {i: (f.read_text().splitlines() if f.exists() else []) for i, f in enumerate(done_files)}
    finished = {(i, from_json(line, EpisodeRecord).episode_id) for i, lines in results.items() for line in lines}
    jobs = [(point_configs[i].model_dump_json(), to_json(e).decode(), list(policies), str(i), vlm_json)
            for i in range(len(points)) for e in episodes if (i, e.episode_id) not in finished]
    for _ in range(len(finished)):
        if progress:
            progress()
    for i, line in interruptible_imap(_run_point_episode, jobs, workers,  # Ctrl-C: finished ones are on disk
                                      name="sweep", log_dir=out_dir / "logs"):
        with done_files[i].open("a") as fh:
            fh.write(line + "\n")
        results[i].append(line)
        if progress:
            progress()
    (out_dir / "points").mkdir(parents=True, exist_ok=True)
    rows = []
    for i, point in enumerate(points):
        lines = sorted(results[i])
        label = value_label(param, point.value)
        (out_dir / "points" / point_file_name(param, label, point.seed)).write_text("\n".join(lines) + "\n")
        rows.append({"value": label, "seed": point.seed, "records": lines})
    # The store stays after a finished sweep: the same command with a value added plays only that value.
    return summarize(rows, out_dir, param)


def _point_key(config_json: str, policies: tuple[str, str], extra: str = "") -> str:
    tail = f"|{extra}" if extra else ""  # scripted policies keep the keys they always had
    return hashlib.sha256((config_json + "|" + "|".join(policies) + tail).encode()).hexdigest()[:12]


def _bootstrap_ci(values: np.ndarray, rng: np.random.Generator, resamples: int = 2000) -> tuple[float, float]:
    if len(values) < 2:
        return float(values.mean()), float(values.mean())
    means = values[rng.integers(0, len(values), size=(resamples, len(values)))].mean(axis=1)
    low, high = np.percentile(means, [2.5, 97.5])
    return float(low), float(high)


def handoff_delay(record: dict[str, Any]) -> float | None:
    """Seconds from the UAV's first annotation until the UGV heard of it; ``inf`` when it never did,
    None when the UAV annotated nothing (or the record has no ledger).

    Read from the ledger: a sync carries the sender's candidates, and one without any has exactly
    ``EMPTY_SYNC_BYTES``; so the UAV's first larger sync or beacon was sent at its first annotation,
    and the first of those delivered told the UGV."""
    from agos.world.sim.comms import EMPTY_SYNC_BYTES

    carrying = [e for e in record.get("ledger") or []
                if e["sender"] == "uav" and e["kind"] != "message" and e["size_bytes"] > EMPTY_SYNC_BYTES]
    if not carrying:
        return None
    arrivals = [e["arrive_s"] for e in carrying if e["delivered"]]
    return min(arrivals) - carrying[0]["sent_s"] if arrivals else math.inf


def summarize(rows: list[dict], out_dir: Path, param: str) -> list[dict]:
    """One table row per axis value (in the order given), every metric with a 95 % bootstrap interval
    over episodes; ``sweep.csv``, ``sweep.md`` and ``sweep.png`` in ``out_dir``. Columns that only a
    localisation error or a link to the model fill appear when a record has them."""
    from agos.evaluator.metrics import acg, decision_steps, spl, success
    from agos.evaluator.summary import EpisodeSummary

    rng = np.random.default_rng(0)
    by_value: dict[str, list[tuple[EpisodeSummary, dict[str, Any]]]] = {}
    for row in rows:
        raw = [json.loads(line) for line in row["records"]]
        by_value.setdefault(row["value"], []).extend((EpisodeSummary.from_valid(r), r) for r in raw)
    table = []
    for value in by_value:
        pairs = [(e, r) for e, r in by_value[value] if e.status == "finished"]
        eps = [e for e, _ in pairs]
        entry: dict[str, Any] = {"value": value, "episodes": len(eps)}
        for name, fn in (("SR", success), ("SPL", spl), ("ACG", acg), ("DS", decision_steps)):
            entry.update(_mean_ci(name, np.array([fn(e) for e in eps], dtype=float), rng))
        entry.update(_pooled_ci("CErr", [[c.center_error_m for c in e.candidates] for e in eps], rng))
        entry.update(_mean_ci("T", np.array([r["sim_time_s"] for _, r in pairs], dtype=float), rng))
        delays = [d for d in (handoff_delay(r) for _, r in pairs) if d is not None]
        entry.update(_mean_ci("handoff", np.array([d for d in delays if math.isfinite(d)], dtype=float), rng))
        entry["handoff_never"] = sum(not math.isfinite(d) for d in delays)
        entry["handoff_episodes"] = len(delays)
        entry["handoff_never_pct"] = 100.0 * entry["handoff_never"] / len(delays) if delays else None
        rates = [e.link["delivery_rate"] for e in eps if e.link and e.link.get("delivery_rate") is not None]
        entry["delivery_rate"] = float(np.mean(rates)) if rates else None
        errors = [s["mean_m"] for _, r in pairs for s in (r.get("pose_error") or {}).values()]
        entry["pose_error_m"] = float(np.mean(errors)) if errors else None
        links = [r["model_link"] for _, r in pairs if r.get("model_link") and r["model_link"]["decisions"]]
        decisions = sum(m["decisions"] for m in links)
        entry["model_link_s"] = sum(m["link_time_s"] for m in links) / decisions if decisions else None
        entry["model_up_kb"] = sum(m["bytes_up"] for m in links) / decisions / 1000 if decisions else None
        entry["corrupted"] = sum((r.get("link") or {}).get("corrupted", 0) for _, r in pairs)
        table.append(entry)
    with (out_dir / "sweep.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(table[0]))
        writer.writeheader()
        writer.writerows(table)
    (out_dir / "sweep.md").write_text(markdown_table(table, param))
    _plots(table, out_dir, param)
    return table


def markdown_table(table: list[dict], param: str) -> str:
    """The sweep's table as Markdown (what ``sweep.md`` holds)."""
    extra = [(key, head, fmt) for key, head, fmt in (("pose_error_m", "pose error m", ".2f"),
                                                    ("model_link_s", "model link s/decision", ".2f"),
                                                    ("model_up_kb", "kB up/decision", ".0f"),
                                                    ("corrupted", "corrupted messages", "d"))
             if any(t[key] for t in table)]
    head = [param, "episodes", "delivered %", *(h for _, h, _ in extra), "SR % [95% CI]", "CErr m [95% CI]",
            "ACG % [95% CI]", "SPL % [95% CI]", "DS [95% CI]", "time s [95% CI]", "handoff s [95% CI] (never/annotated)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---:|" * (3 + len(extra)) + "---|" * 7]
    for t in table:
        delivered = "-" if t["delivery_rate"] is None else f"{100 * t['delivery_rate']:.1f}"
        cells = [str(t["value"]), str(t["episodes"]), delivered,
                 *("-" if t[key] is None else f"{t[key]:{fmt}}" for key, _, fmt in extra),
                 _cell(t, "SR", 100), _cell(t, "CErr"), _cell(t, "ACG", 100), _cell(t, "SPL", 100), _cell(t, "DS"),
                 _cell(t, "T", fmt=".0f"), f"{_cell(t, 'handoff')} ({t['handoff_never']}/{t['handoff_episodes']})"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _pooled_ci(name: str, per_episode: list[list[float]], rng: np.random.Generator,
               resamples: int = 2000) -> dict[str, float | None]:
    """The mean over every value of every episode (candidate-level pooling, as CErr), with a 95 % interval
    from resampling episodes (their values stay together)."""
    flat = [v for vs in per_episode for v in vs]
    if not flat:
        return {name: None, f"{name}_low": None, f"{name}_high": None}
    sums = np.array([sum(vs) for vs in per_episode])
    counts = np.array([len(vs) for vs in per_episode])
    picks = rng.integers(0, len(per_episode), size=(resamples, len(per_episode)))
    with np.errstate(invalid="ignore"):
        means = sums[picks].sum(axis=1) / counts[picks].sum(axis=1)
    means = means[np.isfinite(means)]
    return {name: float(np.mean(flat)), f"{name}_low": float(np.percentile(means, 2.5)),
            f"{name}_high": float(np.percentile(means, 97.5))}


def _mean_ci(name: str, values: np.ndarray, rng: np.random.Generator) -> dict[str, float | None]:
    if not len(values):
        return {name: None, f"{name}_low": None, f"{name}_high": None}
    low, high = _bootstrap_ci(values, rng)
    return {name: float(values.mean()), f"{name}_low": low, f"{name}_high": high}


def _cell(t: dict[str, Any], name: str, scale: float = 1.0, fmt: str = ".1f") -> str:
    if t[name] is None:
        return "-"
    return f"{scale * t[name]:{fmt}} [{scale * t[f'{name}_low']:{fmt}}, {scale * t[f'{name}_high']:{fmt}}]"


def _plots(table: list[dict], out_dir: Path, param: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    numeric = param not in PROFILE_AXES
    if numeric:  # a line drawn through the points in the order given would run back and forth
        table = sorted(table, key=lambda t: float(t["value"]))
    labels = [str(t["value"]) for t in table]
    xs = {t["value"]: (float(t["value"]) if numeric else float(i)) for i, t in enumerate(table)}
    x = np.array(list(xs.values()))
    # Values over decades (a rate of 0.001 to 0.1) would crowd at the left of a linear axis: log, or
    # symmetric log, linear from 0 to the smallest positive value, when 0 is one of them.
    positive = x[x > 0]
    log_x = numeric and len(positive) > 1 and x.min() >= 0 and positive.max() / positive.min() >= 50
    panels = [*METRICS, "handoff_never_pct"]
    fig, axes = plt.subplots(2, 4, figsize=(14, 6), dpi=140)
    for ax, name in zip(axes.flat, panels, strict=True):
        rows = [t for t in table if t[name] is not None]
        if name == "handoff_never_pct":
            ax.plot([xs[t["value"]] for t in rows], [t[name] for t in rows], marker="o")
            ax.set_ylabel("first candidate never heard (%)")
            ax.set_title("UGV never heard of the first candidate", fontsize=9)
            ax.set_ylim(0, 105)
        else:
            scale = 100.0 if name in ("SR", "SPL", "ACG") else 1.0
            y = [scale * t[name] for t in rows]
            lo = [scale * (t[name] - t[f"{name}_low"]) for t in rows]
            hi = [scale * (t[f"{name}_high"] - t[name]) for t in rows]
            ax.errorbar([xs[t["value"]] for t in rows], y, yerr=[lo, hi], marker="o", capsize=3)
            ax.set_ylabel(LABELS[name])
            ax.set_title(f"{LABELS[name]}{' of those heard' if name == 'handoff' else ''} (95% CI)", fontsize=9)
            if name in ("SR", "SPL", "ACG"):
                ax.set_ylim(0, 105)
            else:
                ax.set_ylim(bottom=0)
        if not rows:  # e.g. CErr of a policy that sends no structured candidates: say so, not a blank
            ax.text(0.5, 0.5, "no value at any point", transform=ax.transAxes, ha="center", va="center",
                    color="0.4", fontsize=9)
        ax.set_xlabel(param)
        ax.grid(alpha=0.3)
        if log_x and x.min() > 0:
            ax.set_xscale("log")
        elif log_x:
            ax.set_xscale("symlog", linthresh=float(positive.min()))
            ax.set_xlim(-0.5 * positive.min(), 1.6 * positive.max())
            ax.set_xticks(x, labels, fontsize=8)
        if not numeric:
            ax.set_xticks(x, labels, fontsize=8)
    fig.tight_layout()
    fig.savefig(out_dir / "sweep.png")
    plt.close(fig)
