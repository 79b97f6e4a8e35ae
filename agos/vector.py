"""``n`` agos environments in subprocesses, two ways (docs/LIBRARY.md, "Vector environments"):

* ``agos.vector.make_vector_env(n, ...)``: Gymnasium's ``AsyncVectorEnv`` over
  :class:`agos.gymnasium.RoleEnv`, in lockstep: ``step`` returns when every environment has stepped
  (observations through shared memory, each environment reset when its episode ends). For algorithms
  that need a synchronous batch of all ``n``.
* ``agos.vector.AsyncEnvPool(n, ...)``: EnvPool-style, for throughput: ``send`` actions to some
  environments, ``recv`` the results of whichever are ready. An agos step costs from one render (a
  move) to six (a STOP_OBSERVE) plus the partner's decisions, so in lockstep each step waits for the
  slower environment; the pool keeps every subprocess busy.

.. code-block:: python

    from agos.vector import AsyncEnvPool, make_vector_env

    envs = make_vector_env(2, role="ugv", partner="heuristic")
    obs, infos = envs.reset(seed=0)
    obs, rewards, terminations, truncations, infos = envs.step(envs.action_space.sample())
    envs.close()

    with AsyncEnvPool(2, role="ugv", partner="heuristic") as pool:
        pool.reset(seed=0)
        for _ in range(100):
            ready = pool.recv()                      # at least one environment's result
            pool.send([pool.single_action_space.sample(mask=m) for m in ready.observations["action_mask"]],
                      ready.env_ids)

Throughput: bench/bench_env.py ``--only vector`` (bench/README.md, "agos as a library").
"""

from __future__ import annotations

import contextlib
import functools
import multiprocessing
import time
import traceback
from collections.abc import Sequence
from multiprocessing.connection import Connection, wait
from multiprocessing.process import BaseProcess
from typing import Any, NamedTuple, cast

import gymnasium
import numpy as np
from gymnasium.vector import AsyncVectorEnv

from agos.env import EnvStateError
from agos.gymnasium import RoleEnv

__all__ = ["AsyncEnvPool", "EnvWorkerError", "PoolResult", "make_vector_env"]


def make_vector_env(n: int, *, context: str | None = None, **kwargs: Any) -> AsyncVectorEnv:
    """``n`` :class:`RoleEnv` (built with ``kwargs``) in ``n`` subprocesses. ``context``: the
    multiprocessing start method (default: the platform's; ``"spawn"`` needs picklable ``kwargs``,
    as episode specs, configurations and policy names are)."""
    if n < 1:
        raise ValueError(f"n={n}: give at least 1 environment")
    return AsyncVectorEnv([functools.partial(RoleEnv, **kwargs) for _ in range(n)], context=context)


class EnvWorkerError(RuntimeError):
    """An environment of an :class:`AsyncEnvPool` raised (or its process died): the message names the
    environment (``env_id``) and the exception; ``worker_traceback`` is the traceback in the
    subprocess (also added as a note)."""

    def __init__(self, env_id: int, message: str, worker_traceback: str = "") -> None:
        super().__init__(f"env {env_id}: {message}")
        self.env_id = env_id
        self.worker_traceback = worker_traceback
        if worker_traceback:
            self.add_note(f"in env {env_id}'s process:\n{worker_traceback.rstrip()}")


class PoolResult(NamedTuple):
    """What :meth:`AsyncEnvPool.recv` returns: one row per environment that answered, in ``env_ids``
    order. A reset's row (after :meth:`~AsyncEnvPool.reset`, or the step after an episode's end) has
    reward 0 and no end."""

    env_ids: np.ndarray
    """int64, ascending: which environments these rows are (send their next actions to them)."""
    observations: dict[str, np.ndarray]
    """Each key of the role's observation space, stacked: shape ``(len(env_ids), *space shape)``."""
    rewards: np.ndarray
    """float64, summed over the world's rounds in the step (:class:`RoleEnv`)."""
    terminations: np.ndarray
    """bool: the episode ended (a confirmation, right or wrong)."""
    truncations: np.ndarray
    """bool: the episode was cut (budget, time limit, error)."""
    infos: list[dict[str, Any]]
    """The environments' info dicts, as :class:`RoleEnv` gives them."""


_READY, _RESULT, _ERROR = "ready", "result", "error"


