"""The policy contract: one object per role that turns observations into actions.

Every policy, agos's own and yours, subclasses :class:`Policy` (a base class rather than a typing
``Protocol``: it carries the defaults, so the agent service calls every method without asking
whether it exists, and a class that misses the one required method fails when it is defined).

A policy may keep per-episode memory (keyed by ``episode_id``); it is told when an episode is over
(:meth:`Policy.end_episode`) so memory does not grow. Policies never see ground truth: only the
:class:`~agos.runtime.schemas.Observation` (a msgspec struct), over the bus and in-process alike,
and they answer an :class:`~agos.runtime.schemas.Action`, usually built with :func:`action_for`.
Structs are not checked when built: the agent service encodes the answer and reads it back as the
world will, and answers WAIT for one that fails, as for a policy error.
"""

from __future__ import annotations

import asyncio
from typing import Any, Self, cast

from agos.runtime.schemas import Action, ActionName, Observation, Role
from agos.runtime.settings import VlmOptions


class Policy:
    """What an agent service serves and an in-process runner calls: one role's decisions.

    Define at least one of :meth:`act` (synchronous) and :meth:`act_async` (a coroutine); the other
    defaults to calling it. Everything else has a default.

    * ``act(obs) -> Action``: synchronous. In-process runners (``agos sweep``, tests) call it on their
      own thread; the agent service calls it in a worker thread, at most ``--concurrency`` at once,
      or on the thread that received the observation when ``inline`` is true.
    * ``async act_async(obs) -> Action``: what the agent service awaits on its event loop for a
      policy that is not ``inline``. Define it for policies that wait on I/O (a remote model), so
      many decisions overlap their waiting. Default: ``act`` in a worker thread.
    * ``end_episode(episode_id)``: the episode is over (or re-leased and starting afresh): forget
      what was kept about it. Called on the service's loop (a non-inline policy) or the receiving
      thread (an inline one), never during an ``act`` of the same policy when ``inline``.
    * ``async preflight()``: awaited once before an agent service serves; raise an exception whose
      message says what to fix (the service logs that line and exits 3). Default: nothing to check.
    * ``inline``: ``act`` takes microseconds and does no I/O, so the service answers on the thread
      that received the observation instead of handing it to a worker. Default False.
    * ``name``: the policy's name in logs and decision traces. Default: the class's name.
    * ``role``: ``"uav"`` or ``"ugv"``, set by ``__init__(role)``.

    An exception from ``act``/``act_async`` costs that decision a logged WAIT, never the episode.
    The registry (agents/registry.py) builds a policy of your own with :meth:`from_settings`.
    """

    name: str = "policy"
    inline: bool = False
    role: Role

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "name" not in cls.__dict__:
            cls.name = cls.__name__
        if cls.act is Policy.act and cls.act_async is Policy.act_async:
            raise TypeError(f"policy {cls.__module__}.{cls.__qualname__} must define act(obs) or async act_async(obs) "
                            "(agos.agents.contract.Policy)")

    def __init__(self, role: Role) -> None:
        self.role = role

    @classmethod
    def from_settings(cls, role: Role, *, vlm: VlmOptions) -> Self:
        """Build the policy for ``role``: how ``--policy package.module:Class`` and entry-point policies
        are built. ``vlm``: the ``[vlm]`` settings (``--vlm-base-url``, ``--model`` ...), for a policy
        that asks a model. Default: ``cls(role)``."""
        return cls(role)

    def act(self, obs: Observation) -> Action:
        """Return a legal action for ``obs`` (the world turns an illegal one into WAIT).
        Default: run :meth:`act_async` to completion on a fresh event loop."""
        return asyncio.run(self.act_async(obs))

    async def act_async(self, obs: Observation) -> Action:
        """The action for ``obs``, awaited by the agent service. Default: :meth:`act` in a worker
        thread of the running loop's default executor (the service sizes it to ``--concurrency``)."""
        return await asyncio.get_running_loop().run_in_executor(None, self.act, obs)

    def end_episode(self, episode_id: str) -> None:
        """Forget what was kept about an episode. Default: nothing kept."""

    async def preflight(self) -> object:
        """Check what the policy needs (an endpoint, a model file) before serving; raise with a message
        that says what to fix. The return value is ignored. Default: nothing to check."""
        return None


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


class EndpointOutage(Exception):
    """The policy could not decide because what it asks (a model endpoint) gave no answer after its
    retries or before the world's decision timeout: connection errors, timeouts, 408/409/429/5xx
    beyond the retry budget, or a 401/403. Not a decision of the model: the agent service answers the
    world with :attr:`Action.outage <agos.runtime.schemas.Action.outage>` (this message) instead of a
    WAIT, and the world pauses the episode and gives it back (docs/AGENTS.md, "Outages are not the
    model's failures"). In-process runners (``agos sweep``, :class:`agos.Env`) let it propagate. The
    message names the endpoint and what failed."""
