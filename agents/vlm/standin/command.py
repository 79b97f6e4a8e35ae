"""``agos vlm-standin``: the command's parser and its run (serve until SIGINT or SIGTERM).

``python -m agos.agents.vlm.standin.command [options]`` is the same as ``agos vlm-standin [options]``.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import signal
import sys
import threading
from collections.abc import Mapping
from typing import Any

from agos.agents.vlm.standin.faults import FAULT_KINDS, FaultSpecError, parse_faults
from agos.agents.vlm.standin.server import DEFAULT_MODELS, StandinServer, responder_name


def faults_arg(text: str) -> dict[str, float]:
    """argparse type for ``--faults``."""
    try:
        return parse_faults(text)
    except FaultSpecError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Add the ``vlm-standin`` subcommand to an ``add_subparsers()`` object."""
    p = sub.add_parser("vlm-standin", help="OpenAI-compatible stand-in VLM server on loopback (latency, injected faults)",
                       description="Serve /v1/models and /v1/chat/completions answered by the OpenCV stand-in brain.")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1; no authentication unless --api-key-env)")
    p.add_argument("--port", type=int, default=8000, help="port (default 8000; 0 picks a free one and prints it)")
    p.add_argument("--model", action="append", help=f"model name to serve (repeatable; default {DEFAULT_MODELS[0]})")
    p.add_argument("--latency-ms", type=float, default=0.0, help="fixed reply latency")
    p.add_argument("--jitter-ms", type=float, default=0.0, help="extra latency, uniform in [0, jitter] (seeded)")
    p.add_argument("--faults", type=faults_arg, default={},
                   help=f"KIND=P,... with KIND in {', '.join(FAULT_KINDS)}, e.g. 429=0.1,500=0.05,timeout=0.02,fenced=0.2")
    p.add_argument("--retry-after-s", type=float, default=1.0, help="Retry-After of injected 429s (default 1)")
    p.add_argument("--hang-s", type=float, default=90.0, help="how long an injected timeout hangs (default 90)")
    p.add_argument("--max-images", type=int, help="refuse requests with more images, as vLLM's --limit-mm-per-prompt does")
    p.add_argument("--wrap-p", type=float, default=0.3,
                   help="without response_format: probability that the JSON comes in fences or after a sentence (default 0.3)")
    p.add_argument("--seed", type=int, default=0, help="seed of latency, fault and wrapping draws")
    p.add_argument("--api-key-env", metavar="NAME",
                   help="ask every /v1 request for the key in this environment variable (Authorization: Bearer KEY), "
                        "answering 401 without it, as a hosted API does")
    p.add_argument("--verbose", "-v", action="store_true", help="one line per chat completion on stderr")
    return p


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="agos")
    add_parser(parser.add_subparsers(dest="command", required=True))
    return parser


def _announce(server: StandinServer, faults: Mapping[str, float], key_env: str | None) -> None:
    model = server.models[0]
    fault_text = ",".join(f"{k}={v:g}" for k, v in faults.items()) or "none"
    print(f"agos vlm-standin: listening on {server.url}", flush=True)
    print(f"  models: {', '.join(server.models)}; responder: {responder_name(server.responder)}", flush=True)
    print(f"  latency {server.latency_s * 1000:g} ms + up to {server.jitter_s * 1000:g} ms; faults {fault_text}; "
          f"max images {server.max_images if server.max_images is not None else 'unlimited'}; seed {server.seed}", flush=True)
    key = f" --vlm-api-key-env {key_env}" if key_env else ""
    print(f"  point agos at it: --vlm-base-url {server.url} --model {model}{key}", flush=True)
    if key_env:
        print(f"  API key required: the value of {key_env} (Authorization: Bearer KEY)", flush=True)
    try:
        loopback = server.host == "localhost" or ipaddress.ip_address(server.host).is_loopback
    except ValueError:
        loopback = False
    if not loopback and not key_env:
        print(f"  warning: listening on {server.host}, not loopback; anyone who can reach it can use it", flush=True)


def run(args: argparse.Namespace) -> int:
    """Serve until SIGINT or SIGTERM; 0 on a clean stop, 2 when it cannot listen or a setting is wrong."""
    api_key = None
    if args.api_key_env:
        api_key = os.environ.get(args.api_key_env)
        if not api_key:
            print(f"vlm-standin error: --api-key-env {args.api_key_env}: {args.api_key_env} is not set (or empty); "
                  f"export it with the key clients must send, or leave --api-key-env out", file=sys.stderr)
            return 2
    try:
        server = StandinServer(models=args.model or DEFAULT_MODELS, latency_ms=args.latency_ms, jitter_ms=args.jitter_ms,
                               faults=args.faults, retry_after_s=args.retry_after_s, hang_s=args.hang_s,
                               max_images=args.max_images, seed=args.seed, wrap_p=args.wrap_p, host=args.host, port=args.port,
                               log=(lambda line: print(line, file=sys.stderr, flush=True)) if args.verbose else None,
                               api_key=api_key)
    except OSError as exc:
        print(f"vlm-standin error: cannot listen on {args.host}:{args.port}: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"vlm-standin error: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set()) if in_main else None
    try:
        with server:
            _announce(server, server.faults, args.api_key_env)
            while not stop.wait(0.5):
                pass
    except KeyboardInterrupt:
        pass
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous)
    stats = server.stats()
    print(f"agos vlm-standin: stopped after {stats['chat_completions']} chat completions ({stats['faults']} injected faults)",
          flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m agos.agents.vlm.standin.command [options]``: the same as ``agos vlm-standin``."""
    return run(build_parser().parse_args(["vlm-standin", *(sys.argv[1:] if argv is None else argv)]))


if __name__ == "__main__":
    sys.exit(main())
