"""A policy of one's own (docs/AGENTS.md, "Write your own agent"): the Policy contract's defaults,
``package.module:Class`` names, the ``agos.policies`` entry points, their one-line errors, and the
example (examples/my_policy.py) playing an episode in-process. Its run through ``agos eval`` and
``agos check agent`` as remote processes is tests/test_e2e_own_policy.py."""

from __future__ import annotations

import asyncio
import re
import sys
from pathlib import Path

import pytest

from agos.agents.contract import Policy, action_for
from agos.agents.names import registered_names, split_name, tools_for
from agos.agents.registry import locate_policy, make_policy, policy_class
from agos.runtime.schemas import Action, CoordinationState, Observation, Pose, Waypoint

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = "examples.my_policy:Explorer"


@pytest.fixture
def repo_on_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """The repository root on ``sys.path`` (as when running from it), and the example not yet imported."""
    monkeypatch.syspath_prepend(str(REPO))
    monkeypatch.delitem(sys.modules, "examples.my_policy", raising=False)


def _obs(role: str = "uav", episode: str = "e1", options: tuple[str, ...] = ("U1", "U2")) -> Observation:
    return Observation(
        run_id="r", episode_id=episode, role=role, decision_index=1, sim_time_s=0.0,  # type: ignore[arg-type]
        pose=Pose(position_world_m=(0.0, 0.0, 80.0), yaw_rad=0.0), mode="aerial", images=[], references=[],
        legal_actions=["MOVE_TO_UAV_WAYPOINT", "WAIT"],
        waypoint_options=[Waypoint(waypoint_id=w, position_world_m=(40.0, 0.0, 80.0), kind="uav_grid") for w in options],
        region_world_m=(0.0, 0.0, 100.0, 100.0),
        coordination=CoordinationState(run_id="r", episode_id=episode, sim_time_s=0.0))


def test_the_contract_gives_each_method_a_default_and_refuses_a_policy_that_cannot_act() -> None:
    class Sync(Policy):
        def act(self, obs: Observation) -> Action:
            return action_for(obs, "WAIT", rationale="sync")

    class Async(Policy):
        name = "remote-model"

        async def act_async(self, obs: Observation) -> Action:
            await asyncio.sleep(0)
            return action_for(obs, "WAIT", rationale="async")

    sync, remote = Sync("uav"), Async("ugv")
    assert (sync.name, sync.role, sync.inline, remote.name, remote.role) == ("Sync", "uav", False, "remote-model", "ugv")
    assert asyncio.run(sync.act_async(_obs())).rationale == "sync"  # act in the loop's executor
    assert remote.act(_obs()).rationale == "async"  # act_async on a loop of its own
    assert asyncio.run(sync.preflight()) is None and sync.end_episode("e1") is None
    with pytest.raises(TypeError, match="must define act"):
        class Mute(Policy):  # neither act nor act_async
            name = "mute"


def test_the_example_plays_an_episode_in_process(repo_on_path: None) -> None:
    """``make_policy("examples.my_policy:Explorer", role)`` in this process: every decision legal and
    with valid arguments (no fallback), the budget spent, the memory of the episode dropped when told."""
    from agos import Env
    from agos.runtime.episode_config import EpisodeConfig
    from agos.world.episodes.sampling import generate_episodes
    from agos.world.sim.scene import Scene
    from agos.world.towns.asset import open_town

    assert tools_for({"uav": EXAMPLE, "ugv": EXAMPLE}) == {"candidates": True, "e2a": True, "rgpp": True,
                                                           "oracle": False, "expert": False}
    assert "examples.my_policy" not in sys.modules  # names are checked without importing the policy
    policies = {role: make_policy(EXAMPLE, role) for role in ("uav", "ugv")}
    assert [(type(p).__name__, p.name, p.role, p.inline) for p in policies.values()] == [
        ("Explorer", "explorer", "uav", True), ("Explorer", "explorer", "ugv", True)]
    town = open_town("grid-s7")
    with Scene(town.layout, look="flat") as scene:
        spec = generate_episodes(town, scene, per_difficulty=1, seed=1, difficulties=("easy",))[0]
        with Env(spec, EpisodeConfig(look="flat", decision_budget=10), run_id="t", worker_id="w", scene=scene,
                 town=town) as env:  # illegal="raise": an action without valid arguments fails here
            observations = env.reset()
            while observations:  # Env.play would tell the policies the end before the visits are counted
                observations = env.step({r: policies[r].act(o) for r, o in observations.items()}).observations
            record = env.record
    assert (record.status, record.termination, record.fallbacks) == ("finished", "budget_exhausted", 0)
    assert record.decisions_uav + record.decisions_ugv == 10 and record.ugv_path_length_m > 0
    ugv = policies["ugv"]
    assert sum(ugv.visits[spec.episode_id].values()) == record.decisions_ugv  # type: ignore[attr-defined]
    ugv.end_episode(spec.episode_id)
    assert spec.episode_id not in ugv.visits  # type: ignore[attr-defined]


