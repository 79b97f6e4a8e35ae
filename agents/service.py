"""The agent service process: one role, one policy, any number of episodes of a run.

    agos agent --role uav --policy heuristic --connect tcp/HOST:PORT --run RUN

It answers every observation on ``agos/<run>/ep/*/obs/<role>`` with an action on the matching
``.../act/<role>`` key. A policy that raises is logged and answered with a legal WAIT, so an
agent bug costs a decision, never the episode.
"""

from __future__ import annotations

import logging
import os
import time

from agos.agents.policy import Policy, action_for, make_policy
from agos.runtime import keys
from agos.runtime.bus import Inbox, ZenohBus, zenoh_config
from agos.runtime.codec import DecodeError, decode
from agos.runtime.process import StopFlag, install_stop_handlers, setup_logging
from agos.runtime.schemas import EpisodeRecord, Observation, Role
from agos.runtime.settings import AgosConfig

log = logging.getLogger("agos.agent")


def serve(bus: ZenohBus, policy: Policy, run_id: str, stop: StopFlag) -> int:
    inbox = Inbox()
    bus.subscribe(keys.obs(run_id, "*", policy.role), inbox)
    bus.subscribe(keys.result(run_id, "*"), inbox)
    bus.declare_token(keys.live(run_id, "agent", f"{policy.role}-{os.getpid()}"))
    log.info("%s agent (%s) serving run %s", policy.role, policy.name, run_id)
    while not stop.is_set():
        sample = inbox.get(timeout_s=0.5)
        if sample is None:
            continue
        try:
            message = decode(sample.payload)
        except DecodeError as exc:
            log.warning("ignoring undecodable payload on %s: %s", sample.key, exc)
            continue
        if isinstance(message, EpisodeRecord):
            policy.end_episode(message.episode_id)
        elif isinstance(message, Observation):
            started = time.monotonic()
            try:
                action = policy.act(message)
            except Exception:
                log.exception("policy failed on %s #%d; answering WAIT", message.episode_id, message.decision_index)
                action = action_for(message, "WAIT", rationale="policy error (see agent log)")
            action.agent_wall_latency_s = round(time.monotonic() - started, 4)
            bus.publish(keys.act(run_id, message.episode_id, policy.role), action)
    return 0


def main(cfg: AgosConfig, *, role: Role, policy_name: str | None = None) -> int:
    setup_logging(f"agent-{role}")
    stop = install_stop_handlers()
    name = policy_name or (cfg.run.policy_uav if role == "uav" else cfg.run.policy_ugv)
    policy = make_policy(name, role)
    bus = ZenohBus(zenoh_config(connect=[cfg.zenoh.connect], multicast_scouting=cfg.zenoh.multicast_scouting,
                                connect_timeout_s=cfg.zenoh.connect_timeout_s))
    try:
        return serve(bus, policy, cfg.run.run_id, stop)
    finally:
        bus.close()
