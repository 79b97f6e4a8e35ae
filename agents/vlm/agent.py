"""VLM policies: AGOS-Agent (and its ablations) and the Baseline, over an OpenAI-compatible endpoint.

One decision: build the role's prompt (stage-conditioned for AGOS-Agent), ask the model with the
legal actions as a JSON schema, parse and validate the reply into a legal action. A reply that
cannot be used is re-asked up to ``reasks`` times, telling the model what was wrong; after that, or
when the endpoint refuses the request, the decision becomes the fallback WAIT, logged with its
reason. An endpoint that gives no answer after its retries or before the world's decision timeout
(less a margin), or refuses the key, is no decision of the model:
:class:`~agos.agents.contract.EndpointOutage` is raised instead, and the agent service tells the
world, which pauses the episode (docs/AGENTS.md, "Outages are not the model's failures"). Every decision
carries a :class:`~agos.runtime.schemas.DecisionTrace` (prompt hash, image sizes, raw reply, parsed
action, fallback flag, latency, tokens, HTTP attempts and re-asks), which the world stores with the
episode. Retries and re-asks never add decisions.

The ablation variants (``agos-agent:no_e2a`` ...) use the same prompts; what changes is the tools
the world offers (the prompt follows from the legal actions and the options' hints).
"""

from __future__ import annotations

import asyncio
import copy
import json
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path

import msgspec
import numpy as np

from agos.agents.contract import EndpointOutage, FatalPolicyError, Policy
from agos.agents.names import split_name
from agos.agents.vlm import agos_prompts, baseline_prompts
from agos.agents.vlm.cache import ReplyCache
from agos.agents.vlm.client import CallTag, VlmClient, VlmError, image_part
from agos.agents.vlm.images import as_sent
from agos.agents.vlm.parse import Parsed, to_action
from agos.agents.vlm.protocol import action_schema
from agos.agents.vlm.request import Memory, Prompt, uncovered
from agos.runtime.codec import encode_png
from agos.runtime.schemas import Action, DecisionTrace, Observation, Role
from agos.runtime.settings import VlmOptions

log = logging.getLogger("agos.agent.vlm")
logging.getLogger("httpx").setLevel(logging.WARNING)  # one INFO line per request drowns the agent log
RAW_REPLY_CHARS = 2000
UAV_AT_WAYPOINT_M = 1.0
MAX_IMAGES = {("uav", "all"): 8, ("ugv", "all"): 12, ("uav", "view_only"): 2, ("ugv", "view_only"): 7}
"""Most images one request of a role carries: UAV view + map + 5 references + the teammate's top view;
UGV six panels + map + 5 references. ``view_only``: the view(s) and the top reference."""

ANSWER_MARGIN_S = 5.0
"""A decision's model calls stop this long before the world's decision timeout (at most a quarter of
it), so that an endpoint that does not answer in time is reported as an outage before the world
would apply its WAIT for a missing answer."""

PROBE_PX = 64
"""Side of the preflight's probe images: some VLM image processors refuse images under 28-32 px."""

Builder = Callable[..., Prompt]
BUILDERS: dict[tuple[str, Role], Builder] = {
    ("agos-agent", "uav"): agos_prompts.uav_prompt,
    ("agos-agent", "ugv"): agos_prompts.ugv_prompt,
    ("baseline", "uav"): baseline_prompts.uav_prompt,
    ("baseline", "ugv"): baseline_prompts.ugv_prompt,
}


