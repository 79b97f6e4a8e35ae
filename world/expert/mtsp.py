"""The expert's mTSP (paper, Appendix "Path Generation of the AGOS Dataset"): the instance both
solvers read, their answer, and a checker of an answer against the instance.

Two vehicles, the UAV (A) and the UGV (G), each on the metric closure of its own graph (a
complete graph over its waypoints whose arc times are shortest travel times, so a route may pass
through waypoints it does not count as visited). Node 0 of each is its start. Every node that is
in no pair is exclusive to its vehicle and must be visited; of each pair (a, g) at least one
must be; each route is open (it ends where its last node is) and the objective is the makespan,
``max_k (offset_k + T_k)`` with ``T_k`` the route's travel time. ``offset_k`` (0 in the paper)
lets a re-plan start the two vehicles at different times (after a wrong candidate).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MtspInstance:
    uav_times_s: np.ndarray
    """(n_A, n_A) travel times between UAV waypoints; node 0 is the UAV's start."""
    ugv_times_s: np.ndarray
    """(n_G, n_G) travel times between UGV waypoints; node 0 is the UGV's start."""
    pairs: tuple[tuple[int, int], ...] = ()
    """(UAV node, UGV node): visiting either covers both (the paper's V^C)."""
    uav_offset_s: float = 0.0
    ugv_offset_s: float = 0.0

    @property
    def sizes(self) -> tuple[int, int]:
        return len(self.uav_times_s), len(self.ugv_times_s)

    def exclusive(self, role: int) -> list[int]:
        """Nodes of vehicle ``role`` (0 UAV, 1 UGV) in no pair, the start included: all visited."""
        paired = {p[role] for p in self.pairs}
        return [i for i in range(self.sizes[role]) if i not in paired]

    def route_time_s(self, role: int, route: list[int]) -> float:
        times = self.uav_times_s if role == 0 else self.ugv_times_s
        return float(sum(times[a, b] for a, b in zip(route, route[1:], strict=False)))

    def makespan_s(self, uav_route: list[int], ugv_route: list[int]) -> float:
        return max(self.uav_offset_s + self.route_time_s(0, uav_route), self.ugv_offset_s + self.route_time_s(1, ugv_route))


@dataclass(frozen=True)
class MtspSolution:
    uav_route: list[int]
    """UAV nodes in visiting order, starting with 0."""
    ugv_route: list[int]
    makespan_s: float
    solver: str
    """``milp`` (HiGHS, the paper's model) or ``cp-sat`` (OR-Tools' CP-SAT)."""
    optimal: bool
    """Proven optimal (the MILP within its gap), or not known."""
    solve_wall_s: float


def check_solution(inst: MtspInstance, sol: MtspSolution) -> list[str]:
    """What is wrong with ``sol`` for ``inst`` (empty when it is feasible and its makespan right)."""
    problems = []
    for role, route in ((0, sol.uav_route), (1, sol.ugv_route)):
        n = inst.sizes[role]
        if not route or route[0] != 0:
            problems.append(f"route {role} does not start at node 0: {route}")
        if len(set(route)) != len(route) or any(not 0 <= i < n for i in route):
            problems.append(f"route {role} repeats a node or names one out of range: {route}")
        missing = set(inst.exclusive(role)) - set(route)
        if missing:
            problems.append(f"route {role} misses exclusive nodes {sorted(missing)}")
    for a, g in inst.pairs:
        if a not in sol.uav_route and g not in sol.ugv_route:
            problems.append(f"pair ({a}, {g}) visited by neither")
    if not np.isclose(inst.makespan_s(sol.uav_route, sol.ugv_route), sol.makespan_s, rtol=1e-6, atol=1e-6):
        problems.append(f"makespan {sol.makespan_s} is not the routes' {inst.makespan_s(sol.uav_route, sol.ugv_route)}")
    return problems