class AsyncEnvPool:
    """``n`` :class:`RoleEnv` (built with ``kwargs``, which must pickle: episode specs, configurations,
    policy names and module-level policies do) in ``n`` subprocesses, stepped asynchronously.

    * The constructor starts the processes and returns once every environment is built (an error
      building one raises :class:`EnvWorkerError` naming it). ``single_observation_space`` and
      ``single_action_space`` are :class:`RoleEnv`'s.
    * :meth:`reset` starts an episode in every environment (``seed + i`` for environment ``i``, as
      ``AsyncVectorEnv`` seeds; results still in flight are dropped); their first observations come
      from :meth:`recv`.
    * :meth:`send` hands actions to environments that are not stepping (each has answered since its
      last send); :meth:`recv` waits until at least ``min_envs`` of those stepping have answered and
      returns every answer ready by then (:class:`PoolResult`).
    * Autoreset as ``AsyncVectorEnv``'s default (next step): after a result that ends its episode,
      the next action sent to that environment is ignored and its result is the new episode's first
      observation.
    * An exception in an environment is raised by the call that meets it as :class:`EnvWorkerError`
      naming the environment, and closes the pool (build a new one).
    * :meth:`close` (also on leaving a ``with`` block) stops every process: it asks them to exit,
      waits up to ``close_timeout_s``, then terminates and kills what is left; it never hangs.
    """

    def __init__(self, n: int, *, close_timeout_s: float = 5.0, **kwargs: Any) -> None:
        if n < 1:
            raise ValueError(f"n={n}: give at least 1 environment")
        self.num_envs = n
        self.close_timeout_s = close_timeout_s
        self.closed = False
        self._in_flight: set[int] = set()  # sent a command, not answered yet
        self._answered: dict[int, tuple[Any, ...]] = {}  # answered, not returned by recv yet
        ctx = multiprocessing.get_context("spawn")  # a fresh interpreter each: no forked PyBullet or threads
        self._conns: list[Connection] = []
        self._processes: list[BaseProcess] = []
        try:
            for env_id in range(n):
                parent, child = ctx.Pipe()
                process = ctx.Process(target=_worker, args=(env_id, child, kwargs), name=f"agos-env-{env_id}",
                                      daemon=True)
                process.start()
                child.close()
                self._conns.append(parent)
                self._processes.append(process)
            spaces = [self._answer(env_id) for env_id in range(n)]
        except BaseException:
            self.close()
            raise
        self.single_observation_space: gymnasium.spaces.Dict = spaces[0][0]
        self.single_action_space: gymnasium.spaces.Discrete = spaces[0][1]

    @property
    def processes(self) -> list[BaseProcess]:
        """The environments' processes, environment ``i`` at index ``i``."""
        return list(self._processes)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> None:
        """Start an episode in every environment; :meth:`recv` returns their first observations."""
        self._check_open()
        self._collect(self.num_envs, None)  # answers to earlier commands: dropped
        self._answered.clear()
        for env_id in range(self.num_envs):
            self._command(env_id, ("reset", (None if seed is None else seed + env_id, options)))

    def send(self, actions: Sequence[int | np.integer[Any]] | np.ndarray,
             env_ids: Sequence[int | np.integer[Any]] | np.ndarray) -> None:
        """Hand ``actions[k]`` (an index of ``single_action_space``) to environment ``env_ids[k]``."""
        self._check_open()
        ids = [int(i) for i in env_ids]
        if len(ids) != len(actions):
            raise ValueError(f"{len(actions)} actions for {len(ids)} env_ids: give one action per environment")
        if len(set(ids)) != len(ids):
            raise ValueError(f"env_ids {ids}: each environment at most once per send")
        for env_id in ids:
            if not 0 <= env_id < self.num_envs:
                raise ValueError(f"env_id {env_id}: the pool has environments 0..{self.num_envs - 1}")
            if env_id in self._in_flight or env_id in self._answered:
                raise EnvStateError(f"env {env_id} is still stepping: recv() its result before sending to it again")
        for env_id, action in zip(ids, actions, strict=True):
            self._command(env_id, ("step", int(action)))

    def recv(self, *, min_envs: int = 1, timeout_s: float | None = None) -> PoolResult:
        """The results of the environments that have answered: wait until at least ``min_envs`` (at
        most those stepping) have, then take every answer ready. ``timeout_s``: raise
        ``TimeoutError`` when fewer have answered by then (None: wait as long as it takes)."""
        self._check_open()
        if not self._in_flight and not self._answered:
            raise EnvStateError("recv() with no environment stepping: reset() or send() first")
        self._collect(max(1, min(min_envs, len(self._in_flight) + len(self._answered))), timeout_s)
        rows = [(env_id, *self._answered.pop(env_id)) for env_id in sorted(self._answered)]
        keys = rows[0][1].keys()
        return PoolResult(np.array([r[0] for r in rows], dtype=np.int64),
                          {k: np.stack([r[1][k] for r in rows]) for k in keys},
                          np.array([r[2] for r in rows], dtype=np.float64), np.array([r[3] for r in rows], dtype=bool),
                          np.array([r[4] for r in rows], dtype=bool), [r[5] for r in rows])

    def close(self) -> None:
        """Stop every process (class docstring); a second call does nothing."""
        if self.closed:
            return
        self.closed = True
        deadline = time.monotonic() + self.close_timeout_s
        waiting = {conn: env_id for env_id, conn in enumerate(self._conns) if env_id in self._in_flight}
        for env_id, conn in enumerate(self._conns):
            if env_id not in self._in_flight:
                _send_quietly(conn, ("close", None))
        while waiting and (left := deadline - time.monotonic()) > 0:  # let steps in flight finish, then close
            for ready in wait(list(waiting), timeout=left):
                answering = waiting.pop(cast(Connection, ready))
                with contextlib.suppress(EOFError, OSError):
                    self._conns[answering].recv()
                _send_quietly(self._conns[answering], ("close", None))
        for process in self._processes:
            process.join(max(0.0, deadline - time.monotonic()))
        for process in self._processes:
            if process.is_alive():
                process.terminate()
                process.join(1.0)
            if process.is_alive():
                process.kill()
                process.join(1.0)
        for conn in self._conns:
            conn.close()
        self._in_flight.clear()
        self._answered.clear()

    def __enter__(self) -> AsyncEnvPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        if not getattr(self, "closed", True):
            self.close()

    def _check_open(self) -> None:
        if self.closed:
            raise EnvStateError("the pool is closed: build a new AsyncEnvPool")

    def _command(self, env_id: int, message: tuple[str, Any]) -> None:
        """Send ``message`` to environment ``env_id``, which then steps; a dead process closes the pool and raises."""
        try:
            self._conns[env_id].send(message)
        except (BrokenPipeError, EOFError, OSError):
            self._processes[env_id].join(1.0)
            self.close()
            raise EnvWorkerError(env_id, f"its process exited (exit code {self._processes[env_id].exitcode})") from None
        self._in_flight.add(env_id)

    def _collect(self, at_least: int, timeout_s: float | None) -> None:
        """Move answers of stepping environments into ``_answered`` until it holds ``at_least``, then
        any other answer already there. Answers stay there when it times out."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while self._in_flight:
            enough = len(self._answered) >= at_least
            wait_s = 0.0 if enough else None if deadline is None else max(0.0, deadline - time.monotonic())
            conns = {self._conns[i]: i for i in self._in_flight}
            sentinels = {self._processes[i].sentinel: i for i in self._in_flight}  # a process that died
            ready = wait([*conns, *sentinels], timeout=wait_s)
            if not ready:
                if enough:
                    return
                raise TimeoutError(f"{len(self._answered)} of {at_least} environments answered in {timeout_s} s; "
                                   f"still stepping: {sorted(self._in_flight)}")
            answering = {conns[c] for c in ready if c in conns} | {sentinels[s] for s in ready if s in sentinels}
            for env_id in sorted(answering):
                self._answered[env_id] = self._answer(env_id)
                self._in_flight.discard(env_id)

    def _answer(self, env_id: int) -> tuple[Any, ...]:
        """Environment ``env_id``'s next answer; its error (or its process's end) closes the pool and raises."""
        try:
            kind, payload = self._conns[env_id].recv()
        except (EOFError, OSError):
            self._processes[env_id].join(1.0)
            error = EnvWorkerError(env_id, f"its process exited (exit code {self._processes[env_id].exitcode})")
        else:
            if kind != _ERROR:
                return tuple(payload)
            error = EnvWorkerError(env_id, payload[0], payload[1])
        self.close()
        raise error


def _worker(env_id: int, conn: Connection, kwargs: dict[str, Any]) -> None:
    """Environment ``env_id``'s process: build it, then answer ``reset``/``step`` until ``close``."""
    env: RoleEnv | None = None
    try:
        try:
            env = RoleEnv(**kwargs)
            conn.send((_READY, (env.observation_space, env.action_space)))
            ended = False
            while True:
                command, payload = conn.recv()
                if command == "close":
                    return
                if command == "reset" or ended:
                    seed, options = payload if command == "reset" else (None, None)
                    obs, info = env.reset(seed=seed, options=options)
                    conn.send((_RESULT, (obs, 0.0, False, False, info)))
                    ended = False
                else:
                    obs, reward, terminated, truncated, info = env.step(payload)
                    conn.send((_RESULT, (obs, reward, terminated, truncated, info)))
                    ended = terminated or truncated
        except (KeyboardInterrupt, EOFError, BrokenPipeError):
            return  # Ctrl-C reaches the whole process group; the parent handles it
        except Exception as e:  # every error goes to the parent, which raises it
            _send_quietly(conn, (_ERROR, (f"{type(e).__name__}: {e}", traceback.format_exc())))
    finally:
        if env is not None:
            env.close()
        conn.close()


def _send_quietly(conn: Connection, message: tuple[str, Any]) -> None:
    with contextlib.suppress(BrokenPipeError, EOFError, OSError):
        conn.send(message)
