"""The dataset writer: the expert policy, with every decision written to disk as it is answered.

``agos agent --policy expert --dataset-out DIR`` serves :class:`DatasetWriter`. For each observation
it asks the expert for its action, then writes, under ``DIR/.partial/<episode>/a<attempt>/<role>/``:

- ``d<k>/``: the observation's images as the world rendered them (RGB, the UAV's grid overlay, depth
  and semantic PNGs, the map), and ``d<k>/passed/`` the views along the move that led here
  (``ExpertHints.passed``: every ``capture_every_m`` metres), the bytes as they came, never re-encoded;
- ``decisions.jsonl``: per decision, when and where, the legal actions, the expert's action, and each
  image file with its camera (intrinsics, world_from_camera, depth scale);
- ``export.jsonl``: per decision the fine-tuning example (example.py): AGOS-Agent's request at this
  point of the trajectory, its memory fed with the expert's earlier decisions, answered by the expert;
- ``expert.json`` (first decision): the role's script and trajectories (Tra_0, Tra, t_f, t_arr);
- ``references/``: the target's reference views.

Paths inside the files are relative to ``DIR`` and name where ``agos dataset build`` moves the episode
when its record is stored (``episodes/<episode>/<role>/...``). Everything of a decision is written
before the action is returned, so a stored record means every decision's files are on disk. A repeat
of an answered observation (the world re-sends it) gets the same action and writes nothing.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import threading
from pathlib import Path
from typing import Any

import msgspec

from agos.agents.contract import Policy
from agos.agents.dataset.example import chat_example, reply_json
from agos.agents.expert import ExpertPolicy
from agos.agents.vlm.agent import VlmAgent
from agos.runtime.schemas import Action, ImageFrame, Observation, Role
from agos.runtime.settings import VlmOptions

PARTIAL = ".partial"
EPISODES = "episodes"
EXTENSIONS = {"jpeg": "jpg", "png": "png"}
PROMPT_POLICY = "agos-agent"
"""Whose requests the examples carry: AGOS-Agent's (agents/vlm/agos_prompts.py)."""


def partial_dir(out_dir: Path, episode_id: str, attempt: int, role: Role) -> Path:
    """Where a role's files of one attempt are written until the episode is assembled."""
    return out_dir / PARTIAL / episode_id / f"a{attempt}" / role


def frame_file(frame: ImageFrame) -> str:
    """The file name of an observation frame: ``nadir.jpg``, ``nadir_grid.jpg``, ``front_depth.png`` ..."""
    suffix = {"rgb": "", "rgb_grid": "_grid", "map": ""}.get(frame.kind, f"_{frame.kind}")
    return f"{frame.name}{suffix}.{EXTENSIONS[frame.encoding]}"


class _Episode:
    """One role's files of one attempt of one episode."""

    def __init__(self, out_dir: Path, obs: Observation) -> None:
        self.dir = partial_dir(out_dir, obs.episode_id, obs.attempt, obs.role)
        self.rel = f"{EPISODES}/{obs.episode_id}/{obs.role}"
        if self.dir.exists():  # an earlier try of this attempt (a restarted agent): start it again
            shutil.rmtree(self.dir)
        self.dir.mkdir(parents=True)
        self.attempt = obs.attempt
        self.answered: dict[int, Action] = {}
        self.files_by_hash: dict[str, str] = {}
        """sha256 of bytes written -> their relative path (the request's images are found by bytes)."""

    def write(self, rel_in_role: str, data: bytes) -> str:
        path = self.dir / rel_in_role
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        rel = f"{self.rel}/{rel_in_role}"
        self.files_by_hash.setdefault(hashlib.sha256(data).hexdigest(), rel)
        return rel

    def append(self, name: str, line: dict[str, Any]) -> None:
        with (self.dir / name).open("a") as f:
            f.write(json.dumps(line, separators=(",", ":")) + "\n")


