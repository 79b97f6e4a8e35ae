"""``n`` agos environments in subprocesses: ``agos.vector.make_vector_env(n, ...)``, Gymnasium's
``AsyncVectorEnv`` over :class:`agos.gymnasium.RoleEnv` (one PyBullet world per process, observations
through shared memory, each environment reset when its episode ends, as ``AsyncVectorEnv`` does).

.. code-block:: python

    from agos.vector import make_vector_env

    envs = make_vector_env(2, role="ugv", partner="heuristic")
    obs, infos = envs.reset(seed=0)
    obs, rewards, terminations, truncations, infos = envs.step(envs.action_space.sample())
    envs.close()

Throughput: bench/bench_env.py ``--vector`` (bench/README.md, "agos as a library").
"""

from __future__ import annotations

import functools
from typing import Any

from gymnasium.vector import AsyncVectorEnv

from agos.gymnasium import RoleEnv

__all__ = ["make_vector_env"]


def make_vector_env(n: int, *, context: str | None = None, **kwargs: Any) -> AsyncVectorEnv:
    """``n`` :class:`RoleEnv` (built with ``kwargs``) in ``n`` subprocesses. ``context``: the
    multiprocessing start method (default: the platform's; ``"spawn"`` needs picklable ``kwargs``,
    as episode specs, configurations and policy names are)."""
    if n < 1:
        raise ValueError(f"n={n}: give at least 1 environment")
    return AsyncVectorEnv([functools.partial(RoleEnv, **kwargs) for _ in range(n)], context=context)
