"""Kubernetes manifests rendered from the compose deployment (docs/DEPLOY.md, "Kubernetes").

    .venv/bin/python deploy/k8s/render.py                    # rewrite deploy/k8s/base, overlays/ and components/
    .venv/bin/python deploy/k8s/render.py --check            # exit 1 naming each committed file that differs
    .venv/bin/python deploy/k8s/render.py --env-file deploy/.env --out my-k8s   # your settings, elsewhere

The compose files are the one source: this reads ``deploy/compose.yaml``, ``deploy/compose.secure.yaml`` and
``deploy/compose.gpu.yaml`` with compose's own interpolation of the variables in ``deploy/.env.example``
(overridden by ``--env-file``), and turns each service's image, command, entrypoint, environment, user, grace
period, replicas, GPU request, health check and volumes into Kubernetes objects. A compose key, service or
volume this file has no mapping for stops the rendering with one line naming it, so the two deployments cannot
drift apart silently;
``tests/test_k8s_manifests.py`` re-renders and compares with the committed files.

What Kubernetes needs and compose does not say is fixed here, in the constants below: the router's
Service name (every process connects to it; the router listens on all addresses), the runs volume as a
PersistentVolumeClaim, the split as an optional ConfigMap, resource requests, an init container that
waits for the router (compose's ``depends_on``), and the longer presence checks of the eval Job (pods
start slower than containers on one host).

A compose GPU request (``deploy.resources.reservations.devices``, driver nvidia) becomes the container's
``resources.limits`` ``nvidia.com/gpu: N`` (the NVIDIA device plugin's resource; compose's ``count: all``,
every GPU of the host for each container, is one per pod, which the plugin gives each pod its own) and its capabilities other
than ``gpu`` the variable ``NVIDIA_DRIVER_CAPABILITIES`` (how the NVIDIA container toolkit is asked for them
on Kubernetes). compose.gpu.yaml's override is the kustomize Component ``components/gpu``, applied by
``overlays/gpu`` (over the base) and ``overlays/secure-gpu`` (over the secured overlay).

Needs PyYAML (the dev extra). Writes plain manifests and kustomize files; the secured overlay's
Secrets come from a ``secretGenerator`` over the files ``agos certs`` writes.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

import yaml

HERE = Path(__file__).resolve().parent
DEPLOY = HERE.parent
COMPOSE = DEPLOY / "compose.yaml"
COMPOSE_SECURE = DEPLOY / "compose.secure.yaml"
COMPOSE_GPU = DEPLOY / "compose.gpu.yaml"
ENV_EXAMPLE = DEPLOY / ".env.example"

ROUTER_SERVICE = "agos-router"
"""The router's Service: every process connects to ``<scheme>/agos-router:<AGOS_PORT>``."""
KUBERNETES_VARIABLES = {"AGOS_ROUTER_HOST": ROUTER_SERVICE, "AGOS_LISTEN_HOST": "0.0.0.0"}
"""Compose variables whose value on Kubernetes is fixed, whatever the env file says (it names hosts)."""
LABEL_NAME = "agos"
RUNS_CLAIM, RUNS_STORAGE = "agos-runs", "10Gi"
SPLIT_CONFIGMAP = "agos-split"
VLM_SECRET = "agos-vlm"
"""An optional Secret with the hosted model's key (``OPENAI_API_KEY``): compose passes it through from the shell."""
CA_SECRET, CERT_SECRET = "agos-ca", "agos-cert-{identity}"
CERTS_FOLDER = "certs"
GPU_RESOURCE = "nvidia.com/gpu"
"""The extended resource of the NVIDIA device plugin (one GPU per unit; shared GPUs need its time-slicing)."""
"""Where the secured overlay's ``secretGenerator`` reads the files of ``agos certs`` (beside its kustomization)."""

