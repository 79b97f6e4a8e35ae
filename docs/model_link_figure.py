"""Draw docs/COMMS.md's model-placement figure from two finished sweeps: SR (95 % bootstrap interval
over episodes) and the mean model-link time per decision against the placement, with images as
rendered (``a-link``: onboard, edge, lte, satellite) and small (``a-link-small``: lte, satellite).

    .venv/bin/python docs/model_link_figure.py a-link a-link-small --out docs/images/model_link_image_size.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

PLACEMENTS = ("onboard", "edge", "lte", "satellite")


def _records(sweep_dir: Path, placement: str) -> list[dict]:
    lines = (sweep_dir / "points" / f"model_link={placement}_seed0.jsonl").read_text().splitlines()
    return [json.loads(line) for line in lines]


def _mean_ci(values: list[float], rng: np.random.Generator) -> tuple[float, float, float]:
    x = np.asarray(values, float)
    means = x[rng.integers(0, len(x), (2000, len(x)))].mean(axis=1)
    low, high = np.percentile(means, [2.5, 97.5])
    return float(x.mean()), float(low), float(high)


def _link_s_per_decision(records: list[dict]) -> float:
    links = [r["model_link"] for r in records if r.get("model_link")]
    decisions = sum(m["decisions"] for m in links)
    return sum(m["link_time_s"] for m in links) / decisions if decisions else 0.0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("full", type=Path, help="the sweep over every placement, images as rendered")
    parser.add_argument("small", type=Path, help="the sweep with small images (the placements it has)")
    parser.add_argument("--out", type=Path, default=Path("docs/images/model_link_image_size.png"))
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    fig, (sr_ax, time_ax) = plt.subplots(1, 2, figsize=(10, 3.8), dpi=140)
    for sweep_dir, label, marker in ((args.full, "images as rendered", "o"), (args.small, "256 px, JPEG 60", "s")):
        placements = [p for p in PLACEMENTS if (sweep_dir / "points" / f"model_link={p}_seed0.jsonl").exists()]
        x = [PLACEMENTS.index(p) for p in placements]
        sr = [_mean_ci([100.0 * r["success"] for r in _records(sweep_dir, p)], rng) for p in placements]
        sr_ax.errorbar(x, [m for m, _, _ in sr], yerr=[[m - lo for m, lo, _ in sr], [hi - m for m, _, hi in sr]],
                       marker=marker, capsize=3, label=label)
        time_ax.plot(x, [_link_s_per_decision(_records(sweep_dir, p)) for p in placements], marker=marker, label=label)
    for ax, title in ((sr_ax, "SR (%) (95% CI)"), (time_ax, "model link time per decision (s, mean)")):
        ax.set_xticks(range(len(PLACEMENTS)), PLACEMENTS)
        ax.set_xlabel("model_link")
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    sr_ax.set_ylim(0, 100)
    time_ax.set_ylim(bottom=0)
    fig.suptitle("AGOS-Agent over the stand-in: where the model runs, and the size of what it is sent", fontsize=10)
    fig.tight_layout()
    fig.savefig(args.out)
    print(f"figure: {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
