"""Which GPU a world worker's EGL renderer draws on (world/sim/egl_device.py, ``[render] egl_device``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from agos.runtime.settings import ConfigError, load_config
from agos.world.sim import egl_device


def _dev(tmp_path: Path, gpus: int) -> Path:
    for name in [f"nvidia{k}" for k in range(gpus)] + ["nvidiactl", "nvidia-uvm", "null"]:
        (tmp_path / name).touch()
    return tmp_path


def test_slurm_tasks_spread_over_the_node_gpus_by_local_id(tmp_path: Path) -> None:
    env = {"CUDA_VISIBLE_DEVICES": "2,3", "SLURM_LOCALID": "0"}
    picks = [egl_device.choose(None, "n1-0-j7", {**env, "SLURM_LOCALID": str(k)}, tmp_path)[0] for k in range(5)]
    assert picks == [2, 3, 2, 3, 2]  # Slurm's numbers are the node's GPU indices


def test_local_workers_use_their_number_and_containers_count_from_zero(tmp_path: Path) -> None:
    env = {"NVIDIA_VISIBLE_DEVICES": "1,3,5"}  # a container sees only these, numbered from 0
    assert [egl_device.choose(None, f"w{k}", env, tmp_path)[0] for k in range(4)] == [0, 1, 2, 0]
    uuids = {"CUDA_VISIBLE_DEVICES": "GPU-aaaa,GPU-bbbb"}
    assert egl_device.choose(None, "w3", uuids, tmp_path)[0] == 1


def test_device_files_when_no_variable_says_and_a_hash_without_an_index(tmp_path: Path) -> None:
    dev = _dev(tmp_path, 4)
    assert egl_device.visible_gpus({"NVIDIA_VISIBLE_DEVICES": "all"}, dev) == [0, 1, 2, 3]
    picks = {egl_device.choose(None, f"host-{k:04x}", {}, dev)[0] for k in range(40)}
    assert picks == {0, 1, 2, 3}  # replicas without an index spread over every GPU


def test_one_gpu_or_none_is_the_plugin_choice_and_the_setting_wins(tmp_path: Path) -> None:
    assert egl_device.choose(None, "w5", {"CUDA_VISIBLE_DEVICES": "0"}, tmp_path)[0] is None
    assert egl_device.choose(None, "w5", {}, _dev(tmp_path, 0))[0] is None
    assert egl_device.choose(None, "w1", {"CUDA_VISIBLE_DEVICES": ""}, tmp_path)[0] is None
    env = {"CUDA_VISIBLE_DEVICES": "0,1", "EGL_VISIBLE_DEVICES": "0"}
    assert egl_device.choose(None, "w1", env, tmp_path)[0] is None  # the user's variable stays
    assert egl_device.choose(3, "w1", env, tmp_path)[0] == 3


def test_apply_sets_the_plugin_variable_only_when_there_is_a_choice(tmp_path: Path) -> None:
    env = {"CUDA_VISIBLE_DEVICES": "0,1", "SLURM_LOCALID": "3"}
    line = egl_device.apply(None, "n-3-j1", env, tmp_path)
    assert env["EGL_VISIBLE_DEVICES"] == "1" and line.startswith("EGL device 1 (")
    env = {}
    assert "plugin's choice" in egl_device.apply(None, "w0", env, _dev(tmp_path, 1)) and env == {}


def test_the_setting_is_read_from_the_environment_and_checked() -> None:
    assert load_config(environ={"AGOS_RENDER__EGL_DEVICE": "2"}).render.egl_device == 2
    assert load_config(environ={}).render.egl_device is None
    with pytest.raises(ConfigError, match=r"render\.egl_device"):
        load_config(environ={"AGOS_RENDER__EGL_DEVICE": "-1"})
