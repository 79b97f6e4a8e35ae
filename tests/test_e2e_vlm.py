"""The VLM path end to end: real agent processes asking the real stand-in HTTP server, over a real
router, with injected faults; and ``agos check agent`` against attached services.

"DS is unchanged by retries": each policy's run with faults is compared, decision for decision,
with the same episode run in-process against a fault-free stand-in (the stand-in's answers are a
deterministic function of the request). Those runs record their model calls (``--vlm-cache``), and
AGOS-Agent's is replayed with its endpoint gone: the same records, no HTTP request.
"""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import msgspec
import pytest

from agos import Env
from agos.agents.names import tools_for
from agos.agents.registry import make_policy
from agos.agents.vlm.cache import cache_stats
from agos.agents.vlm.standin.server import StandinServer
from agos.deploy.run.launcher import free_port, wait_listening
from agos.runtime.episode_config import EpisodeConfig, ToolConfig
from agos.runtime.settings import VlmOptions
from agos.world.episodes.sampling import read_episodes, write_episodes
from agos.world.sim.scene import Scene
from agos.world.towns.asset import open_town

pytestmark = pytest.mark.e2e
AGOS = [sys.executable, "-m", "agos.deploy.cli"]
POLICIES = ["agos-agent", "baseline"]
# The ablations differ from agos-agent only in the policy's name and the configuration's tools, which
# cross the bus in the job grant as the baseline's switched-off candidates do here; in-process,
# tests/test_tools_and_policies.py covers no_e2a, no_rgpp and no_both one by one.
FAULTS = "429=0.15,500=0.1,timeout=0.02,fenced=0.3"


@pytest.fixture(scope="module")
def episode_file(sample_mid_episodes) -> Path:
    return sample_mid_episodes(1, seed=3)


@pytest.fixture(scope="module")
def reference(episode_file) -> dict[str, dict]:
    """Each policy's episode in-process against a fault-free stand-in server: the expected record."""
    spec = read_episodes(episode_file)[0]
    town = open_town(spec.town.town_id)
    scene = Scene(town.layout, look=EpisodeConfig().look)  # as agos eval runs it: the default look
    out = {}
    with StandinServer() as server:
        options = VlmOptions(base_url=server.url, model="agos-standin")
        for policy in POLICIES:
            tools = tools_for({"uav": policy, "ugv": policy})
            config = EpisodeConfig(tools=ToolConfig(candidates=tools["candidates"], e2a=tools["e2a"], rgpp=tools["rgpp"]))
            with Env(spec, config, illegal="wait", run_id="ref", worker_id="w", scene=scene, town=town) as env:
                record = env.play({r: make_policy(policy, r, vlm=options) for r in ("uav", "ugv")})
            out[policy] = msgspec.to_builtins(record)
    scene.close()
    return out


@pytest.fixture(scope="module")
def faulty_run(episode_file, tmp_path_factory) -> Callable[[str], Path]:
    """``faulty_run(policy)``: the run directory of ``agos eval`` of the episode with ``policy`` over a
    stand-in injecting FAULTS that the run starts (and stops) itself, its model calls recorded in
    ``<run>/../cache``; run once per policy."""
    runs: dict[str, Path] = {}

    def run(policy: str) -> Path:
        if policy not in runs:
            tmp = tmp_path_factory.mktemp(f"faulty-{policy}")
            proc = subprocess.run([*AGOS, "eval", "--split", str(episode_file), "--policy", policy, "--vlm-standin",
                                   FAULTS, "--vlm-cache", str(tmp / "cache"), "--run-dir", str(tmp / "run"),
                                   "--port", str(free_port(21000 + os.getpid() % 400))],
                                  cwd=tmp, capture_output=True, text=True, timeout=400)
            assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
            runs[policy] = tmp / "run"
        return runs[policy]

    return run


def _records(run_dir: Path) -> list[dict]:
    with sqlite3.connect(run_dir / "results.sqlite") as db:
        return [json.loads(r) for (r,) in db.execute("SELECT record_json FROM episodes")]


def _actions(record: dict) -> list[tuple]:
    return [(t["role"], t["decision_index"], t["parsed_action"]) for t in record["decision_traces"]]


