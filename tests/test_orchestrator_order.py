"""The orchestrator when an acknowledgement overtakes its record (a small ack and a large record
travel on different keys): the early ack is refused, the record is published again at the next
repeat, and the evaluator's second ack counts it (found in a 63-episode run: an episode was
re-leased after 180 s although its record was stored)."""

from __future__ import annotations

from unittest.mock import MagicMock

import msgspec

from agos.deploy.run.orchestrator import LEASE_REPEAT_S, Lease, Orchestrator
from agos.runtime import keys
from agos.runtime.bus import Sample
from agos.runtime.codec import encode
from agos.runtime.schemas import ResultAck
from tests.test_codec import _record, _spec


def test_an_ack_that_overtakes_its_record_costs_one_repeat_not_a_re_lease() -> None:
    now = [0.0]
    spec = _spec()
    record = msgspec.structs.replace(_record(), run_id="r", episode_id=spec.episode_id, worker_id="w1")
    bus = MagicMock()
    orch = Orchestrator(bus, "r", [spec], policies={"uav": "heuristic", "ugv": "heuristic"}, clock=lambda: now[0])
    orch.pending.clear()
    orch.leases[spec.episode_id] = Lease(spec, "w1", 1, 0.0, 0.0)
    ack = ResultAck(run_id="r", episode_id=spec.episode_id, newly_stored=True)

    orch._inbox.put(Sample(keys.result_ack("r", record.worker_id), encode(ack)))
    orch._inbox.put(Sample(keys.result("r", record.worker_id), encode(record)))
    assert orch.pump(0.0) == [] and orch.unacknowledged() == [spec.episode_id]

    now[0] = LEASE_REPEAT_S + 0.1
    bus.publish.reset_mock()
    orch.pump(0.0)
    republished = [c.args for c in bus.publish.call_args_list if c.args[0] == keys.result("r", record.worker_id)]
    assert republished == [(keys.result("r", record.worker_id), orch.records[spec.episode_id])]

    orch._inbox.put(Sample(keys.result_ack("r", record.worker_id), encode(ResultAck(
        run_id="r", episode_id=spec.episode_id, newly_stored=False))))
    assert [r.episode_id for r in orch.pump(0.0)] == [spec.episode_id]
    assert orch.finished and orch.releases == 0
