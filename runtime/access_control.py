"""The router's access control, generated from the key space (runtime/keys.py): default deny.

On a secured bus (mutual TLS, runtime/tls.py) every process's certificate names its identity
(the common name). This module says, for each identity, which keys it may publish, hear, query,
serve, declare liveliness tokens on and watch; :func:`access_control` turns that into zenoh's
``access_control`` section, which the router enforces on every link. Anything not granted is
dropped by the router, silently for the sender (zenoh does not report it).

What each identity may say (the issue's rules):

- ``world`` (world workers, ``agos check agent``): observations, events, coordination states,
  messages, results and the visualisation stream; it hears actions, acknowledgements and the
  manifest; it asks for jobs and assets.
- ``agent-uav`` / ``agent-ugv``: only that role's action key of any slot; they hear that role's
  observations, watch the slots' tokens and declare their ``ready`` tokens for that role only.
- ``evaluator``: alone publishes acknowledgements; hears results, manifests and lease notices.
- ``orchestrator`` (``agos eval``, the compose ``eval`` job): the manifest, lease notices and
  infrastructure failure records; serves jobs and assets; hears results, acknowledgements and events.
- ``observer``: only reads the visualisation stream.
- ``router``: relays everything under ``agos/**``, both ways (a router mesh: docs/DEPLOY.md). zenoh
  applies these rules to the links between routers as to any other, by the certificate the other
  router presents, so without this grant nothing would cross a mesh (measured: not a put, query or
  token). Each router enforces its own clients' rules where their messages come in, so what another
  router relays was already checked there; the price is that ``router.key`` may say anything: it
  belongs on router hosts only.

Which slot a world may publish on is not a key rule (worker ids are made at start, not certified):
any ``world`` certificate may publish on any slot, and the evaluator stores a record only when it
names the worker of its key's slot and that worker holds the episode's lease, as the orchestrator's
lease notice names it (evaluator/evaluator_service.py). The key space is bounded (runtime/keys.py), so these
rules, generated from it, do not change with episodes either.

How zenoh's rules read: a message *into* the router from a client is ``ingress``; one the router
sends *out* to a client is ``egress``. Publishing is ``put`` ingress, and hearing it is ``put``
egress plus ``declare_subscriber`` ingress. A publisher also learns of matching subscribers
(``declare_subscriber`` egress), which agos uses to wait for a receiver. So a subscriber
declares keys inside each publisher's grant (a world worker: ``act/<slot>/uav`` and ``.../ugv``, not
``act/*/*``): the router tells no publisher of a wider subscription, and a zenoh 1.10 client that never
heard of a subscriber drops its own puts (seen: 1 run in 10, whenever the declaration reached the router
after the publisher's session opened).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from agos.runtime import keys

ANY = "*"


@dataclass(frozen=True)
class Grants:
    """Key expressions one identity may use, by kind of use."""

    publish: tuple[str, ...] = ()
    hear: tuple[str, ...] = ()
    query: tuple[str, ...] = ()
    serve: tuple[str, ...] = ()
    tokens: tuple[str, ...] = ()
    watch: tuple[str, ...] = ()
    relay: tuple[str, ...] = ()
    """Every message kind, both ways: another router of a mesh forwarding its clients' traffic."""


def _health() -> tuple[str, ...]:
    """Every identity may ask which processes (and routers) are alive: ``agos health``."""
    return (keys.live_all(ANY), keys.router_live(ANY))


def _agent(role: str) -> Grants:
    return Grants(
        publish=(keys.act(ANY, ANY, role),),
        hear=(keys.obs(ANY, ANY, role),),
        tokens=(keys.live(ANY, "agent", ANY), keys.slot_ready(ANY, ANY, role, ANY)),
        watch=(keys.slot_live(ANY, ANY), *_health()),
    )


IDENTITIES: dict[str, Grants] = {
    "router": Grants(watch=_health(), relay=(f"{keys.ROOT}/**",)),
    "world": Grants(
        publish=(keys.obs(ANY, ANY, ANY), keys.events(ANY, ANY), keys.coord_truth(ANY, ANY),
                 keys.coord_view(ANY, ANY, ANY), keys.message(ANY, ANY, ANY, ANY), keys.result(ANY, ANY),
                 keys.viz_all(ANY)),
        hear=(keys.act(ANY, ANY, ANY), keys.result_ack(ANY, ANY), keys.manifest(ANY)),
        query=(keys.jobs(ANY), keys.asset(ANY)),
        tokens=(keys.live(ANY, "world", ANY), keys.slot_live(ANY, ANY)),
        watch=(keys.slot_ready(ANY, ANY, ANY, ANY), *_health()),
    ),
    "agent-uav": _agent("uav"),
    "agent-ugv": _agent("ugv"),
    "evaluator": Grants(
        publish=(keys.result_ack(ANY, ANY),),
        hear=(keys.result(ANY, ANY), keys.manifest(ANY), keys.lease(ANY)),
        tokens=(keys.live(ANY, "evaluator", ANY),),
        watch=_health(),
    ),
    "orchestrator": Grants(
        publish=(keys.manifest(ANY), keys.result(ANY, ANY), keys.lease(ANY)),
        hear=(keys.result(ANY, ANY), keys.result_ack(ANY, ANY), keys.events(ANY, ANY)),
        serve=(keys.jobs(ANY), keys.asset(ANY)),
        tokens=(keys.live(ANY, "orchestrator", ANY),),
        watch=(keys.live(ANY, "world", ANY), *_health()),
    ),
    "observer": Grants(hear=(keys.viz_all(ANY),), watch=_health()),
}
"""Every identity a certificate may name (``agos certs`` makes one certificate per entry)."""


# (messages, flows) allowed on each kind of grant.
_RULES: dict[str, list[tuple[list[str], list[str]]]] = {
    "publish": [(["put", "delete"], ["ingress"]), (["declare_subscriber"], ["egress"])],
    "hear": [(["declare_subscriber"], ["ingress"]), (["put", "delete"], ["egress"])],
    "query": [(["query"], ["ingress"]), (["reply"], ["egress"]), (["declare_queryable"], ["egress"])],
    "serve": [(["declare_queryable"], ["ingress"]), (["query"], ["egress"]), (["reply"], ["ingress"])],
    "tokens": [(["liveliness_token"], ["ingress"])],
    "watch": [(["declare_liveliness_subscriber", "liveliness_query"], ["ingress"]),
              (["liveliness_token", "reply"], ["egress"])],
    "relay": [(["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable", "liveliness_token",
                "declare_liveliness_subscriber", "liveliness_query"], ["ingress", "egress"])],
}


def access_control(identities: dict[str, Grants] | None = None) -> dict[str, Any]:
    """zenoh's ``access_control`` section: default deny, one subject per identity (certificate
    common name), one rule per (identity, kind of grant, message set)."""
    identities = IDENTITIES if identities is None else identities
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for identity, grants in identities.items():
        subjects.append({"id": identity, "cert_common_names": [identity]})
        rule_ids = []
        for kind, allowed in _RULES.items():
            key_exprs = list(getattr(grants, kind))
            if not key_exprs:
                continue
            for k, (messages, flows) in enumerate(allowed):
                rule_id = f"{identity}-{kind}-{k}"
                rules.append({"id": rule_id, "messages": messages, "flows": flows, "permission": "allow",
                              "key_exprs": key_exprs})
                rule_ids.append(rule_id)
        if rule_ids:
            policies.append({"id": identity, "rules": rule_ids, "subjects": [identity]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}
