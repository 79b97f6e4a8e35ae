"""The exact mTSP MILP as the paper writes it (Appendix "Path Generation of the AGOS Dataset"),
solved with HiGHS (``highspy``): the reference for small instances.

Per vehicle k with start s_k, on the complete digraph of its waypoints (the metric closure):
binaries x_ij (arc), y_i (visited), z_i (terminal), continuous MTZ orders u_i >= 0 and the
completion times T_k; minimise T_max subject to

* T_max >= offset_k + T_k,  T_k = sum t_ij x_ij;
* y_{s_k} = 1; y_i = 1 for exclusive nodes; y^A_a + y^G_g >= 1 for each pair;
* sum_i z_i = 1, z_i <= y_i;
* in-degree sum_j x_ji = y_i and out-degree sum_j x_ij = y_i - z_i for i != s_k;
* MTZ: u_{s_k} = 0, y_i <= u_i <= (n_k - 1) y_i, u_j >= u_i + 1 - n_k (1 - x_ij) for j != s_k.

Written out where the paper leaves it implicit: the start has no incoming arc and one outgoing
arc unless it is the terminal (a route leaves its start once and never returns). One departure
from the paper: it fixes z_{s_k} = 0 ("each vehicle visits at least one node other than its
start"); here the start may be the terminal, an empty route, which the paper's constraint would
forbid even when every node left to a vehicle is better searched by the other (it happens when a
plan is solved again after a wrong candidate, with only paired nodes left to one role).

A tie-break of ``TIE_BREAK`` x (T_A + T_G) makes the vehicle that does not set the makespan take a
short route too; it never trades makespan for it beyond the solver's tolerance.
"""

from __future__ import annotations

import time

import highspy
import numpy as np

from agos.world.expert.mtsp import MtspInstance, MtspSolution

TIE_BREAK = 1e-5


def solve_milp(inst: MtspInstance, *, time_limit_s: float = 120.0, tie_break: float = TIE_BREAK) -> MtspSolution:
    """Solve ``inst`` exactly (``optimal`` False when ``time_limit_s`` ran out first)."""
    started = time.perf_counter()
    h = highspy.Highs()
    h.setOptionValue("output_flag", False)
    h.setOptionValue("time_limit", float(time_limit_s))
    h.setOptionValue("mip_rel_gap", 1e-7)
    h.setOptionValue("threads", 1)
    h.setOptionValue("random_seed", 0)
    t_max = h.addVariable(lb=0.0)
    arcs: list[dict[tuple[int, int], highspy.highs_var]] = []
    visited: list[list[highspy.highs_var]] = []
    completion = []
    for role, (times, offset) in enumerate(((inst.uav_times_s, inst.uav_offset_s), (inst.ugv_times_s, inst.ugv_offset_s))):
        n = len(times)
        exclusive = set(inst.exclusive(role))
        y = [h.addBinary() for _ in range(n)]
        visited.append(y)
        h.addConstr(y[0] == 1)
        for i in exclusive:
            h.addConstr(y[i] == 1)
        x = {(i, j): h.addBinary() for i in range(n) for j in range(1, n) if i != j and np.isfinite(times[i, j])}
        arcs.append(x)
        t_k = h.addVariable(lb=0.0)
        completion.append(t_k)
        h.addConstr(t_k == sum(float(times[i, j]) * v for (i, j), v in x.items()) if x else t_k == 0.0)
        h.addConstr(t_max >= t_k + float(offset))
        if n == 1:
            continue
        z = [h.addBinary() for _ in range(n)]
        u = [h.addVariable(lb=0.0, ub=float(n - 1)) for _ in range(n)]
        h.addConstr(sum(z) == 1)
        h.addConstr(u[0] == 0)
        h.addConstr(sum(v for (i, _), v in x.items() if i == 0) == 1 - z[0])
        for i in range(n):
            h.addConstr(z[i] <= y[i])
            if i == 0:
                continue
            h.addConstr(sum(v for (_, j), v in x.items() if j == i) == y[i])
            h.addConstr(sum(v for (a, _), v in x.items() if a == i) == y[i] - z[i])
            h.addConstr(u[i] >= y[i])
            h.addConstr(u[i] <= (n - 1) * y[i])
        for (i, j), v in x.items():
            h.addConstr(u[j] >= u[i] + 1 - n * (1 - v))
    for a, g in inst.pairs:
        h.addConstr(visited[0][a] + visited[1][g] >= 1)
    h.minimize(t_max + tie_break * (completion[0] + completion[1]))
    status = h.getModelStatus()
    feasible = h.getInfo().primal_solution_status == 2  # kSolutionStatusFeasible
    if status not in (highspy.HighsModelStatus.kOptimal, highspy.HighsModelStatus.kTimeLimit) or not feasible:
        raise RuntimeError(f"the mTSP MILP found no solution ({h.modelStatusToString(status)})")
    values = np.asarray(h.getSolution().col_value)
    routes = [_route({ij: values[v.index] for ij, v in x.items()}) for x in arcs]
    return MtspSolution(routes[0], routes[1], inst.makespan_s(routes[0], routes[1]), "milp",
                        status == highspy.HighsModelStatus.kOptimal, time.perf_counter() - started)


def _route(x: dict[tuple[int, int], float]) -> list[int]:
    """Follow the chosen arcs from node 0."""
    nxt = {i: j for (i, j), v in x.items() if v > 0.5}
    route = [0]
    while route[-1] in nxt and len(route) <= len(x) + 1:
        route.append(nxt[route[-1]])
    return route
