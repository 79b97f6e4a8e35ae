"""agos: air-ground cooperative object search, as processes on a bus (the ``agos`` command) and as a
Python library (docs/LIBRARY.md):

* :class:`Env` (``agos.env``): one episode at a time, stepped from your own loop, in this process;
* ``agos.pettingzoo.parallel_env()``: the two roles as a PettingZoo parallel environment;
* ``agos.gymnasium.RoleEnv``: one role as a Gymnasium environment, the other played by a policy;
* ``agos.vector.make_vector_env(n)``: ``n`` of those in subprocesses (Gymnasium's AsyncVectorEnv).

The subpackages (``agos.runtime``, ``agos.world``, ``agos.agents``, ``agos.evaluator``,
``agos.deploy``) are the repository's top-level folders. Every import of any of them runs this
file, so it imports nothing: the names below are loaded when first used.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from agos.env import Env, EnvStateError, IllegalActionError, StepResult, episode_config

__all__ = ["Env", "EnvStateError", "IllegalActionError", "StepResult", "episode_config"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from agos import env

        return getattr(env, name)
    raise AttributeError(f"module 'agos' has no attribute {name!r}")
