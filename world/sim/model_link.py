"""A model-backed decision's trip over the link to the model (runtime/model_link.py), for the engine.

A decision is model-backed when its action carries a :class:`~agos.runtime.schemas.DecisionTrace`
with ``request_bytes > 0`` (VLM policies fill it; scripted policies send no trace and pay nothing).
With a link configured (``EpisodeConfig.model_link``), the engine delays the decision's effect by the
exchange's link time, in both timing modes, and a decision whose request or reply never got through
becomes a counted WAIT whose fallback reason names the link.
"""

from __future__ import annotations

from agos.runtime.model_link import Exchange
from agos.runtime.schemas import Action, Role
from agos.world.sim.state import EpisodeState


def exchange(st: EpisodeState, role: Role, action: Action | None, compute_s: float = 0.0) -> Exchange | None:
    """The trip of ``role``'s decision taken at ``st.sim_time_s - compute_s`` (``compute_s``: the
    model's measured time, realtime mode, already added to the clock), or None when it pays none."""
    trace = action.trace if action is not None else None
    if st.model_link is None or trace is None or trace.request_bytes <= 0:
        return None
    n = 1 + trace.reasks  # the model was asked n times, each time the whole way
    return st.model_link.exchange(role, st.sim_time_s - compute_s, trace.request_bytes, trace.reply_bytes,
                                  exchanges=n, compute_s=compute_s / n)


def failure(st: EpisodeState, trip: Exchange | None) -> str | None:
    """The fallback reason of a decision whose reply never came back, else None."""
    if trip is None or trip.failed is None or st.model_link is None:
        return None
    return f"model link {st.model_link.profile.name}: no reply after {trip.attempts} attempt(s), last {trip.failed}"
