"""The embedded zenoh router: ``agos router --listen tcp/127.0.0.1:7447 [--peer EP ...]``.

A Python zenoh session in router mode routes pub/sub, queries and liveliness between the
clients (it cannot load zenohd plugins; use the eclipse/zenoh image for storage or REST). It
declares ``agos/routers/<zid>`` in its own session, which is what ``agos health router`` asks for.

With peers (``--peer``, ``[zenoh] peers``) it also connects to other routers, making a mesh: one
router per site or rack, its processes connected to it first (``--connect NEAR,FAR``), the routers
routing between them; it keeps trying a peer that is not up yet or went away (docs/DEPLOY.md,
"Router mesh").

On ``tls/`` endpoints it is the secured bus: mutual TLS with its own certificate (runtime/tls.py),
on the links to its peers too, and default-deny access control generated from the key space
(runtime/access_control.py), which lets another router's certificate relay what that router's own
clients were allowed to say.
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


def router_config(z: ZenohSettings) -> zenoh.Config:
    """The router's zenoh config: listening on ``z.listen``, connecting to ``z.peers``; on ``tls/``,
    mutual TLS and the access control of runtime/access_control.py."""
    secure = z.listen.startswith("tls/")
    return session_config(z, mode="router", access_control=access_control() if secure else None)


def main(z: ZenohSettings) -> int:
    config = router_config(z)
    setup_logging("router")
    stop = install_stop_handlers()
    session = zenoh.open(config)
    zid = str(session.zid())
    token = session.liveliness().declare_token(keys.router_live(zid))
    announce("router", zid)
    peers = f", peering with {', '.join(z.peers)}" if z.peers else ""
    if z.listen.startswith("tls/"):
        log.info("zenoh router %s listening on %s%s: mutual TLS, access control (default deny) for %s",
                 zid, z.listen, peers, ", ".join(IDENTITIES))
    else:
        log.info("zenoh router %s listening on %s%s (plain TCP: any client may say anything)", zid, z.listen, peers)
    try:
        while not stop.wait(0.5):
            pass
    finally:
        token.undeclare()
        session.close()
    return 0
