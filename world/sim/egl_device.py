"""Which GPU a world worker's EGL renderer draws on (``[render] egl_device``, docs/DEPLOY.md "GPU world workers").

PyBullet's EGL plugin (``eglRenderer``) lists the EGL devices when it loads and draws on the one
``EGL_VISIBLE_DEVICES`` names (an index into that list); unset, it initialises every device and keeps
the last that works, so every worker of a node would share one GPU. The world worker sets the variable
in its own process before any scene loads the plugin (:func:`apply`):

- ``[render] egl_device`` set (``AGOS_RENDER__EGL_DEVICE``): that index;
- else ``EGL_VISIBLE_DEVICES`` already in the environment: left as it is;
- else the worker's index modulo the GPUs it sees: the index is ``SLURM_LOCALID`` (Slurm), the ``k`` of a
  local worker ``w<k>`` (``agos eval``, ``agos demo``), else a hash of the worker id (compose and
  Kubernetes replicas have no index: they spread at random); the GPUs are ``CUDA_VISIBLE_DEVICES``
  (numbers are the node's GPU indices, as Slurm sets them), else ``NVIDIA_VISIBLE_DEVICES`` (a
  container sees only those, numbered from 0), else the ``/dev/nvidia<N>`` device files. One GPU or
  none: the plugin's own choice (nothing set).

EGL's list follows the drivers' order (NVIDIA's before Mesa's software device where both are installed),
which on most nodes is the GPUs' PCI order, CUDA's too with ``CUDA_DEVICE_ORDER=PCI_BUS_ID``; where it is
not, set ``egl_device`` per worker.
"""

from __future__ import annotations

import os
import re
import zlib
from collections.abc import Mapping, MutableMapping
from pathlib import Path

VARIABLE = "EGL_VISIBLE_DEVICES"
"""What the plugin reads (bullet3 examples/OpenGLWindow/EGLOpenGLWindow.cpp, via the plugin's
``m_renderDevice``)."""
_NOT_A_LIST = {"", "all", "none", "void", "nodevfiles", "-1"}


def visible_gpus(environ: Mapping[str, str], dev: Path = Path("/dev")) -> list[int]:
    """The EGL indices of the GPUs this process may use, in order (see the module docstring)."""
    cuda = [e.strip() for e in environ.get("CUDA_VISIBLE_DEVICES", "").split(",") if e.strip()]
    if cuda and cuda[0].lower() not in _NOT_A_LIST:
        if all(e.isdigit() for e in cuda):
            return [int(e) for e in cuda]
        return list(range(len(cuda)))  # UUIDs or MIG names: positions
    nvidia = [e.strip() for e in environ.get("NVIDIA_VISIBLE_DEVICES", "").split(",") if e.strip()]
    if nvidia and nvidia[0].lower() not in _NOT_A_LIST:
        return list(range(len(nvidia)))
    try:
        files = [p.name for p in dev.iterdir() if re.fullmatch(r"nvidia\d+", p.name)]
    except OSError:
        files = []
    return list(range(len(files)))


def worker_index(worker_id: str, environ: Mapping[str, str]) -> int:
    """This worker's index among the workers of its node (see the module docstring)."""
    local = environ.get("SLURM_LOCALID", "")
    if local.isdigit():
        return int(local)
    match = re.fullmatch(r"w(\d+)", worker_id)
    if match:
        return int(match[1])
    return zlib.crc32(worker_id.encode())


def choose(setting: int | None, worker_id: str, environ: Mapping[str, str],
           dev: Path = Path("/dev")) -> tuple[int | None, str]:
    """The EGL device index to set (None: set nothing) and why, in words for the log."""
    if setting is not None:
        return setting, "[render] egl_device"
    if environ.get(VARIABLE, "").strip():
        return None, f"{VARIABLE}={environ[VARIABLE]} from the environment"
    gpus = visible_gpus(environ, dev)
    if len(gpus) <= 1:
        return None, f"{len(gpus)} GPU(s) visible: the plugin's choice"
    index = worker_index(worker_id, environ)
    return gpus[index % len(gpus)], f"worker index {index} of {len(gpus)} visible GPUs {gpus}"


def apply(setting: int | None, worker_id: str, environ: MutableMapping[str, str] | None = None,
          dev: Path = Path("/dev")) -> str:
    """Set ``EGL_VISIBLE_DEVICES`` in this process (before the plugin loads); one line for the log."""
    env = os.environ if environ is None else environ
    device, why = choose(setting, worker_id, env, dev)
    if device is None:
        return f"EGL device: {why}"
    env[VARIABLE] = str(device)
    return f"EGL device {device} ({why})"
