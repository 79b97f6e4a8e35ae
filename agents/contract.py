"""The policy contract: one object per role that turns observations into actions.

A policy may keep per-episode memory (keyed by ``episode_id``); the service calls
:meth:`Policy.end_episode` when an episode's result is seen so memory does not grow.
Policies never see ground truth: only :class:`~agos.runtime.schemas.Observation`.

Over the bus, the agent service delivers an observation as its compiled mirror
(:mod:`agos.runtime.structs`): the same fields and nested values, read the same way, but without
the pydantic methods. In-process runs pass the model itself. Read observations; do not rely on
``model_dump``/``model_copy`` (``structs.to_model`` gives the model when one is needed).
:func:`action_for` answers in the same kind (a mirror action for a mirror observation), so a
decision over the bus touches no pydantic code; a policy may also return an :class:`Action` model.
"""

from __future__ import annotations

from typing import Protocol

import msgspec

from agos.runtime.schemas import Action, Observation, Role
from agos.runtime.structs import mirror

_MIRROR_ACTION = mirror(Action)


class Policy(Protocol):
    """What an agent service serves. Optional extras: ``act_async`` (a coroutine the service awaits:
    remote models), ``inline = True`` (``act`` takes microseconds and does no I/O, so the service
    answers on the thread that received the observation instead of handing it to a worker),
    ``preflight`` (checked before serving)."""

    role: Role
    name: str

    def act(self, obs: Observation) -> Action:
        """Return a legal action for ``obs`` (the world turns an illegal one into WAIT)."""
        ...

    def end_episode(self, episode_id: str) -> None:
        """Forget what was kept about an episode."""
        ...


def action_for(obs: Observation, name: str, **fields: object) -> Action:
    """An action answering ``obs`` (run, episode, role and decision index filled in), in the
    observation's kind: the model for a model; for a mirror (over the bus), the mirror of
    :class:`Action`, which is built without checks: the agent service checks its types before
    sending it (``codec.encode_checked``) and answers WAIT for one that fails, as for a policy error."""
    kind = _MIRROR_ACTION if isinstance(obs, msgspec.Struct) else Action
    return kind(run_id=obs.run_id, episode_id=obs.episode_id, role=obs.role,
                decision_index=obs.decision_index, action=name, **fields)