class VlmAgent(Policy):
    """A policy whose decisions come from a vision-language model (see the module docstring)."""

    def __init__(self, role: Role, name: str, options: VlmOptions, *, client: VlmClient | None = None) -> None:
        base, _ = split_name(name)
        self.role, self.name, self.base = role, name, base
        self.options = options
        self.build = BUILDERS[(base, role)]
        self._client = client
        self._memory: dict[str, Memory] = {}
        self._answers: dict[str, dict[int, asyncio.Future[Action]]] = {}
        """Per episode: the decision being answered (or answered last), for repeated requests."""
        self._trace_path: Path | None = options.trace_file
        self._cache: ReplyCache | None = None
        if options.cache_dir is not None and options.cache_mode != "off":  # a bad cache fails here, before serving
            self._cache = ReplyCache(options.cache_dir, options.cache_mode)

    # ----- lifecycle --------------------------------------------------------------------------
    def _new_client(self, **overrides: object) -> VlmClient:
        o = self.options
        kw: dict = {"api_key_env": o.api_key_env, "timeout_s": o.timeout_s, "max_retries": o.max_retries,
                    "concurrency": o.concurrency, "structured": o.structured, "max_tokens": o.max_tokens, **overrides}
        return VlmClient(o.base_url or "", str(o.model), **kw)  # no base URL: a replay, which sends nothing

    def client(self) -> VlmClient:
        """The client decisions ask through (with the cache of ``--vlm-cache``; the preflight's has none)."""
        if self._client is None:
            self._client = self._new_client(cache=self._cache)
        return self._client

    async def aclose(self) -> None:
        if self._client is not None:
            await self._client.close()
            self._client = None

    async def preflight(self) -> list[str]:
        """Before serving: the endpoint is up, serves the model, and accepts this role's largest request
        (as many images as a six-view decision sends). Raises VlmError saying what to change.
        A replay asks nothing: the cache must hold calls of the model."""
        o = self.options
        if self._cache is not None and self._cache.mode == "replay":
            models = self._cache.models()
            if o.model not in models:
                raise VlmError(f"--vlm-cache {o.cache_dir} holds no call of model {o.model!r} to replay "
                               f"(it holds: {', '.join(models) or 'nothing'})")
            return models
        client = self._new_client(max_retries=min(o.max_retries, 2), max_tokens=32)
        try:
            models = await client.preflight()
            n = MAX_IMAGES[(self.role, o.images)]
            probe = encode_png(np.full((PROBE_PX, PROBE_PX, 3), 128, np.uint8))
            parts: list[dict] = [{"type": "text", "text": "Connectivity check: reply with {\"action\": \"WAIT\"}."}]
            parts += [image_part(probe, "png") for _ in range(n)]
            try:
                await client.complete([{"role": "user", "content": parts}], schema=action_schema(["WAIT"]))
            except VlmError as exc:
                raise VlmError(
                    f"{exc}\n{o.base_url} refused a request like a {self.role} decision ({n} images"
                    + (", a JSON-schema response_format" if o.structured else "") + "). For vLLM, start the server with "
                    f"--limit-mm-per-prompt '{{\"image\": {n}}}'; or send fewer images with [vlm] images = \"view_only\" "
                    "(AGOS_VLM__IMAGES=view_only)" + ("; if the server rejects response_format, add --vlm-no-structured"
                                                     if o.structured else "") + ".") from None
            return models
        finally:
            await client.close()

    def end_episode(self, episode_id: str) -> None:
        self._memory.pop(episode_id, None)
        self._answers.pop(episode_id, None)
        if self._cache is not None:  # a re-leased attempt replays its calls from the stream's start
            self._cache.forget(episode_id, self.role)

    def act(self, obs: Observation) -> Action:
        """Synchronous use (in-process runners): one event loop and one HTTP client per call."""

        async def once() -> Action:
            try:
                return await self.act_async(obs)
            finally:
                await self.aclose()

        return asyncio.run(once())

    # ----- one decision -----------------------------------------------------------------------
    async def act_async(self, obs: Observation) -> Action:
        """The action for ``obs``. The world re-sends an unanswered observation every few seconds (a
        slow model is normal): a repeat of a decision in progress waits for the same answer, and a
        repeat of an answered one gets that answer again, so the model is asked once per decision and
        memory is updated once."""
        answers = self._answers.setdefault(obs.episode_id, {})
        pending = answers.get(obs.decision_index)
        if pending is not None and pending.done():
            return copy.deepcopy(pending.result())
        if pending is None or pending.get_loop() is not asyncio.get_running_loop():
            pending = asyncio.ensure_future(self._decide_safely(obs))
            for old in [k for k in answers if k < obs.decision_index]:
                del answers[old]  # only the latest decision of an episode can be asked again
            answers[obs.decision_index] = pending
        action = await asyncio.shield(pending)
        return copy.deepcopy(action)

    async def _decide_safely(self, obs: Observation) -> Action:
        try:
            return await self._decide(obs)
        except (FatalPolicyError, EndpointOutage):  # a replay without the recorded reply: the service stops;
            raise  # an endpoint that gave no answer: the world pauses the episode
        except Exception as exc:  # a bug or an unforeseen reply shape costs a decision, never the episode
            log.exception("%s %s #%d: decision failed; fallback WAIT", obs.episode_id, self.role, obs.decision_index)
            action = to_action(None, obs).action
            action.trace = DecisionTrace(
                policy=self.name, model=str(self.options.model), stage="unknown", prompt_sha256="", image_bytes={},
                raw_reply=None, parsed_action=action.action, fallback=True,
                fallback_reason=f"agent error: {type(exc).__name__}: {exc}"[:300], error=type(exc).__name__)
            return action

    def prompt_for(self, obs: Observation) -> Prompt:
        """The request for ``obs``, after updating the episode's memory with where the role is now:
        what the model is sent at this decision. Call :meth:`note_decision` with the answer."""
        memory = self._memory.setdefault(obs.episode_id, Memory())
        self._locate(obs, memory)
        sent = as_sent(obs, self.options.image_max_px, self.options.jpeg_quality)  # [vlm] image size and encoding
        return self.build(sent, memory, images=self.options.images)

    def note_decision(self, obs: Observation, action: Action) -> None:
        """Remember the decision taken at ``obs`` (the memory the next prompts show). The dataset's
        export replays the expert's decisions through this and :meth:`prompt_for`, so its prompts are
        the ones this agent would have been sent on the same trajectory (agents/dataset/)."""
        self._remember(obs, self._memory.setdefault(obs.episode_id, Memory()), action)

    async def _decide(self, obs: Observation) -> Action:
        prompt = self.prompt_for(obs)
        schema = action_schema(prompt.actions)
        messages = prompt.messages()
        attempts = reasks = prompt_tokens = completion_tokens = request_bytes = reply_bytes = 0
        latency = 0.0
        raw: str | None = None
        error: str | None = None
        parsed: Parsed | None = None
        call = CallTag(obs.episode_id, self.role, obs.decision_index)
        deadline = _deadline(obs.decision_timeout_s)
        for ask in range(self.options.reasks + 1):
            try:
                reply = await self.client().complete(messages, schema=schema, call=call, deadline=deadline)
            except VlmError as exc:
                if exc.outage:  # not the model's decision: nothing is answered, the episode pauses
                    raise EndpointOutage(str(exc)) from None
                error = str(exc)
                attempts += exc.attempts
                break
            attempts += reply.attempts
            latency += reply.latency_s
            request_bytes += reply.request_bytes
            reply_bytes += reply.reply_bytes
            prompt_tokens += reply.prompt_tokens or 0
            completion_tokens += reply.completion_tokens or 0
            raw = reply.text
            parsed = to_action(reply.text, obs, truncated=reply.finish_reason == "length")
            if not parsed.fallback:
                break
            if ask < self.options.reasks:
                reasks += 1
                messages = [*messages, {"role": "assistant", "content": reply.text or ""},
                            {"role": "user", "content": _reask_text(parsed.reason, prompt.actions)}]
        if parsed is None or parsed.fallback:
            reason = f"no answer from the model: {error}" if parsed is None else str(parsed.reason)
            parsed = to_action(None, obs) if parsed is None else parsed
            log.warning("%s %s #%d: fallback %s (%s)", obs.episode_id, self.role, obs.decision_index,
                        parsed.action.action, reason)
        else:
            reason = None
        action = parsed.action
        action.trace = DecisionTrace(
            policy=self.name, model=str(self.options.model), stage=prompt.stage, prompt_sha256=prompt.sha256(),
            image_bytes=prompt.image_bytes, raw_reply=None if raw is None else raw[:RAW_REPLY_CHARS],
            parsed_action=action.action, fallback=reason is not None, fallback_reason=reason, repaired=parsed.repaired,
            reasks=reasks, http_attempts=attempts, latency_s=round(latency, 4), request_bytes=request_bytes,
            reply_bytes=reply_bytes, prompt_tokens=prompt_tokens or None,
            completion_tokens=completion_tokens or None, error=error)
        self.note_decision(obs, action)
        if self._trace_path is not None:
            self._append_trace(obs, action)
        return action

    # ----- memory -----------------------------------------------------------------------------
    def _locate(self, obs: Observation, memory: Memory) -> None:
        here = (float(obs.pose.position_world_m[0]), float(obs.pose.position_world_m[1]))
        if self.role == "uav":
            memory.seen_from(here)
            if obs.active_uav_waypoints and not uncovered(obs, memory):
                memory.visited_xy = [here]  # everything covered once: a second sweep starts here
            node = next((w for w in obs.active_uav_waypoints
                         if math.dist(w.position_world_m[:2], here) <= UAV_AT_WAYPOINT_M), None)
            memory.at(node.waypoint_id if node else None)

    def _remember(self, obs: Observation, memory: Memory, action: Action) -> None:
        detail = action.waypoint_id or action.cell or action.candidate_id or ""
        memory.note(obs.decision_index, action.action, detail)
        here = (round(obs.pose.position_world_m[0], 1), round(obs.pose.position_world_m[1], 1))
        if action.action == "WAIT" and memory.last_position == here:
            memory.waits_here += 1
        elif action.action == "WAIT":
            memory.waits_here = 1
        else:
            memory.waits_here = 0
        memory.last_position = here
        if action.action == "MOVE_TO_ROAD_WAYPOINT":
            memory.at(action.waypoint_id)
        if self.base == "baseline" and self.role == "ugv" and action.action == "REJECT":
            anchor = baseline_prompts.anchor_from_messages(obs, memory)
            memory.inspected_anchors.append(anchor if anchor is not None else here)

    def _append_trace(self, obs: Observation, action: Action) -> None:
        assert action.trace is not None and self._trace_path is not None
        line = {"run_id": obs.run_id, "episode_id": obs.episode_id, "role": self.role,
                "decision_index": obs.decision_index, **msgspec.structs.asdict(action.trace)}
        self._trace_path.parent.mkdir(parents=True, exist_ok=True)
        with self._trace_path.open("a") as f:
            f.write(json.dumps(line) + "\n")


def _deadline(decision_timeout_s: float | None) -> float | None:
    """When a decision's model calls must have an answer (``time.monotonic()``): the world's decision
    timeout from now, less :data:`ANSWER_MARGIN_S`; None where no world said (in-process runners)."""
    if decision_timeout_s is None:
        return None
    return time.monotonic() + decision_timeout_s - min(ANSWER_MARGIN_S, decision_timeout_s / 4)


def _reask_text(reason: str | None, actions: list[str]) -> str:
    return (f"Your last reply could not be used: {reason}. Answer again with exactly one JSON object, no other "
            f"text. The action must be one of: {', '.join(actions)}; use only ids listed in the state.")
