"""``python tests/support/mesh_client.py NAME ENDPOINTS``: a client process of a router mesh
(tests/test_e2e_faults.py), until SIGTERM. Its bus is made as every agos process makes its own
(``ZenohBus.from_settings`` of ``[zenoh] connect = ENDPOINTS``, its own router first); it holds the token
``failback/NAME/live`` and answers each ping on ``failback/NAME/ping`` with a pong on
``failback/NAME/pong``: the ping's payload, a space, and the id of the router it is on now
(``session.info.routers_zid()``)."""

from __future__ import annotations

import sys

from agos.runtime.bus import Inbox, ZenohBus
from agos.runtime.process import install_stop_handlers, setup_logging
from agos.runtime.settings import ZenohSettings


def main(name: str, endpoints: str) -> int:
    setup_logging("mesh-client")
    stop = install_stop_handlers()
    with ZenohBus.from_settings(ZenohSettings(connect=endpoints)) as bus:
        pings = Inbox()
        bus.subscribe(f"failback/{name}/ping", pings)
        bus.declare_token(f"failback/{name}/live")
        while not stop.is_set():
            ping = pings.get(0.1)
            if ping is not None:
                routers = bus.session.info.routers_zid()
                bus.publish(f"failback/{name}/pong", ping.payload + b" " + (str(routers[0]).encode() if routers else b"-"))
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
