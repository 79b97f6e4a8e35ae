"""The embedded zenoh router: ``agos router --listen tcp/127.0.0.1:7447``.

A Python zenoh session in router mode routes pub/sub, queries and liveliness between the
clients (it cannot load zenohd plugins; use the eclipse/zenoh image for storage or REST).
"""

from __future__ import annotations

import logging

import zenoh

from agos.runtime.bus import zenoh_config
from agos.runtime.process import install_stop_handlers, setup_logging

log = logging.getLogger("agos.router")


def main(listen: str, *, multicast_scouting: bool = False) -> int:
    setup_logging("router")
    stop = install_stop_handlers()
    session = zenoh.open(zenoh_config(mode="router", listen=[listen], multicast_scouting=multicast_scouting))
    log.info("zenoh router %s listening on %s", session.zid(), listen)
    try:
        while not stop.wait(0.5):
            pass
    finally:
        session.close()
    return 0
