"""The embedded zenoh router: ``agos router --listen tcp/127.0.0.1:7447``.

A Python zenoh session in router mode routes pub/sub, queries and liveliness between the
clients (it cannot load zenohd plugins; use the eclipse/zenoh image for storage or REST). It
declares ``agos/routers/<zid>`` in its own session, which is what ``agos health router`` asks for.

On ``tls/`` endpoints it is the secured bus: mutual TLS with its own certificate (runtime/tls.py)
and default-deny access control generated from the key space (runtime/access_control.py).
"""

from __future__ import annotations

import logging

import zenoh

from agos.runtime import keys
from agos.runtime.access_control import IDENTITIES, access_control
from agos.runtime.bus import session_config
from agos.runtime.health import announce
from agos.runtime.process import install_stop_handlers, setup_logging
from agos.runtime.settings import ZenohSettings

log = logging.getLogger("agos.router")


def main(z: ZenohSettings) -> int:
    secure = z.listen.startswith("tls/")
    config = session_config(z, mode="router", access_control=access_control() if secure else None)
    setup_logging("router")
    stop = install_stop_handlers()
    session = zenoh.open(config)
    zid = str(session.zid())
    token = session.liveliness().declare_token(keys.router_live(zid))
    announce("router", zid)
    if secure:
        log.info("zenoh router %s listening on %s: mutual TLS, access control (default deny) for %s",
                 zid, z.listen, ", ".join(IDENTITIES))
    else:
        log.info("zenoh router %s listening on %s (plain TCP: any client may say anything)", zid, z.listen)
    try:
        while not stop.wait(0.5):
            pass
    finally:
        token.undeclare()
        session.close()
    return 0