class DatasetWriter(Policy):
    """The expert policy of one role, writing each decision under ``out_dir`` (module docstring)."""

    name = "expert"

    def __init__(self, role: Role, out_dir: Path) -> None:
        self.role: Role = role
        self.out_dir = out_dir
        self.expert = ExpertPolicy(role)
        self.prompts = VlmAgent(role, PROMPT_POLICY, VlmOptions())  # builds requests; never asks a model
        self.episodes: dict[str, _Episode] = {}
        self.lock = threading.Lock()  # decisions of several episodes arrive on worker threads

    def end_episode(self, episode_id: str) -> None:
        with self.lock:
            self.episodes.pop(episode_id, None)
            self.prompts.end_episode(episode_id)
            self.expert.end_episode(episode_id)

    def act(self, obs: Observation) -> Action:
        with self.lock:
            ep = self.episodes.get(obs.episode_id)
            if ep is None or ep.attempt != obs.attempt:
                self.prompts.end_episode(obs.episode_id)
                ep = self.episodes[obs.episode_id] = _Episode(self.out_dir, obs)
            done = ep.answered.get(obs.decision_index)
            if done is not None:
                return done
            action = self.expert.act(obs)
            self._write_decision(ep, obs, action)
            ep.answered[obs.decision_index] = action
            return action

    def _write_decision(self, ep: _Episode, obs: Observation, action: Action) -> None:
        k = obs.decision_index
        if k == 1:
            if obs.expert is not None:
                plan = msgspec.to_builtins(msgspec.structs.replace(obs.expert, passed=[]))
                plan.pop("passed", None)
                (ep.dir / "expert.json").write_text(json.dumps({"episode_id": obs.episode_id, "role": obs.role,
                                                                **plan}, indent=1) + "\n")
            for ref in obs.references:
                ep.write(f"references/{frame_file(ref)}", ref.data)
        step = f"d{k:03d}"
        images = [_image_entry(ep.write(f"{step}/{frame_file(f)}", f.data), f) for f in obs.images]
        passed = []
        for n, view in enumerate(obs.expert.passed if obs.expert is not None else [], start=1):
            files = [_image_entry(ep.write(f"{step}/passed/{n:02d}_{frame_file(f)}", f.data), f) for f in view.images]
            passed.append({"sim_time_s": view.sim_time_s, "distance_m": view.distance_m,
                           "pose": msgspec.to_builtins(view.pose), "images": files})
        reply = json.loads(reply_json(action))
        ep.append("decisions.jsonl", {
            "episode_id": obs.episode_id, "role": obs.role, "decision_index": k, "sim_time_s": obs.sim_time_s,
            "mode": obs.mode, "pose": msgspec.to_builtins(obs.pose), "legal_actions": list(obs.legal_actions),
            "action": reply, "images": images, "passed": passed})

        def image_path(label: str, data: bytes, encoding: str) -> str:
            known = ep.files_by_hash.get(hashlib.sha256(data).hexdigest())
            return known or ep.write(f"{step}/request_{label}.{EXTENSIONS[encoding]}", data)

        prompt = self.prompts.prompt_for(obs)
        example = chat_example(prompt, action, image_path)
        ep.append("export.jsonl", {"id": f"{obs.episode_id}/{obs.role}/{k}", "episode_id": obs.episode_id,
                                   "role": obs.role, "decision_index": k, "stage": prompt.stage,
                                   "legal_actions": prompt.actions, **example})
        self.prompts.note_decision(obs, action)


def _image_entry(path: str, frame: ImageFrame) -> dict[str, Any]:
    entry: dict[str, Any] = {"name": frame.name, "kind": frame.kind, "path": path}
    if frame.intrinsics is not None:
        entry["intrinsics"] = msgspec.to_builtins(frame.intrinsics)
    if frame.world_from_camera is not None:
        entry["world_from_camera"] = frame.world_from_camera
    if frame.depth_scale_m is not None:
        entry["depth_scale_m"] = frame.depth_scale_m
    if frame.metres_per_px is not None:
        entry["metres_per_px"] = frame.metres_per_px
    return entry
