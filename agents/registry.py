"""The policy registry: a policy name (see :mod:`agos.agents.names`) to a policy object for one role.
Implementations are imported only when asked for, so a process loads just the policy it serves.
"""

from __future__ import annotations

from pathlib import Path

from agos.agents.contract import Policy
from agos.agents.names import KNOWN, VLM_POLICIES, parse_standin, split_name
from agos.runtime.schemas import Role
from agos.runtime.settings import VlmOptions


def make_policy(name: str, role: Role, *, vlm: VlmOptions | None = None, dataset_out: Path | None = None) -> Policy:
    """Build a policy by name (see ``KNOWN``); ablation variants change only world-side tools.

    VLM policies (``agos-agent``, ``baseline``) need ``vlm``: the endpoint, model and client options.
    ``dataset_out``: the expert also writes every decision there (agents/dataset/writer.py)."""
    base, _ = split_name(name)
    if dataset_out is not None:
        if base != "expert":
            raise ValueError(f"--dataset-out writes the expert's decisions; policy {name!r} is not 'expert'")
        from agos.agents.dataset.writer import DatasetWriter

        return DatasetWriter(role, dataset_out)
    if base in VLM_POLICIES:
        if vlm is None or not vlm.base_url or not vlm.model:
            raise ValueError(f"policy {name!r} asks a VLM: give --vlm-base-url URL and --model NAME "
                             "(offline: start `agos vlm-standin` and use its URL)")
        from agos.agents.vlm.agent import VlmAgent

        return VlmAgent(role, name, vlm)
    if base == "heuristic":
        from agos.agents.heuristic.uav import HeuristicUav
        from agos.agents.heuristic.ugv import HeuristicUgv

        return HeuristicUav() if role == "uav" else HeuristicUgv()
    if base == "paint-only":  # the heuristic with every cue but the paint switched off: one cue's floor
        from agos.agents.heuristic.uav import HeuristicUav
        from agos.agents.heuristic.ugv import HeuristicUgv

        return HeuristicUav(paint_only=True) if role == "uav" else HeuristicUgv(paint_only=True)
    if base == "oracle":
        from agos.agents.oracle import OracleUav, OracleUgv

        return OracleUav() if role == "uav" else OracleUgv()
    if base == "expert":
        from agos.agents.expert import ExpertPolicy

        return ExpertPolicy(role)
    if base == "human":
        raise ValueError("the human policy is a person at a browser: serve the role with `agos human --role ROLE "
                         "--connect EP --run RUN` instead of `agos agent` (docs/HUMAN.md)")
    if base == "random":
        from agos.agents.random_policy import RandomPolicy

        return RandomPolicy(role)
    if base.startswith("standin-"):
        from agos.agents.standin_policy import FixedLatencyPolicy

        return FixedLatencyPolicy(role, parse_standin(base))
    raise ValueError(f"unknown policy {name!r}; known: {KNOWN}")
