"""The bus operators' commands' parsers (deploy/ops/).

    agos health KIND                is that process's liveliness token on the bus? (healthchecks)
    agos certs --out DIR            a CA and one certificate per identity of a secured bus
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from agos.deploy.cli.common import Command, with_settings
from agos.runtime.health import HEALTH_KINDS
from agos.runtime.settings import AgosConfig


def _add_health(sub: Any) -> None:
    health = sub.add_parser("health", help="exit 0 if a process's liveliness token is on the bus (compose healthchecks)")
    health.add_argument("kind", choices=HEALTH_KINDS)
    health.add_argument("--id", dest="ident", help="the process id (default: what the process of that kind here announced)")
    health.add_argument("--config", type=Path)
    health.add_argument("--connect", help="zenoh router endpoint (default from settings)")
    health.add_argument("--run", dest="run_id", help="run id (default: the one the process announced, else settings)")
    health.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for the answer (default 3)")


def _health(args: argparse.Namespace, cfg: AgosConfig) -> int:
    from agos.deploy.ops.healthcheck import main as health_main

    return health_main(cfg, args.kind, ident=args.ident, run=args.run_id, timeout_s=args.timeout)


def _add_certs(sub: Any) -> None:
    certs = sub.add_parser("certs", help="make a CA and per-identity certificates for a secured bus (mutual TLS)")
    certs.add_argument("--out", type=Path, required=True, help="directory to write (created, mode 0700)")
    certs.add_argument("--router-host", action="append", dest="router_hosts", metavar="HOST",
                       help="a name or address clients reach the router by (repeat; default localhost, 127.0.0.1)")
    certs.add_argument("--days", type=int, default=365, help="validity (default 365)")
    certs.add_argument("--force", action="store_true", help="replace an existing CA and every certificate")


def _certs(args: argparse.Namespace) -> int:
    from agos.deploy.ops.certs import main as certs_main

    return certs_main(args.out, router_hosts=args.router_hosts, days=args.days, force=args.force)


HEALTH = Command(("health",), _add_health, with_settings(_health))
CERTS = Command(("certs",), _add_certs, _certs)
