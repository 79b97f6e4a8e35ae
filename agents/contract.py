"""The policy contract: one object per role that turns observations into actions.

A policy may keep per-episode memory (keyed by ``episode_id``); the service calls
:meth:`Policy.end_episode` when an episode's result is seen so memory does not grow.
Policies never see ground truth: only :class:`~agos.runtime.schemas.Observation`.

Policies receive the real :class:`~agos.runtime.schemas.Observation` (a msgspec struct), over
the bus and in-process alike, and answer an :class:`~agos.runtime.schemas.Action`, usually built
with :func:`action_for`. Structs are not checked when built: the agent service encodes the answer
and reads it back as the world will, and answers WAIT for one that fails, as for a policy error.
"""

from __future__ import annotations

from typing import Any, Protocol, cast

from agos.runtime.schemas import Action, ActionName, Observation, Role


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


def action_for(obs: Observation, name: str, **fields: Any) -> Action:
    """An action answering ``obs`` (run, episode, role, decision index and attempt filled in). Built
    without checks, like any struct (``name`` is not checked against ``ActionName`` here): the
    agent service checks it before sending it, and the world refuses an action that is not legal."""
    return Action(run_id=obs.run_id, episode_id=obs.episode_id, role=obs.role,
                  decision_index=obs.decision_index, attempt=obs.attempt, action=cast(ActionName, name), **fields)


class FatalPolicyError(Exception):
    """A policy error after which its agent service must stop answering rather than answer WAIT (a
    replay of recorded model calls that lacks one): the service logs the message as one ERROR line
    and exits with :attr:`exit_code`, and ``agos eval`` shows that line."""

    exit_code = 4
