"""The expert of AGOS-Dataset (paper §3.3 and Appendix "Path Generation of the AGOS Dataset"):
trajectories by mTSP (Stage 1) and the actions and messages that realise them (Stage 2).
docs/DATASET.md describes the pipeline and every choice where the paper is vague.

Layer: above ``world.sim`` (it renders and asks the world's rules), beside ``world.episodes``.
:func:`install` lets this process's episodes carry the expert's plan in observations when the
run's policy is ``expert`` (``world/sim/observations.py`` delivers what this package plans).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from agos.runtime.schemas import ExpertHints, Role
    from agos.world.sim.state import EpisodeState


def install() -> None:
    """Plan expert episodes in this process (world workers, in-process runs). The solvers are
    imported at the first expert episode, not here: a world worker of other runs never loads them."""
    from agos.world.sim.observations import use_expert_planner

    def plan(st: EpisodeState) -> dict[Role, ExpertHints]:
        from agos.world.expert.planner import hints_of, plan_episode

        return hints_of(st, plan_episode(st))

    use_expert_planner(plan)