@pytest.mark.parametrize("policy", POLICIES)
def test_policy_completes_over_the_standin_with_faults_and_retries_do_not_change_ds(policy, faulty_run,
                                                                                    reference) -> None:
    run_dir = faulty_run(policy)
    [record] = _records(run_dir)
    ref = reference[policy]
    assert record["status"] == "finished"
    ds, ref_ds = record["decisions_uav"] + record["decisions_ugv"], ref["decisions_uav"] + ref["decisions_ugv"]
    assert ds == ref_ds, (policy, ds, ref_ds)
    assert _actions(record) == _actions(ref)
    assert record["termination"] == ref["termination"]
    stats = record["agent_stats"]
    decisions = sum(s["decisions"] for s in stats.values())
    assert decisions == ds  # one trace per logical decision
    assert sum(s["http_attempts"] for s in stats.values()) > decisions  # faults were injected and retried
    assert sum(s["fallbacks"] for s in stats.values()) == 0
    assert all(t["prompt_sha256"] and t["image_bytes"] and t["raw_reply"] for t in record["decision_traces"])
    if policy == "baseline":
        assert record["candidates"] == []  # no candidate tools
    else:
        assert record["candidates"], "AGOS-Agent hands off through candidates"
    log = (run_dir / "logs" / "vlm-standin.log").read_text()
    assert "listening on http://127.0.0.1:" in log


WALL_CLOCK = ("run_id", "wall_time_s")
"""What a replay may change in a record: the run's name and the episode's wall time."""


def test_a_recorded_run_replays_with_its_endpoint_off_to_the_same_records(faulty_run, episode_file, tmp_path,
                                                                         agos) -> None:
    recorded = faulty_run("agos-agent")  # its stand-in, started and stopped by that run, is gone
    cache = recorded.parent / "cache"
    with StandinServer(faults={"500": 1.0}) as off:  # an endpoint that answers nothing and counts what reaches it
        proc = subprocess.run([*AGOS, "eval", "--split", str(episode_file), "--policy", "agos-agent",
                               "--vlm-base-url", off.url, "--model", "agos-standin", "--vlm-cache", str(cache),
                               "--vlm-cache-mode", "replay", "--run-dir", str(tmp_path / "replay"),
                               "--port", str(free_port(21400 + os.getpid() % 400))],
                              cwd=tmp_path, capture_output=True, text=True, timeout=400)
        assert off.stats()["requests"] == 0
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "VLM calls replayed from" in proc.stdout
    [before], [after] = _records(recorded), _records(tmp_path / "replay")
    stats = before["agent_stats"]
    assert sum(s["http_attempts"] for s in stats.values()) > sum(s["decisions"] for s in stats.values())  # faults
    assert {k: v for k, v in after.items() if k not in WALL_CLOCK} == {k: v for k, v in before.items()
                                                                        if k not in WALL_CLOCK}
    metrics = [agos("metrics", run, "--json") for run in (recorded, tmp_path / "replay")]
    assert all(m.returncode == 0 for m in metrics)
    recorded_metrics, replayed_metrics = (_not_wall_clock(json.loads(m.stdout)) for m in metrics)
    assert replayed_metrics == recorded_metrics and recorded_metrics["overall"]["prompt_tokens"] > 0
    calls = sum(1 + t["reasks"] for t in before["decision_traces"])
    [model] = cache_stats(cache).models  # every call asked once when recorded, served once when replayed
    assert (model.model, model.misses, model.hits, model.replies, model.errors) == ("agos-standin", calls, calls, calls, 0)


def _not_wall_clock(metrics: dict[str, dict]) -> dict[str, dict]:
    """``agos metrics --json`` without the decisions' wall-clock latency (a replay answers at CPU speed)."""
    return {group: {k: v for k, v in values.items() if not k.startswith("latency_")} for group, values in metrics.items()}


