"""The fast mTSP solver for full-size instances: OR-Tools CP-SAT with circuit constraints.

The same instance and model as the MILP (:mod:`agos.world.expert.milp`), with the MTZ orders
replaced by CP-SAT's circuit constraint, which propagates far better: per vehicle one circuit
over its waypoints and a dummy node D closing the open route (terminal -> D -> start), a
self-loop on each waypoint meaning "not visited", no arc into the start; the arc start -> D is
the empty route (the MILP's start as terminal, see there).
Exclusive nodes are visited, each pair at least once; the objective is the makespan plus a
tie-break of the summed route times, in centiseconds.

Determinism: one worker, a fixed seed and a limit in CP-SAT's *deterministic* time
(``max_deterministic_time``, its count of work, not seconds of the wall clock), so the same
instance gives the same routes on any machine. ``optimal`` says whether CP-SAT proved it.
"""

from __future__ import annotations

import time

import numpy as np
from ortools.sat.python import cp_model

from agos.world.expert.mtsp import MtspInstance, MtspSolution

SCALE = 100
"""Solver time unit: centiseconds."""


def solve_fast(inst: MtspInstance, *, deterministic_time: float = 5.0) -> MtspSolution:
    """Solve ``inst`` (module docstring); ``deterministic_time`` bounds CP-SAT's work."""
    started = time.perf_counter()
    model = cp_model.CpModel()
    visited: list[list[cp_model.IntVar]] = []
    arcs: list[dict[tuple[int, int], cp_model.IntVar]] = []
    totals = []
    finite_sum_s = sum(float(np.where(np.isfinite(t), t, 0.0).sum()) for t in (inst.uav_times_s, inst.ugv_times_s))
    horizon = int(SCALE * (inst.uav_offset_s + inst.ugv_offset_s + finite_sum_s)) + 1
    t_max = model.new_int_var(0, horizon, "t_max")
    for role, (times, offset) in enumerate(((inst.uav_times_s, inst.uav_offset_s), (inst.ugv_times_s, inst.ugv_offset_s))):
        n = len(times)
        exclusive = set(inst.exclusive(role))
        y = [model.new_bool_var(f"y{role}_{i}") for i in range(n)]
        visited.append(y)
        for i in exclusive:
            model.add(y[i] == 1)
        x: dict[tuple[int, int], cp_model.IntVar] = {}
        cost = []
        if n > 1:
            dummy = n
            circuit: list[tuple[int, int, cp_model.LiteralT]] = []
            for i in range(n):
                for j in range(1, n):
                    if i != j and np.isfinite(times[i, j]):
                        x[(i, j)] = model.new_bool_var(f"x{role}_{i}_{j}")
                        circuit.append((i, j, x[(i, j)]))
                        cost.append(round(float(times[i, j]) * SCALE) * x[(i, j)])
                circuit.append((i, dummy, model.new_bool_var(f"end{role}_{i}")))
                if i > 0:
                    circuit.append((i, i, ~y[i]))
            circuit.append((dummy, 0, model.new_constant(1)))
            model.add_circuit(circuit)
        arcs.append(x)
        total = model.new_int_var(0, horizon, f"T{role}")
        model.add(total == sum(cost))
        model.add(t_max >= total + round(offset * SCALE))
        totals.append(total)
    for a, g in inst.pairs:
        model.add_bool_or([visited[0][a], visited[1][g]])
    model.minimize(t_max * (2 * horizon + 1) + totals[0] + totals[1])
    solver = cp_model.CpSolver()
    solver.parameters.num_workers = 1
    solver.parameters.random_seed = 0
    solver.parameters.max_deterministic_time = deterministic_time
    status = solver.solve(model)
    if status not in (cp_model.OPTIMAL, cp_model.FEASIBLE):
        raise RuntimeError(f"CP-SAT found no mTSP solution ({solver.status_name(status)})")
    routes = [_route({ij: solver.boolean_value(v) for ij, v in x.items()}) for x in arcs]
    return MtspSolution(routes[0], routes[1], inst.makespan_s(routes[0], routes[1]), "cp-sat", status == cp_model.OPTIMAL,
                        time.perf_counter() - started)


def _route(x: dict[tuple[int, int], bool]) -> list[int]:
    nxt = {i: j for (i, j), v in x.items() if v}
    route = [0]
    while route[-1] in nxt and len(route) <= len(x) + 1:
        route.append(nxt[route[-1]])
    return route