RESOURCES: dict[str, dict[str, str]] = {
    # A world worker uses about one core and 250 MB (docs/DEPLOY.md); the others are starting points, not measured.
    "router": {"cpu": "250m", "memory": "256Mi"},
    "evaluator": {"cpu": "250m", "memory": "512Mi"},
    "agent-uav": {"cpu": "250m", "memory": "512Mi"},
    "agent-ugv": {"cpu": "250m", "memory": "512Mi"},
    "world": {"cpu": "1", "memory": "512Mi"},
    "eval": {"cpu": "250m", "memory": "512Mi"},
}
JOB_ENV = {"AGOS_RUN__PRESENCE_CHECK_S": "60"}
"""The eval Job stops when no world worker joined for 3 presence checks: 3 minutes here (45 s by default),
for pods still being scheduled, pulling the image or scaled up from zero."""
ROUTER_WAIT_S = 300
WAIT_FOR_ROUTER = """\
import os, socket, sys, time
host, port = os.environ["AGOS_ZENOH__CONNECT"].split("/", 1)[1].rsplit(":", 1)
deadline = time.monotonic() + float(sys.argv[1])
while True:
    try:
        socket.create_connection((host, int(port)), timeout=5).close()
        break
    except OSError as exc:
        if time.monotonic() > deadline:
            sys.exit(f"wait-router: {host}:{port} did not answer for {sys.argv[1]} s: {exc}")
        time.sleep(2)
"""
"""The init container of every process but the router: compose's ``depends_on: router`` (a TCP connect to
the router's Service, which answers once the router pod is ready)."""


class RenderError(Exception):
    """One line: the file, the service or key, and what to do."""


@dataclass(frozen=True)
class Workload:
    kind: str
    """``Deployment`` or ``Job``."""
    name: str
    strategy: str = "RollingUpdate"
    """``Recreate`` where two copies must never run at once (one router, one SQLite writer, one agent per role)."""


WORKLOADS = {
    "router": Workload("Deployment", ROUTER_SERVICE, "Recreate"),
    "evaluator": Workload("Deployment", "agos-evaluator", "Recreate"),
    "agent-uav": Workload("Deployment", "agos-agent-uav", "Recreate"),
    "agent-ugv": Workload("Deployment", "agos-agent-ugv", "Recreate"),
    "world": Workload("Deployment", "agos-world"),
    "eval": Workload("Job", "agos-eval"),
}
"""The compose services rendered, in order, and the object each becomes."""
NOT_RENDERED = {"vlm-standin": "the offline stand-in model (profile vlm) serves loopback tests, not a cluster"}
SERVICE_KEYS = {"image", "network_mode", "user", "stop_signal", "stop_grace_period", "logging", "build", "command",
                "entrypoint", "environment", "volumes", "restart", "depends_on", "healthcheck", "deploy", "profiles"}
"""Compose keys with a mapping here (or none needed: network_mode host, logging, build, depends_on)."""
HEADER = ("# Rendered by deploy/k8s/render.py from deploy/compose{secure}.yaml and deploy/.env.example: do not edit,\n"
          "# re-render (docs/DEPLOY.md, \"Kubernetes\").\n")


# --- compose's variables ---------------------------------------------------------------------------------------------