def test_a_policy_class_that_cannot_be_found_is_one_line(repo_on_path: None) -> None:
    locate_policy(EXAMPLE)  # found without being imported
    assert "examples.my_policy" not in sys.modules
    cases = {
        "examples.nope:Explorer": "no module 'examples.nope' on the Python path or in the current folder",
        "nopkg.agent:Explorer": "no module 'nopkg'",
        "examples.my_policy:Nope": "module 'examples.my_policy' (",
        "agos.agents.contract:action_for": "action_for is not a subclass of agos.agents.contract.Policy",
        "examples.my_policy:": "a policy class is named package.module:Class",
        "examples.my-policy:Explorer": "a policy class is named package.module:Class",
    }
    for name, message in cases.items():
        with pytest.raises(ValueError, match=re.escape(message)) as caught:
            make_policy(name, "uav")
        assert "\n" not in str(caught.value), name
    with pytest.raises(ValueError, match=r"unknown policy 'heurstic'; known: heuristic.*or your own as package\.module:Class"):
        make_policy("heurstic", "uav")
    assert split_name("heuristic:no_rgpp") == ("heuristic", "no_rgpp")  # a variant, not a class
    with pytest.raises(ValueError, match=re.escape("no module 'examples.nope'")):
        locate_policy("examples.nope:Explorer")


def test_a_module_of_the_current_folder_is_found_through_the_agos_script(tmp_path: Path, monkeypatch) -> None:
    """The ``agos`` script's ``sys.path`` starts at its own folder, not the current one: the registry
    looks there too, after the installed packages."""
    (tmp_path / "here_policy.py").write_text(
        "from agos.agents.contract import Policy, action_for\n\n\n"
        "class Here(Policy):\n    def act(self, obs):\n        return action_for(obs, 'WAIT')\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", str(tmp_path))])
    monkeypatch.delitem(sys.modules, "here_policy", raising=False)
    try:
        assert type(make_policy("here_policy:Here", "ugv")).__name__ == "Here"
        assert sys.path[-1] == str(tmp_path)
    finally:
        sys.modules.pop("here_policy", None)


def _plugin(root: Path) -> None:
    """A package installed in ``root`` that registers policies in the ``agos.policies`` group."""
    (root / "agos_plugin_demo.py").write_text(
        "from agos.agents.contract import Policy, action_for\n\n\n"
        "class Waiter(Policy):\n    def act(self, obs):\n        return action_for(obs, 'WAIT')\n\n\n"
        "class NotAPolicy:\n    pass\n")
    info = root / "agos_plugin_demo-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: agos-plugin-demo\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[agos.policies]\nwaiter = agos_plugin_demo:Waiter\nnot-a-policy = agos_plugin_demo:NotAPolicy\n"
        "whole-module = agos_plugin_demo\nheuristic = agos_plugin_demo:Waiter\n")


def test_policies_registered_through_the_entry_point_group(tmp_path: Path, monkeypatch) -> None:
    """Names come from the package metadata without importing the package; the class is imported
    when the policy is built; agos's own names win over a registered one that repeats them."""
    _plugin(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "agos_plugin_demo", raising=False)
    try:
        assert registered_names() == {"waiter": "agos_plugin_demo:Waiter", "not-a-policy": "agos_plugin_demo:NotAPolicy",
                                      "whole-module": "agos_plugin_demo"}
        assert split_name("waiter") == ("waiter", "")
        assert tools_for({"uav": "waiter", "ugv": "heuristic"})["candidates"]
        locate_policy("waiter")
        assert "agos_plugin_demo" not in sys.modules
        policy = make_policy("waiter", "ugv")
        assert (type(policy).__name__, policy.role, policy.name) == ("Waiter", "ugv", "Waiter")
        assert policy.act(_obs("ugv")).action == "WAIT"
        assert policy_class("waiter") is type(policy)
        assert type(make_policy("heuristic", "uav")).__name__ == "HeuristicUav"
        with pytest.raises(ValueError, match=re.escape("NotAPolicy is not a subclass of agos.agents.contract.Policy")):
            make_policy("not-a-policy", "uav")
        with pytest.raises(ValueError, match="names a module, not a class"):
            make_policy("whole-module", "uav")
        with pytest.raises(ValueError, match="registered: not-a-policy, waiter, whole-module; or your own"):
            make_policy("waiterr", "uav")
    finally:
        sys.modules.pop("agos_plugin_demo", None)


def test_commands_refuse_a_policy_that_cannot_be_found_before_anything_starts(tmp_path: Path, agos) -> None:
    out = agos("eval", "--policy-uav", "heuristic", "--policy-ugv", "examples.nope:Explorer", "--run-dir", tmp_path / "r",
               cwd=REPO)
    assert out.returncode == 2 and out.stderr.strip().count("\n") == 0, out.stderr
    assert "eval error: policy 'examples.nope:Explorer': no module 'examples.nope'" in out.stderr
    assert not (tmp_path / "r").exists()  # no run directory, no process
    out = agos("check", "agent", "--connect", "tcp/127.0.0.1:1", "--policy-ugv", "heurstic")
    assert out.returncode == 2 and "check error: unknown policy 'heurstic'" in out.stderr, out.stderr


def test_the_guide_shows_the_example_as_it_is() -> None:
    """docs/AGENTS.md's "Write your own agent" shows examples/my_policy.py's code, word for word."""
    guide = (REPO / "docs" / "AGENTS.md").read_text()
    shown = guide.split("## Write your own agent", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    code = (REPO / "examples" / "my_policy.py").read_text()
    assert shown == code[code.index("from __future__"):]
    assert 25 <= len(shown.splitlines()) <= 35
