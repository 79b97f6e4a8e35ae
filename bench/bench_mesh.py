"""The observation path through routers: MB/s of observation-sized samples (244 KB) through one
router and through a mesh of three, against raw zenoh peer to peer, in the same run.

Each transfer is a publisher process and a subscriber process using agos's own bus with the QoS of
control traffic (``ZenohBus.publish``: reliable, congestion control BLOCK, as observations go) on
one key, over loopback TCP. Paths:

  raw zenoh (peer to peer)  both sessions in peer mode, the subscriber listening: no router
  one router                both clients of one ``agos router``
  3-router mesh             ``agos router`` A, B (``--peer A``) and C (``--peer A``); the publisher a
                            client of B, the subscriber of C: every sample crosses B, A and C

Per transfer: the publisher waits for the subscriber to match, then puts ``--messages`` samples as
fast as BLOCK lets it; MB/s is the payload bytes over the time from its first put to the
subscriber's last sample (one clock: CLOCK_MONOTONIC is machine-wide). Also the samples lost (BLOCK:
none expected), the routers' CPU seconds per GB carried (``/proc``, each router's own) and the CPU
per GB of every process of the path (publisher and subscriber from their first sample to their end,
routers): on a machine with fewer cores than the path has processes, MB/s measures the cores
shared, and the CPU per GB what a path costs wherever it runs. Rounds
interleave the paths, because a shared machine's load drifts; the table shows each path's median
over the rounds and its range, and the median of the per-round ratios to raw zenoh.

    .venv/bin/python bench/bench_mesh.py                      # 1,000 samples a transfer, 3 rounds
    .venv/bin/python bench/bench_mesh.py --messages 300 --rounds 1 --json

The goal (issue 33) is context, not a pass mark: 50 hosts x 16 decisions/s x 244 KB is about
195 MB/s through one router. :func:`measure` returns the rows for another bench to print
(bench_control_plane.py).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from figures import Figures

from agos.deploy.run.launcher import wait_listening
from agos.runtime.bus import ZenohBus, zenoh_config

AGOS = [sys.executable, "-m", "agos.deploy.cli"]
KEY = "agos/bench/slot/w0/obs/uav"  # the shape of a world slot's observation key (runtime/keys.py)
OBSERVATION_BYTES = 244_000
"""An observation as the issue sizes it (two encoded views and the references of one decision)."""
PATHS = ("raw zenoh (peer to peer)", "one router", "3-router mesh")
START_TIMEOUT_S = 60.0
"""How long a child process may take to start and match (imports on a loaded machine)."""


def _free_ports(n: int) -> list[int]:
    """``n`` distinct free loopback ports (each held while the next is chosen)."""
    socks = [socket.socket() for _ in range(n)]
    for sock in socks:
        sock.bind(("127.0.0.1", 0))
    ports = [sock.getsockname()[1] for sock in socks]
    for sock in socks:
        sock.close()
    return ports


def cpu_s(pid: int) -> float:
    """CPU seconds (user + system) a live process has used (``/proc/<pid>/stat``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


# --- the two ends, each run as a process of its own: `bench_mesh.py --child sub|pub MODE ENDPOINT ...` ---

def _bus(mode: str, endpoint: str, *, listening: bool) -> ZenohBus:
    if mode == "peer":
        return ZenohBus(zenoh_config(mode="peer", listen=[endpoint] if listening else None,
                                     connect=None if listening else [endpoint]))
    return ZenohBus(zenoh_config(connect=[endpoint]))


def _subscriber(mode: str, endpoint: str, messages: int, timeout_s: float) -> int:
    """Count the samples on :data:`KEY`; print READY once subscribed, then one JSON line."""
    received, nbytes, last, cpu_first = [0], [0], [0.0], [0.0]
    done = threading.Event()

    def on_payload(payload: bytes) -> None:  # zenoh's thread: counting only
        if not received[0]:
            cpu_first[0] = time.process_time()
        received[0] += 1
        nbytes[0] += len(payload)
        last[0] = time.monotonic()
        if received[0] >= messages:
            done.set()

    with _bus(mode, endpoint, listening=True) as bus:
        bus.subscribe_payloads(KEY, on_payload)
        print("READY", flush=True)
        done.wait(timeout_s)
        cpu_s = time.process_time() - cpu_first[0] if received[0] else 0.0
        print(json.dumps({"received": received[0], "bytes": nbytes[0], "last": last[0], "cpu_s": cpu_s}), flush=True)
    return 0


def _publisher(mode: str, endpoint: str, messages: int, size: int) -> int:
    """Put ``messages`` samples of ``size`` bytes once the subscriber matches; print one JSON line,
    keep the session open until stdin closes (closing it at once could drop what is queued), then
    print the CPU seconds spent since the first put."""
    payload = os.urandom(size)
    with _bus(mode, endpoint, listening=False) as bus:
        if not bus.wait_for_subscriber(KEY, START_TIMEOUT_S):
            print(json.dumps({"error": "no subscriber matched"}), flush=True)
            return 1
        start, cpu_start = time.monotonic(), time.process_time()
        for _ in range(messages):
            bus.publish(KEY, payload)
        print(json.dumps({"start": start, "end": time.monotonic()}), flush=True)
        sys.stdin.read()
        print(json.dumps({"cpu_s": time.process_time() - cpu_start}), flush=True)
    return 0


# --- the parent: routers, transfers, the table ---

@dataclass
class Route:
    """One path's routers and the endpoints its two ends use."""

    name: str
    mode: str  # "peer" (no router) or "client"
    pub_endpoint: str
    sub_endpoint: str
    routers: list[subprocess.Popen] = field(default_factory=list)


@dataclass
class Transfer:
    path: str
    mb_s: float
    lost: int
    router_cpu_s_per_gb: float | None
    cpu_s_per_gb: float
    """Publisher, subscriber and routers together."""


def _start_routers(tmp: Path) -> tuple[list[Route], list[subprocess.Popen]]:
    ports = _free_ports(5)
    raw, one, a, b, c = (f"tcp/127.0.0.1:{p}" for p in ports)
    logs = tmp / "logs"
    logs.mkdir(exist_ok=True)

    def router(name: str, listen: str, *peers: str) -> subprocess.Popen:
        args = [*AGOS, "router", "--listen", listen, *[w for p in peers for w in ("--peer", p)]]
        with (logs / f"{name}.log").open("wb") as log:
            return subprocess.Popen(args, cwd=tmp, stdout=log, stderr=subprocess.STDOUT)

    one_router = router("one", one)
    mesh = [router("mesh-a", a), router("mesh-b", b, a), router("mesh-c", c, a)]
    for port in ports[1:]:
        if not wait_listening("127.0.0.1", port, START_TIMEOUT_S):
            raise RuntimeError(f"a router did not listen on {port} within {START_TIMEOUT_S:.0f} s (logs in {logs})")
    paths = [Route(PATHS[0], "peer", raw, raw), Route(PATHS[1], "client", one, one, [one_router]),
             Route(PATHS[2], "client", b, c, mesh)]
    return paths, [one_router, *mesh]


def _line(stream: IO[str], what: str) -> str:
    line = stream.readline()
    if not line:
        raise RuntimeError(f"the {what} exited without a word")
    return line


def transfer(path: Route, messages: int, size: int, tmp: Path) -> Transfer:
    """One transfer over ``path``; its MB/s, samples lost and the routers' CPU per GB."""
    me = [sys.executable, str(Path(__file__).resolve()), "--child"]
    timeout_s = START_TIMEOUT_S + messages * size / 5e6  # no slower than 5 MB/s, or it is stuck
    sub = subprocess.Popen([*me, "sub", path.mode, path.sub_endpoint, str(messages), str(timeout_s)], cwd=tmp,
                           stdout=subprocess.PIPE, text=True)
    pub = None
    try:
        if _line(sub.stdout, "subscriber").strip() != "READY":  # type: ignore[arg-type]
            raise RuntimeError("the subscriber did not start")
        cpu_before = sum(cpu_s(r.pid) for r in path.routers)
        pub = subprocess.Popen([*me, "pub", path.mode, path.pub_endpoint, str(messages), str(size)], cwd=tmp,
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        sent = json.loads(_line(pub.stdout, "publisher"))  # type: ignore[arg-type]
        if "error" in sent:
            raise RuntimeError(f"{path.name}: {sent['error']}")
        got = json.loads(_line(sub.stdout, "subscriber"))  # type: ignore[arg-type]
        cpu_after = sum(cpu_s(r.pid) for r in path.routers)
        pub.stdin.close()  # type: ignore[union-attr]
        pub_cpu_s = json.loads(_line(pub.stdout, "publisher"))["cpu_s"]  # type: ignore[arg-type]
    finally:
        for proc in (pub, sub):
            if proc is not None:
                if proc.stdin and not proc.stdin.closed:
                    proc.stdin.close()
                try:
                    proc.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
    seconds = max(got["last"] - sent["start"], 1e-9)
    gb = max(got["bytes"] / 1e9, 1e-9)
    routers_cpu_s = cpu_after - cpu_before
    return Transfer(path.name, got["bytes"] / 1e6 / seconds, messages - got["received"],
                    routers_cpu_s / gb if path.routers else None, (routers_cpu_s + pub_cpu_s + got["cpu_s"]) / gb)


@dataclass
class Row:
    path: str
    mb_s: float
    mb_s_range: tuple[float, float]
    ratio_to_raw: float
    lost: int
    router_cpu_s_per_gb: float | None
    cpu_s_per_gb: float


def measure(messages: int = 1000, rounds: int = 3, size: int = OBSERVATION_BYTES) -> list[Row]:
    """Every path, ``rounds`` times interleaved; one row per path (raw zenoh first)."""
    with tempfile.TemporaryDirectory(prefix="agos-bench-mesh-") as tmp_name:
        tmp = Path(tmp_name)
        paths, routers = _start_routers(tmp)
        try:
            runs = [[transfer(path, messages, size, tmp) for path in paths] for _ in range(rounds)]
        finally:
            for router in routers:
                router.terminate()
            for router in routers:
                try:
                    router.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    router.kill()
    rows = []
    for k, name in enumerate(PATHS):
        mine = [run[k] for run in runs]
        cpu = [t.router_cpu_s_per_gb for t in mine if t.router_cpu_s_per_gb is not None]
        rows.append(Row(name, statistics.median(t.mb_s for t in mine), (min(t.mb_s for t in mine), max(t.mb_s for t in mine)),
                        statistics.median(run[k].mb_s / run[0].mb_s for run in runs), sum(t.lost for t in mine),
                        statistics.median(cpu) if cpu else None, statistics.median(t.cpu_s_per_gb for t in mine)))
    return rows


def print_table(rows: list[Row], messages: int, rounds: int, size: int, load: tuple[float, float]) -> None:
    print(f"observation path: {messages} samples of {size / 1000:.0f} KB a transfer, {rounds} round(s), "
          f"reliable + BLOCK, loopback TCP, {os.cpu_count()} CPUs, load {load[0]:.1f} before, {load[1]:.1f} after")
    print(f"| {'path':<26} | {'MB/s (median)':>13} | {'range':>13} | {'vs raw':>6} | {'lost':>4} | "
          f"{'router CPU s/GB':>15} | {'all CPU s/GB':>12} |")
    print(f"|{'-' * 28}|{'-' * 14}:|{'-' * 14}:|{'-' * 7}:|{'-' * 5}:|{'-' * 16}:|{'-' * 13}:|")
    for r in rows:
        cpu = f"{r.router_cpu_s_per_gb:.1f}" if r.router_cpu_s_per_gb is not None else "-"
        print(f"| {r.path:<26} | {r.mb_s:>13.0f} | {r.mb_s_range[0]:>5.0f} - {r.mb_s_range[1]:<5.0f} | "
              f"{r.ratio_to_raw:>5.2f}x | {r.lost:>4} | {cpu:>15} | {r.cpu_s_per_gb:>12.1f} |")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--messages", type=int, default=1000, help="samples a transfer (default 1000)")
    parser.add_argument("--rounds", type=int, default=3, help="rounds, each path once a round (default 3)")
    parser.add_argument("--payload-kb", type=float, default=OBSERVATION_BYTES / 1000,
                        help="sample size in KB (default 244: an observation)")
    parser.add_argument("--json", action="store_true", help="also one BENCH-FIGURE line per path (bench/figures.py)")
    parser.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        role, mode, endpoint, messages, last = args.child
        if role == "sub":
            return _subscriber(mode, endpoint, int(messages), float(last))
        return _publisher(mode, endpoint, int(messages), int(last))
    if args.messages < 1 or args.rounds < 1 or args.payload_kb <= 0:
        print("bench_mesh: --messages and --rounds must be >= 1 and --payload-kb > 0", file=sys.stderr)
        return 2
    size = int(args.payload_kb * 1000)
    load_before = os.getloadavg()[0]
    rows = measure(args.messages, args.rounds, size)
    print_table(rows, args.messages, args.rounds, size, (load_before, os.getloadavg()[0]))
    figures = Figures(args.json)
    for r in rows:
        figures.add(f"observation path MB/s: {r.path}", r.mb_s,
                    f"{r.mb_s:.0f} MB/s ({r.ratio_to_raw:.2f}x raw zenoh, {r.lost} lost)")
    return 0 if all(r.lost == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