def read_env_file(path: Path) -> dict[str, str]:
    """``NAME=VALUE`` lines as compose reads them (comments, blank lines; quotes around a value dropped)."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise RenderError(f"{path}: {exc.strerror or exc}") from None
    values: dict[str, str] = {}
    for number, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        name, eq, value = line.partition("=")
        name = name.removeprefix("export ").strip()
        if not eq or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
            raise RenderError(f"{path}:{number}: not NAME=VALUE: {line!r}")
        value = value.strip()
        if len(value) >= 2 and value[0] == value[-1] and value[0] in "'\"":
            value = value[1:-1]
        values[name] = value
    return values


_VARIABLE = re.compile(r"\$(?:(?P<escaped>\$)|\{(?P<braced>[A-Za-z_][A-Za-z0-9_]*)(?:(?P<op>:?[-?+])(?P<arg>[^}]*))?\}"
                       r"|(?P<bare>[A-Za-z_][A-Za-z0-9_]*))")


def interpolate(text: str, variables: dict[str, str], where: str) -> str:
    """Compose's interpolation: ``$$`` is ``$``; ``${NAME}``, ``${NAME:-default}``, ``${NAME-default}``,
    ``${NAME:+other}`` and ``$NAME`` read ``variables``, which must name every variable used (the env file
    lists them all)."""
    def one(match: re.Match[str]) -> str:
        if match["escaped"]:
            return "$"
        name = match["braced"] or match["bare"]
        if name not in variables:
            raise RenderError(f"{where}: ${{{name}}} is not in deploy/.env.example: add it there with its default")
        value, op, arg = variables[name], match["op"] or "", match["arg"] or ""
        if op in (":-", "-"):
            return value if value or op == "-" else arg
        if op in (":+", "+"):
            return arg if value or op == "+" else ""
        if op in (":?", "?") and not value:
            raise RenderError(f"{where}: ${{{name}}} is required: {arg}")
        return value
    return _VARIABLE.sub(one, text)


def _interpolated(node: Any, variables: dict[str, str], where: str) -> Any:
    if isinstance(node, str):
        return interpolate(node, variables, where)
    if isinstance(node, list):
        return [_interpolated(item, variables, where) for item in node]
    if isinstance(node, dict):
        return {key: _interpolated(value, variables, f"{where}: {key}") for key, value in node.items()}
    return node


def load_compose(path: Path, variables: dict[str, str]) -> dict[str, Any]:
    """The compose file's services, anchors merged and every string interpolated."""
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise RenderError(f"{path}: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise RenderError(f"{path}: not YAML: {' '.join(str(exc).split())}") from None
    if not isinstance(data, dict) or not isinstance(data.get("services"), dict):
        raise RenderError(f"{path}: no services")
    return {name: _interpolated(service, variables, f"{path.name}: {name}") for name, service in data["services"].items()}


def seconds(duration: str, where: str) -> int:
    """A compose duration (``10s``, ``1m30s``, ``500ms`` rounded up) in whole seconds."""
    parts = re.findall(r"(\d+(?:\.\d+)?)(ms|us|h|m|s)", duration)
    if not parts or "".join(n + u for n, u in parts) != duration:
        raise RenderError(f"{where}: {duration!r} is not a duration such as 10s or 1m30s")
    scale = {"h": 3600.0, "m": 60.0, "s": 1.0, "ms": 1e-3, "us": 1e-6}
    total = sum(float(n) * scale[u] for n, u in parts)
    return max(1, int(-(-total // 1)))


# --- one compose service as a pod ------------------------------------------------------------------------------------

def _labels(service: str) -> dict[str, str]:
    return {"app.kubernetes.io/name": LABEL_NAME, "app.kubernetes.io/component": service}


def _environment(service: str, environment: Any) -> list[dict[str, Any]]:
    if not isinstance(environment, dict):
        raise RenderError(f"compose.yaml: {service}: environment must be a map")
    env: list[dict[str, Any]] = []
    for name, value in environment.items():
        if value is None:  # passed through from compose's own environment: a secret on Kubernetes
            if name != "OPENAI_API_KEY":
                raise RenderError(f"compose.yaml: {service}: {name} is passed through; only OPENAI_API_KEY has a Secret here")
            env.append({"name": name, "valueFrom": {"secretKeyRef": {"name": VLM_SECRET, "key": name, "optional": True}}})
        elif isinstance(value, str | int | float) and not isinstance(value, bool):
            env.append({"name": name, "value": str(value)})
        else:
            raise RenderError(f"compose.yaml: {service}: environment {name}: {value!r} is not a string")
    return env


def _volumes(service: str, entries: list[str]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Compose volumes by their path in the container: /runs the claim, /data the split's ConfigMap, /assets empty."""
    volumes: list[dict[str, Any]] = []
    mounts: list[dict[str, Any]] = []
    for entry in entries:
        _, target, *mode = str(entry).split(":")
        read_only = mode == ["ro"]
        if target == "/runs":
            volumes.append({"name": "runs", "persistentVolumeClaim": {"claimName": RUNS_CLAIM}})
        elif target == "/data":
            volumes.append({"name": "data", "configMap": {"name": SPLIT_CONFIGMAP, "optional": True}})
        elif target == "/assets":
            volumes.append({"name": "assets", "emptyDir": {}})
        else:
            raise RenderError(f"compose.yaml: {service}: volume {entry!r}: no Kubernetes volume for {target} "
                              "in deploy/k8s/render.py")
        mounts.append({"name": volumes[-1]["name"], "mountPath": target, **({"readOnly": True} if read_only else {})})
    return volumes, mounts


def gpu_request(service: str, deploy: Any, environment: dict[str, Any], file: str = "compose.yaml") -> tuple[
        dict[str, str], dict[str, str]]:
    """A compose ``deploy`` block's GPU request as the container's resource limits and the environment it
    needs (``NVIDIA_DRIVER_CAPABILITIES`` from the capabilities besides ``gpu``, unless the service sets it
    with all of them); ``replicas`` is read by :func:`workload`, anything else has no mapping."""
    if not isinstance(deploy, dict):
        raise RenderError(f"{file}: {service}: deploy must be a map")
    unknown = sorted(set(deploy) - {"replicas", "resources"})
    resources = deploy.get("resources", {})
    unknown += sorted(f"resources.{k}" for k in set(resources) - {"reservations"})
    reservations = resources.get("reservations", {})
    unknown += sorted(f"resources.reservations.{k}" for k in set(reservations) - {"devices"})
    if unknown:
        raise RenderError(f"{file}: {service}: deploy.{unknown[0]} has no Kubernetes mapping in deploy/k8s/render.py")
    limits: dict[str, str] = {}
    env: dict[str, str] = {}
    for device in reservations.get("devices", []):
        capabilities = [str(c) for c in device.get("capabilities", [])]
        if device.get("driver") != "nvidia" or "gpu" not in capabilities:
            raise RenderError(f"{file}: {service}: device {device!r}: only driver nvidia with capability gpu is rendered")
        if "device_ids" in device or sorted(set(device) - {"driver", "count", "capabilities"}):
            raise RenderError(f"{file}: {service}: device {device!r}: give a count (Kubernetes' device plugin "
                              "chooses the GPUs), nothing else")
        count = str(device.get("count", "all"))
        if count == "all":  # every GPU of the host, for each container; a pod gets its own from the device plugin
            count = "1"
        if not count.isdigit() or int(count) < 1:
            raise RenderError(f"{file}: {service}: device count {count!r}: give a number of GPUs per pod or all "
                              "(AGOS_WORLD_GPUS)")
        limits[GPU_RESOURCE] = str(int(limits.get(GPU_RESOURCE, "0")) + int(count))
        wanted = [c for c in capabilities if c != "gpu"]
        if wanted:
            given = str(environment.get("NVIDIA_DRIVER_CAPABILITIES") or "")
            missing = [c for c in wanted if given and c not in given.split(",") and given != "all"]
            if missing:
                raise RenderError(f"{file}: {service}: NVIDIA_DRIVER_CAPABILITIES {given!r} lacks {missing[0]!r}, "
                                  "a capability its device request asks for")
            if not given:
                env["NVIDIA_DRIVER_CAPABILITIES"] = ",".join(wanted)
    return limits, env


def _probe(service: str, check: dict[str, Any]) -> dict[str, Any]:
    """A compose healthcheck as a readiness probe: it gates the router's Service and shows in READY, like
    ``docker compose ps``; nothing is restarted for it (compose restarts nothing for it either)."""
    test = check["test"]
    if test[0] == "CMD":
        command = list(test[1:])
    elif test[0] == "CMD-SHELL":
        command = ["/bin/sh", "-c", test[1]]
    else:
        raise RenderError(f"compose.yaml: {service}: healthcheck test {test[0]!r}: only CMD and CMD-SHELL are rendered")
    interval_s = seconds(check["interval"], f"{service}: healthcheck interval")
    return {"exec": {"command": command}, "initialDelaySeconds": interval_s, "periodSeconds": interval_s,
            "timeoutSeconds": seconds(check["timeout"], f"{service}: healthcheck timeout"),
            "failureThreshold": int(check["retries"])}


def _user(service: str, user: str) -> dict[str, Any]:
    match = re.fullmatch(r"(\d+):(\d+)", user)
    if not match:
        raise RenderError(f"compose.yaml: {service}: user {user!r}: give numeric UID:GID (AGOS_UID, AGOS_GID)")
    uid, gid = int(match[1]), int(match[2])
    return {"runAsUser": uid, "runAsGroup": gid, "fsGroup": gid, "runAsNonRoot": True,
            "fsGroupChangePolicy": "OnRootMismatch"}


def pod_template(service: str, spec: dict[str, Any], connect: str) -> dict[str, Any]:
    """The pod of one compose service: its container (args = the compose command, as the image's entrypoint
    is ``agos``), the router wait, the volumes, the user and the grace period."""
    unknown = sorted(set(spec) - SERVICE_KEYS)
    if unknown:
        raise RenderError(f"compose.yaml: {service}: key {unknown[0]!r} has no Kubernetes mapping in deploy/k8s/render.py")
    if spec.get("stop_signal", "SIGTERM") != "SIGTERM":
        raise RenderError(f"compose.yaml: {service}: stop_signal {spec['stop_signal']}: Kubernetes sends SIGTERM only")
    container: dict[str, Any] = {"name": service, "image": spec["image"], "imagePullPolicy": "IfNotPresent"}
    if "entrypoint" in spec:
        container["command"] = list(spec["entrypoint"])
    container["args"] = [str(arg) for arg in spec["command"]]
    container["env"] = _environment(service, spec.get("environment", {}))
    limits, gpu_env = gpu_request(service, spec.get("deploy", {}), spec.get("environment", {}))
    container["env"] += [{"name": name, "value": value} for name, value in gpu_env.items()]
    if service == "eval":
        container["env"] += [{"name": name, "value": value} for name, value in JOB_ENV.items()]
    volumes, mounts = _volumes(service, spec.get("volumes", []))
    if mounts:
        container["volumeMounts"] = mounts
    if "healthcheck" in spec:
        container["readinessProbe"] = _probe(service, spec["healthcheck"])
    container["resources"] = {"requests": dict(RESOURCES[service]), **({"limits": limits} if limits else {})}
    if service == "router":
        port = connect.rsplit(":", 1)[1]
        container["ports"] = [{"name": "zenoh", "containerPort": int(port), "protocol": "TCP"}]
    pod: dict[str, Any] = {"enableServiceLinks": False,  # no AGOS_ROUTER_* variables from the Service
                           "securityContext": _user(service, spec["user"]),
                           "terminationGracePeriodSeconds": seconds(spec.get("stop_grace_period", "10s"), service)}
    if service == "router":
        # The router's own health check connects as every client does, to the Service name: here, itself.
        pod["hostAliases"] = [{"ip": "127.0.0.1", "hostnames": [ROUTER_SERVICE]}]
    else:
        pod["initContainers"] = [{"name": "wait-router", "image": spec["image"], "imagePullPolicy": "IfNotPresent",
                                  "command": ["python3", "-c", WAIT_FOR_ROUTER, str(ROUTER_WAIT_S)],
                                  "env": [{"name": "AGOS_ZENOH__CONNECT", "value": connect}]}]
    if service == "eval":
        pod["restartPolicy"] = "Never"
        # The runs claim is ReadWriteOnce: the Job's pod goes where the evaluator's is.
        pod["affinity"] = {"podAffinity": {"requiredDuringSchedulingIgnoredDuringExecution": [{
            "labelSelector": {"matchLabels": _labels("evaluator")}, "topologyKey": "kubernetes.io/hostname"}]}}
    pod["containers"] = [container]
    if volumes:
        pod["volumes"] = volumes
    return {"metadata": {"labels": _labels(service)}, "spec": pod}


def workload(service: str, spec: dict[str, Any], connect: str) -> list[dict[str, Any]]:
    """The objects of one compose service: its Deployment or Job, and the router's Service or the runs claim."""
    what = WORKLOADS[service]
    meta = {"name": what.name, "labels": _labels(service)}
    template = pod_template(service, spec, connect)
    objects: list[dict[str, Any]] = []
    if service == "evaluator":
        objects.append({"apiVersion": "v1", "kind": "PersistentVolumeClaim",
                        "metadata": {"name": RUNS_CLAIM, "labels": _labels(service)},
                        "spec": {"accessModes": ["ReadWriteOnce"], "resources": {"requests": {"storage": RUNS_STORAGE}}}})
    if what.kind == "Job":
        if spec.get("restart", "no") != "no":
            raise RenderError(f"compose.yaml: {service}: a Job restarts nothing (restart: \"no\")")
        objects.append({"apiVersion": "batch/v1", "kind": "Job", "metadata": meta,
                        "spec": {"backoffLimit": 0, "template": template}})
        return objects
    if spec.get("restart") not in ("unless-stopped", "on-failure", "always"):
        raise RenderError(f"compose.yaml: {service}: restart {spec.get('restart')!r}: a Deployment always restarts")
    replicas = int(spec.get("deploy", {}).get("replicas", 1))
    objects.append({"apiVersion": "apps/v1", "kind": "Deployment", "metadata": meta,
                    "spec": {"replicas": replicas, "selector": {"matchLabels": _labels(service)},
                             "strategy": {"type": what.strategy}, "template": template}})
    if service == "router":
        port = int(connect.rsplit(":", 1)[1])
        objects.append({"apiVersion": "v1", "kind": "Service", "metadata": meta,
                        "spec": {"selector": _labels(service),
                                 "ports": [{"name": "zenoh", "port": port, "targetPort": "zenoh", "protocol": "TCP"}]}})
    return objects


# --- the secured overlay ---------------------------------------------------------------------------------------------

def secure_patch(service: str, spec: dict[str, Any]) -> tuple[dict[str, Any], dict[str, list[str]]]:
    """compose.secure.yaml's override of one service as a strategic-merge patch: its TLS environment, and
    its read-only certificate files as one projected volume of Secrets at their folder. Also the files each
    Secret holds (Secret name -> file names as ``agos certs`` writes them)."""
    unknown = sorted(set(spec) - {"environment", "volumes"})
    if unknown:
        raise RenderError(f"compose.secure.yaml: {service}: key {unknown[0]!r} has no mapping in deploy/k8s/render.py")
    items: dict[str, list[dict[str, str]]] = {}
    folders = set()
    for entry in spec.get("volumes", []):
        source, target, *mode = str(entry).split(":")
        if mode != ["ro"]:
            raise RenderError(f"compose.secure.yaml: {service}: {entry!r}: certificate files are mounted read-only (:ro)")
        file = PurePosixPath(source).name
        identity = PurePosixPath(file).stem
        secret = CA_SECRET if identity == "ca" else CERT_SECRET.format(identity=identity)
        if file == "ca.key":
            raise RenderError(f"compose.secure.yaml: {service}: ca.key is never mounted")
        items.setdefault(secret, []).append({"key": file, "path": PurePosixPath(target).name})
        folders.add(str(PurePosixPath(target).parent))
    if len(folders) != 1:
        raise RenderError(f"compose.secure.yaml: {service}: certificate files in {sorted(folders)}: one folder expected")
    what = WORKLOADS[service]
    sources = [{"secret": {"name": secret, "items": files}} for secret, files in items.items()]
    container: dict[str, Any] = {"name": service, "env": _environment(service, spec["environment"]),
                 "volumeMounts": [{"name": "certs", "mountPath": folders.pop(), "readOnly": True}]}
    # 0440: the files belong to root and the pod's fsGroup (AGOS_GID), so the containers' user reads its key.
    volume = {"name": "certs", "projected": {"defaultMode": 0o440, "sources": sources}}
    patch: dict[str, Any] = {"apiVersion": "batch/v1" if what.kind == "Job" else "apps/v1", "kind": what.kind,
             "metadata": {"name": what.name},
             "spec": {"template": {"spec": {"containers": [container], "volumes": [volume]}}}}
    if service != "router":  # the wait for the router connects to the TLS port now
        tls_connect = next(e for e in container["env"] if e["name"] == "AGOS_ZENOH__CONNECT")
        patch["spec"]["template"]["spec"]["initContainers"] = [{"name": "wait-router", "env": [dict(tls_connect)]}]
    return patch, {secret: [i["key"] for i in files] for secret, files in items.items()}


# --- the GPU component -----------------------------------------------------------------------------------------------

def gpu_patch(service: str, spec: dict[str, Any]) -> dict[str, Any]:
    """compose.gpu.yaml's override of one service as a strategic-merge patch: its environment, and its GPU
    request as resource limits (:func:`gpu_request`). Its build arguments say how the image is built, which
    on Kubernetes is done before (push the RENDERER=egl build as AGOS_IMAGE)."""
    unknown = sorted(set(spec) - {"environment", "deploy", "build"})
    if unknown:
        raise RenderError(f"compose.gpu.yaml: {service}: key {unknown[0]!r} has no mapping in deploy/k8s/render.py")
    if sorted(set(spec.get("build", {})) - {"args"}):
        raise RenderError(f"compose.gpu.yaml: {service}: build: only args are read (the image is built before)")
    if "replicas" in spec.get("deploy", {}):
        raise RenderError(f"compose.gpu.yaml: {service}: replicas stay compose.yaml's")
    environment = spec.get("environment", {})
    limits, gpu_env = gpu_request(service, spec.get("deploy", {}), environment, "compose.gpu.yaml")
    container: dict[str, Any] = {"name": service}
    env = _environment(service, environment) + [{"name": name, "value": value} for name, value in gpu_env.items()]
    if env:
        container["env"] = env
    if limits:
        container["resources"] = {"limits": limits}
    what = WORKLOADS[service]
    return {"apiVersion": "batch/v1" if what.kind == "Job" else "apps/v1", "kind": what.kind,
            "metadata": {"name": what.name}, "spec": {"template": {"spec": {"containers": [container]}}}}


# --- files -----------------------------------------------------------------------------------------------------------

class _Dumper(yaml.SafeDumper):
    def ignore_aliases(self, data: Any) -> bool:
        return True  # a value used twice is written twice, never as an anchor


def _str(dumper: yaml.SafeDumper, value: str) -> yaml.Node:
    style = "|" if "\n" in value else None
    return dumper.represent_scalar("tag:yaml.org,2002:str", value, style=style)


_Dumper.add_representer(str, _str)


def dump(documents: list[dict[str, Any]], header: str) -> str:
    """YAML documents, block style, keys in the order built, after a header comment."""
    body = "---\n".join(yaml.dump(d, Dumper=_Dumper, sort_keys=False, default_flow_style=False, width=120)
                        for d in documents)
    return header + body


def _octal_mode(text: str) -> str:
    """A comment with the octal form after each ``defaultMode`` (kept decimal: YAML 1.1 and 1.2 read a
    leading 0 differently)."""
    return re.sub(r"(defaultMode: )(\d+)\n", lambda m: f"{m[1]}{m[2]}  # 0{int(m[2]):o}\n", text)


def render(variables: dict[str, str], *, compose: Path = COMPOSE, compose_secure: Path = COMPOSE_SECURE,
           compose_gpu: Path = COMPOSE_GPU) -> dict[str, str]:
    """Every file of deploy/k8s (path relative to it -> text) for the compose variables ``variables``
    (:func:`read_env_file`); :class:`RenderError` for anything the compose files say that has no mapping."""
    variables = {**variables, **KUBERNETES_VARIABLES}
    services = load_compose(compose, variables)
    secure = load_compose(compose_secure, variables)
    for name in services:
        if name not in WORKLOADS and name not in NOT_RENDERED:
            raise RenderError(f"compose.yaml: service {name!r} has no Kubernetes object in deploy/k8s/render.py")
    for name in WORKLOADS:
        if name not in services:
            raise RenderError(f"compose.yaml: service {name!r} is gone: remove it from deploy/k8s/render.py")
    connect = services["router"]["environment"]["AGOS_ZENOH__CONNECT"]
    files: dict[str, str] = {}
    plain, tls = HEADER.format(secure=""), HEADER.format(secure="{,.secure}")
    base = []
    for name in WORKLOADS:
        file = f"{name}.yaml"
        files[f"base/{file}"] = dump(workload(name, services[name], connect), plain)
        base.append(file)
    files["base/kustomization.yaml"] = dump([{
        "apiVersion": "kustomize.config.k8s.io/v1beta1", "kind": "Kustomization", "resources": base}], plain)
    patches: list[dict[str, str]] = []
    secrets: dict[str, list[str]] = {}
    for name in WORKLOADS:
        if name not in secure:
            raise RenderError(f"compose.secure.yaml: service {name!r} is not secured: every process needs its certificate")
        patch, held = secure_patch(name, secure[name])
        files[f"overlays/secure/{name}.yaml"] = _octal_mode(dump([patch], tls))
        patches.append({"path": f"{name}.yaml"})
        for secret, held_files in held.items():
            if secrets.setdefault(secret, held_files) != held_files:
                raise RenderError(f"compose.secure.yaml: {name}: Secret {secret} with other files than another service's")
    extra = sorted(set(secure) - set(WORKLOADS) - set(NOT_RENDERED))
    if extra:
        raise RenderError(f"compose.secure.yaml: service {extra[0]!r} has no Kubernetes object in deploy/k8s/render.py")
    generators = [{"name": secret, "files": [f"{CERTS_FOLDER}/{f}" for f in held]} for secret, held in sorted(secrets.items())]
    files["overlays/secure/kustomization.yaml"] = dump([{
        "apiVersion": "kustomize.config.k8s.io/v1beta1", "kind": "Kustomization", "resources": ["../../base"],
        "secretGenerator": generators, "patches": patches}], tls)
    files["overlays/secure/.gitignore"] = (f"# the files of `agos certs --out {CERTS_FOLDER}` (private keys): never committed\n"
                                           f"/{CERTS_FOLDER}/\n")
    gpu = load_compose(compose_gpu, variables)
    gpu_header = HEADER.format(secure="{,.gpu}")
    extra = sorted(set(gpu) - set(WORKLOADS))
    if extra:
        raise RenderError(f"compose.gpu.yaml: service {extra[0]!r} has no Kubernetes object in deploy/k8s/render.py")
    gpu_patches = []
    for name in WORKLOADS:
        if name not in gpu:
            continue
        patch = gpu_patch(name, gpu[name])
        if len(patch["spec"]["template"]["spec"]["containers"][0]) > 1:  # more than its name: something to patch
            files[f"components/gpu/{name}.yaml"] = dump([patch], gpu_header)
            gpu_patches.append({"path": f"{name}.yaml"})
    files["components/gpu/kustomization.yaml"] = dump([{
        "apiVersion": "kustomize.config.k8s.io/v1alpha1", "kind": "Component", "patches": gpu_patches}], gpu_header)
    for overlay, below, sources in (("gpu", "../../base", "{,.gpu}"), ("secure-gpu", "../secure", "{,.secure,.gpu}")):
        files[f"overlays/{overlay}/kustomization.yaml"] = dump([{
            "apiVersion": "kustomize.config.k8s.io/v1beta1", "kind": "Kustomization", "resources": [below],
            "components": ["../../components/gpu"]}], HEADER.format(secure=sources))
    return files


def main(argv: list[str] | None = None, *, out: Callable[[str], None] = print) -> int:
    parser = argparse.ArgumentParser(prog="deploy/k8s/render.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--env-file", type=Path, help="compose variables over deploy/.env.example's (e.g. deploy/.env)")
    parser.add_argument("--out", type=Path, default=HERE, help="folder to write (default deploy/k8s)")
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 if a file in --out differs")
    args = parser.parse_args(argv)
    try:
        variables = read_env_file(ENV_EXAMPLE)
        if args.env_file is not None:
            variables.update(read_env_file(args.env_file))
        files = render(variables)
    except RenderError as exc:
        print(f"render: {exc}", file=sys.stderr)
        return 2
    differ = []
    for relative, text in files.items():
        path = args.out / relative
        current = path.read_text(encoding="utf-8") if path.exists() else None
        if current == text:
            continue
        if args.check:
            differ.append(relative)
            continue
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
        out(f"wrote {path}")
    if differ:
        print(f"render: {', '.join(differ)} in {args.out} differ from deploy/compose.yaml's rendering: "
              f"run .venv/bin/python deploy/k8s/render.py and commit", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
