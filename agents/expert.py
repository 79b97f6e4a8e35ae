"""The expert policy: replays the plan of AGOS-Dataset's expert (agos.world.expert) through the
real runtime, the dataset's own proof that its trajectories are solutions.

The world plans each episode once (it holds the ground truth: the mTSP over both roles'
waypoints, truncation where the target is found, the handoff, wrong candidates in hard episodes)
and gives each role its script in ``Observation.expert``, only in runs whose policy is
``expert``: one step per decision, with the sim time the world will ask it at. This policy holds
no memory: decision k answers with step k. A step whose time or legality does not match the
observation means the world and the plan disagree (a bug, or a link profile other than the
ideal one the plan assumes): it is logged and answered with WAIT.
"""

from __future__ import annotations

import logging

from agos.agents.contract import Policy, action_for
from agos.runtime.schemas import Action, Observation, Role

log = logging.getLogger(__name__)

TIME_TOLERANCE_S = 1e-6


class ExpertPolicy(Policy):
    name = "expert"
    inline = True  # a list lookup, no I/O: answered on the receiving thread (agents/agent_service.py)

    def __init__(self, role: Role) -> None:
        self.role: Role = role

    def end_episode(self, episode_id: str) -> None:
        pass

    def act(self, obs: Observation) -> Action:
        if obs.expert is None:
            raise ValueError("the expert policy needs a run started with policy 'expert' (the world's plan is missing)")
        steps = obs.expert.steps
        k = obs.decision_index - 1
        if k >= len(steps):
            log.warning("%s %s#%d: the plan has only %d steps", obs.episode_id, obs.role, obs.decision_index, len(steps))
            return action_for(obs, "WAIT")
        step = steps[k]
        if abs(step.sim_time_s - obs.sim_time_s) > TIME_TOLERANCE_S or step.action not in obs.legal_actions:
            log.warning("%s %s#%d: the plan says %s at %.3f s, the world asks at %.3f s with %s legal",
                        obs.episode_id, obs.role, obs.decision_index, step.action, step.sim_time_s, obs.sim_time_s,
                        ", ".join(obs.legal_actions))
            return action_for(obs, "WAIT")
        return action_for(obs, step.action, waypoint_id=step.waypoint_id, cell=step.cell,
                          candidate_id=step.candidate_id, message=step.message)