def test_a_cost_cap_stops_the_run_and_resume_completes_it(episode_file, tmp_path, agos) -> None:
    """Issue 31 (c): a cost cap the first episode already reaches stops the run once that episode is stored
    (one console line, exit 5), ``--resume`` with the cap lifted plays the other, and ``agos report`` shows
    the run card, tokens, cost, cost per success, latency and SR intervals. Two episodes of 3 decisions:
    the module's episode and a copy of it under another id."""
    [spec] = read_episodes(episode_file)
    split = tmp_path / "two.jsonl"
    write_episodes(split, [spec, msgspec.structs.replace(spec, episode_id=spec.episode_id + "-copy")])
    run_dir = tmp_path / "run"
    env = {**os.environ, "AGOS_WORLD__DECISION_BUDGET": "3"}
    port = str(free_port(22400 + os.getpid() % 400))
    capped = subprocess.run([*AGOS, "eval", "--split", str(split), "--policy", "agos-agent", "--vlm-standin",
                             "--max-cost-usd", "0.000001", "--price-in", "1", "--price-out", "4", "--run-dir",
                             str(run_dir), "--port", port], cwd=tmp_path, env=env, capture_output=True, text=True,
                            timeout=300)
    assert capped.returncode == 5, capped.stdout[-3000:] + capped.stderr[-3000:]
    [line] = [x for x in capped.stdout.splitlines() if x.startswith("stopping:")]
    assert "reaching --max-cost-usd 1e-06" in line and "1 of 2 episodes not run" in line
    assert f"agos eval --resume {run_dir} --max-cost-usd N (or none)" in line
    assert [r["status"] for r in _records(run_dir)] == ["finished"]
    done = subprocess.run([*AGOS, "eval", "--resume", str(run_dir), "--max-cost-usd", "none", "--port", port],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    records = _records(run_dir)
    assert sorted(r["status"] for r in records) == ["finished", "finished"]
    assert all(r["usage"][0]["model"] == "agos-standin" and r["usage"][0]["prompt_tokens"] > 0 for r in records)
    assert "model calls: " in done.stdout and "at * $1/$4 per M tokens" in done.stdout
    meta = json.loads((run_dir / "run.json").read_text())
    assert meta["caps"]["max_cost_usd"] is None and meta["resumes"][0]["caps"]["max_cost_usd"] is None
    assert meta["card"]["models_answer"][0]["id"] == "agos-standin"
    report = agos("report", run_dir, "--out", tmp_path / "report")
    assert report.returncode == 0, report.stderr
    out = report.stdout
    assert out.index("prompts: sha256") < out.index("success rate")  # the card above the tables
    for part in ("/models: agos-standin", "sampling: temperature 0.0", "commit ", "prices: * $1/$4", "% [95% CI]",
                 "tokens, cost and latency per decision"):
        assert part in out, part
    assert "| USD/success | p50 latency s | p95 latency s |" in (tmp_path / "report" / "cost.md").read_text()
    with open(tmp_path / "report" / "cost.csv", newline="") as fh:
        total = next(r for r in csv.DictReader(fh) if r["Difficulty"] == "total")
    tokens = sum(u["prompt_tokens"] for r in records for u in r["usage"])
    assert total["episodes"] == "2" and total["prompt tok"] == f"{tokens:,}"
    assert float(total["cost USD"]) > 0 and float(total["p95 latency s"]) > 0
    assert total["USD/success"] == "--"  # 3 decisions find nothing: undefined, never 0 (tests/test_cost.py pins the math)


def test_an_outage_window_pauses_episodes_and_resume_finishes_them(episode_file, tmp_path, agos) -> None:
    """Issue 31 (a): the endpoint fails every chat request for a window (12 HTTP 500s after the agents'
    two preflight probes; one retry per call), then answers again. Episode a loses both its attempts
    (4 requests each: both roles at decision 1) and is stored as infra_error; b loses its first and
    finishes on its second, fresh attempt. No episode is scored as a failure, the console says what
    happened, eval exits 6, and --resume plays a, whose record equals b's (a re-leased attempt is an
    undisturbed run). The calls are recorded (--vlm-cache): the failed ones are asked again, none stays."""
    [spec] = read_episodes(episode_file)
    split = tmp_path / "two.jsonl"
    write_episodes(split, [spec, msgspec.structs.replace(spec, episode_id=spec.episode_id + "-copy")])
    a, b = spec.episode_id, spec.episode_id + "-copy"
    run_dir, cache = tmp_path / "run", tmp_path / "cache"
    env = {**os.environ, "AGOS_WORLD__DECISION_BUDGET": "3", "AGOS_VLM__MAX_RETRIES": "1",
           "AGOS_RUN__MAX_INFRA_ATTEMPTS": "2", "AGOS_RUN__INFRA_WAIT_S": "1"}
    port = str(free_port(22800 + os.getpid() % 400))
    with StandinServer(script=("ok", "ok", *("500",) * 12)) as server:
        first = subprocess.run([*AGOS, "eval", "--split", str(split), "--policy", "agos-agent", "--vlm-base-url",
                                server.url, "--model", "agos-standin", "--vlm-cache", str(cache), "--run-dir",
                                str(run_dir), "--port", port], cwd=tmp_path, env=env, capture_output=True, text=True,
                               timeout=300)
        assert first.returncode == 6, first.stdout[-3000:] + first.stderr[-3000:]
        out = " ".join(first.stdout.split())  # the console wraps long lines at its width
        assert re.search(rf"model endpoint outage: U[AG]V agent: {re.escape(server.url)}: no answer after 2 attempts "
                         rf"\(HTTP 500\) \(episode {re.escape(a)}, attempt 1\); 1 episode waits, leased again in 1 s as a "
                         rf"fresh attempt \(1 of 2 attempts lost\)", out), out
        assert f"{a}: stored as infra_error after 2 attempts without an answer from the model endpoint" in out
        assert f"model endpoint answers again: {b} (attempt 2) decided" in out
        assert ("1 episode stored as infra_error (not scored; the model endpoint gave no answer in 2 attempts" in out
                and f"play it again once the endpoint answers: agos eval --resume {run_dir}" in out)
        records = {r["episode_id"]: r for r in _records(run_dir)}
        assert (records[a]["status"], records[b]["status"]) == ("infra_error", "finished")
        metrics = agos("metrics", run_dir, "--json")
        assert metrics.returncode == 0, metrics.stderr
        overall = json.loads(metrics.stdout)["overall"]
        assert (overall["n"], overall["not_scored"], overall["infra_error"]) == (1, 1, 1)  # a is nobody's failure
        assert server.stats()["outcomes"]["500"] == 12
        done = subprocess.run([*AGOS, "eval", "--resume", str(run_dir), "--vlm-cache", str(cache), "--port", port],
                              cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    records = {r["episode_id"]: r for r in _records(run_dir)}
    assert [records[e]["status"] for e in (a, b)] == ["finished", "finished"]
    assert _played(records[a]) == _played(records[b])
    assert sum(m.errors for m in cache_stats(cache).models) == 0  # every unanswered call was asked again


def _played(record: dict) -> dict:
    """What a played episode's record says about the play: outcome, counts, trajectories, each decision's
    action and tokens (not its HTTP attempts or wall-clock latency)."""
    keep = ("status", "termination", "success", "decisions_uav", "decisions_ugv", "fallbacks", "step_log", "candidates",
            "sim_time_s")
    traces = [(t["role"], t["decision_index"], t["parsed_action"], t["prompt_tokens"], t["completion_tokens"])
              for t in record["decision_traces"]]
    return {**{k: record[k] for k in keep}, "traces": traces}


def _start(tmp: Path, name: str, *args: str) -> subprocess.Popen:
    log = (tmp / f"{name}.log").open("ab")
    return subprocess.Popen([*AGOS, *args], cwd=tmp, stdout=log, stderr=subprocess.STDOUT)


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()


def test_check_agent_names_a_missing_role_then_passes_with_remote_vlm_agents(tmp_path) -> None:
    port = free_port(22000 + os.getpid() % 400)
    endpoint = f"tcp/127.0.0.1:{port}"
    procs = [_start(tmp_path, "router", "router", "--listen", endpoint)]
    try:
        assert wait_listening("127.0.0.1", port, 15.0)
        with StandinServer() as server:
            attach = ["--connect", endpoint, "--run", "remote", "--policy", "agos-agent", "--vlm-base-url", server.url,
                      "--model", "agos-standin"]
            procs.append(_start(tmp_path, "agent-uav", "agent", "--role", "uav", *attach))
            check = [*AGOS, "check", "agent", "--connect", endpoint, "--run", "remote", "--budget", "12"]
            missing = subprocess.run([*check, "--agent-wait", "4"], cwd=tmp_path, capture_output=True, text=True,
                                     timeout=120)
            assert missing.returncode == 1, missing.stdout
            assert "no UGV agent service" in missing.stdout and "FAIL" in missing.stdout
            procs.append(_start(tmp_path, "agent-ugv", "agent", "--role", "ugv", *attach))
            ok = subprocess.run(check, cwd=tmp_path, capture_output=True, text=True, timeout=300)
            assert ok.returncode == 0, ok.stdout + ok.stderr
            assert "PASS" in ok.stdout and "uav:" in ok.stdout and "ugv:" in ok.stdout
            assert server.stats()["requests"] > 0
    finally:
        _stop(procs)


def test_agent_preflight_fails_clearly_when_the_model_is_missing(tmp_path) -> None:
    with StandinServer(models=("other-model",)) as server:
        proc = subprocess.run([*AGOS, "agent", "--role", "uav", "--policy", "agos-agent", "--vlm-base-url", server.url,
                               "--model", "agos-standin", "--connect", "tcp/127.0.0.1:1", "--run", "x"],
                              cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 3
    assert "agos-standin" in proc.stderr and "not served" in proc.stderr
