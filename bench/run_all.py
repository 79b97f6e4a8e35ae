"""``make bench``: the quick form of every ratio benchmark, then one table of figures against goals.

Each bench runs as its own process with ``--quick --json`` (bench/figures.py: one ``BENCH-FIGURE``
line per figure), one after another, so they do not share the cores; its whole output goes to
``<logs>/<bench>.log``. The table lists each figure, what it measured, its goal and whether it was
met. Every figure is a ratio against a baseline measured in the same run (the recorder's is a
guard on an absolute cost), but a shared machine moves them: a missed goal is a reason to rerun
that bench alone (its log names the command) and read its own output, never a failure here. The
exit status is non-zero when a bench crashed, timed out or printed no figure, and when a *gating*
bench missed a goal: ``bench_cues.py --check`` (the look-alike table against a fresh measurement
at a fixed seed; not a timing, so a shared machine does not move it).

    .venv/bin/python bench/run_all.py [--only roundtrip --only metrics] [--logs DIR]

Not here: ``bench_cues.py``'s full run (a separability floor, not a ratio, 12 min a repeat) and
``oracle_sweep.py`` (correctness, not timing).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from figures import parse
from rich import box
from rich.console import Console
from rich.table import Table

HERE = Path(__file__).resolve().parent


@dataclass
class Bench:
    name: str
    script: str
    args: list[str]
    timeout_s: int
    figures: list[dict[str, Any]] = field(default_factory=list)
    gate: bool = False
    """A missed goal fails ``make bench`` (a deterministic check, not a timing)."""
    status: str = "not run"
    wall_s: float = 0.0


def benches() -> list[Bench]:
    return [
        Bench("roundtrip", "bench_runtime.py", ["--quick"], 180),  # the round trip and agent concurrency
        Bench("world", "bench_world.py", ["--quick"], 240),
        Bench("look", "bench_look.py", ["--quick"], 300),
        Bench("metrics", "bench_metrics.py", ["--quick"], 180),
        Bench("record", "bench_record.py", ["--quick"], 240),
        Bench("expert", "bench_expert.py", ["--quick"], 300),
        Bench("eval", "bench_eval.py", ["--quick"], 420),
        Bench("dataset", "bench_dataset.py", ["--quick", "--workers", "1", "--no-breakdown"], 600),
        Bench("env", "bench_env.py", ["--quick"], 420),  # agos.Env vs the engine; 2 subprocess envs vs 1
        Bench("control-plane", "bench_control_plane.py", ["--quick"], 180),  # orchestrator, evaluator, router vs N workers
        Bench("control-plane-soak", "bench_control_plane.py", ["--soak", "--quick"], 300),  # 2,000 episodes: cost flat?
        Bench("cues", "bench_cues.py", ["--check"], 600, gate=True),  # the look-alike table still true
    ]


def run(bench: Bench, logs: Path, console: Console) -> None:
    cmd = [sys.executable, str(HERE / bench.script), *bench.args, "--json"]
    log = logs / f"{bench.name}.log"
    console.print(f"[bold]{bench.name}[/]: {' '.join(cmd[1:])}", highlight=False, soft_wrap=True)
    started = time.monotonic()
    try:
        out = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=bench.timeout_s,
                             cwd=HERE.parent, env={**os.environ, "COLUMNS": "160"})
        output, code = out.stdout, out.returncode
    except subprocess.TimeoutExpired as exc:
        output = exc.stdout.decode(errors="replace") if isinstance(exc.stdout, bytes) else exc.stdout or ""
        code = None
    bench.wall_s = time.monotonic() - started
    log.write_text(f"$ {' '.join(cmd)}\n{output}")
    bench.figures = parse(output)
    if code is None:
        bench.status = f"timed out after {bench.timeout_s} s"
    elif not bench.figures:
        bench.status = f"crashed (exit {code}, no figure)" if code else "no figure printed"
    elif code not in (0, 1):  # bench_expert and bench_cues exit 1 when a goal is missed: a figure, not a crash
        bench.status = f"crashed (exit {code})"
    else:
        bench.status = "ran"
    style = "green" if bench.status == "ran" else "red"
    console.print(f"  [{style}]{bench.status}[/] in {bench.wall_s:.0f} s, {len(bench.figures)} figures; log {log}",
                  highlight=False)


def table(done: list[Bench], wall_s: float) -> Table:
    t = Table(title=f"make bench: quick figures against their goals ({wall_s:.0f} s, {os.cpu_count()} cores)",
              box=box.MARKDOWN, title_justify="left", title_style="")
    for col in ("bench", "figure", "measured", "goal", "result"):
        t.add_column(col, justify="left" if col in ("bench", "figure") else "right")
    for bench in done:
        for f in bench.figures:
            met = f.get("met")
            result = "info" if met is None else ("pass" if met else "[red]FAIL" + (" (gate)" if bench.gate else ""))
            t.add_row(bench.name, f["figure"], f["shown"], f.get("goal", ""), result)
        if bench.status != "ran":
            t.add_row(bench.name, f"[red]{bench.status}", "", "", "[red]ERROR")
    return t


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    names = [b.name for b in benches()]
    ap.add_argument("--only", action="append", choices=names, help="run only these benches (repeatable)")
    ap.add_argument("--logs", type=Path, help="where each bench's output goes (default: a new temporary directory)")
    args = ap.parse_args(argv)
    console = Console(width=160)
    logs = args.logs or Path(tempfile.mkdtemp(prefix="agos-bench-"))
    logs.mkdir(parents=True, exist_ok=True)
    todo = [b for b in benches() if not args.only or b.name in args.only]
    started = time.monotonic()
    done: list[Bench] = []
    try:
        for bench in todo:
            run(bench, logs, console)
            done.append(bench)
    except KeyboardInterrupt:
        console.print("[yellow]interrupted: the figures so far")
    console.print()
    with console.capture() as captured:  # a markdown table without rich's padding: pasteable as it is
        console.print(table(done, time.monotonic() - started))
    print("\n".join(line.rstrip() for line in captured.get().splitlines() if line.strip()))
    missed = sum(1 for b in done for f in b.figures if f.get("met") is False)
    broken = [b.name for b in done if b.status != "ran"]
    gated = [b.name for b in done if b.gate and any(f.get("met") is False for f in b.figures)]
    console.print(f"{sum(len(b.figures) for b in done)} figures, {missed} goals missed (a missed timing goal does not "
                  f"fail make bench: rerun that bench alone and read its own output); logs in {logs}", highlight=False)
    if broken:
        console.print(f"[red]benches that did not run to a figure: {', '.join(broken)}")
    if gated:
        console.print(f"[red]gating checks that failed: {', '.join(gated)} (their logs name what to do)")
    if broken or gated:
        return 1
    return 130 if len(done) < len(todo) else 0


if __name__ == "__main__":
    sys.exit(main())
