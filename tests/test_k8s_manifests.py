"""The Kubernetes manifests (deploy/k8s): the committed files are deploy/k8s/render.py's rendering of the
compose files, and every object, with and without the secured overlay, validates against the Kubernetes API
schemas (kubernetes-validate's, offline, strict: an unknown field fails)."""

from __future__ import annotations

import base64
import copy
import importlib.util
import sys
from pathlib import Path
from typing import Any

import kubernetes_validate
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
K8S = ROOT / "deploy" / "k8s"


def _load_renderer() -> Any:
    spec = importlib.util.spec_from_file_location("k8s_render", K8S / "render.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


render = _load_renderer()
VERSIONS = [kubernetes_validate.utils.all_versions()[0], kubernetes_validate.utils.latest_version()]
"""The oldest and newest Kubernetes versions whose schemas the package ships."""


def _documents(text: str) -> list[dict[str, Any]]:
    return [d for d in yaml.safe_load_all(text) if d]


def _committed(relative: str) -> list[dict[str, Any]]:
    return _documents((K8S / relative).read_text(encoding="utf-8"))


def _validate(obj: dict[str, Any], where: str) -> None:
    for version in VERSIONS:
        try:
            kubernetes_validate.validate(obj, version, strict=True)
        except kubernetes_validate.ValidationError as exc:
            path = ".".join(str(p) for p in exc.path)
            pytest.fail(f"{where}: {obj['kind']} {obj['metadata']['name']} against Kubernetes {version}: {path}: {exc.message}")


def _merge(base: Any, patch: Any, key: str = "") -> Any:
    """Kubernetes' strategic merge for the fields the overlay patches: maps merge; containers, init
    containers, env and volumes merge by ``name``, volume mounts by ``mountPath`` (their patchMergeKey in the
    API), patch entries first as kustomize writes them; any other value is replaced."""
    if isinstance(base, dict) and isinstance(patch, dict):
        out = dict(base)
        for k, v in patch.items():
            out[k] = _merge(base[k], v, k) if k in base else copy.deepcopy(v)
        return out
    merge_key = {"containers": "name", "initContainers": "name", "env": "name", "volumes": "name",
                 "volumeMounts": "mountPath"}.get(key)
    if merge_key and isinstance(base, list) and isinstance(patch, list):
        by_key = {item[merge_key]: item for item in base}
        merged = [_merge(by_key[p[merge_key]], p) if p[merge_key] in by_key else copy.deepcopy(p) for p in patch]
        return merged + [item for item in base if item[merge_key] not in {p[merge_key] for p in patch}]
    return copy.deepcopy(patch)


def _secure_objects() -> list[dict[str, Any]]:
    """What ``kubectl apply -k deploy/k8s/overlays/secure`` applies: the base's objects with the overlay's
    patches, and one Secret per generator (stand-in file contents; names without kustomize's hash suffix)."""
    overlay = _committed("overlays/secure/kustomization.yaml")[0]
    assert overlay["resources"] == ["../../base"]
    base = [o for f in _committed("base/kustomization.yaml")[0]["resources"] for o in _committed(f"base/{f}")]
    for entry in overlay["patches"]:
        patch = _committed(f"overlays/secure/{entry['path']}")[0]
        target = [o for o in base if (o["kind"], o["metadata"]["name"]) == (patch["kind"], patch["metadata"]["name"])]
        assert len(target) == 1, f"{entry['path']} patches {patch['kind']} {patch['metadata']['name']}: not one base object"
        base[base.index(target[0])] = _merge(target[0], patch)
    secrets = [{"apiVersion": "v1", "kind": "Secret", "type": "Opaque", "metadata": {"name": g["name"]},
                "data": {Path(f).name: base64.b64encode(b"-----stand-in-----\n").decode() for f in g["files"]}}
               for g in overlay["secretGenerator"]]
    return base + secrets


def test_committed_files_are_the_rendering_of_the_compose_files() -> None:
    files = render.render(render.read_env_file(ROOT / "deploy" / ".env.example"))
    for relative, text in files.items():
        assert (K8S / relative).read_text(encoding="utf-8") == text, (
            f"deploy/k8s/{relative} differs from its rendering: run .venv/bin/python deploy/k8s/render.py and commit")
    on_disk = {str(p.relative_to(K8S)) for p in K8S.rglob("*") if p.is_file() and "__pycache__" not in p.parts}
    ignored = {str(p.relative_to(K8S)) for p in (K8S / "overlays" / "secure" / "certs").rglob("*")}
    assert on_disk - ignored == set(files) | {"render.py"}, "a file in deploy/k8s that the renderer does not write"


def test_every_object_validates_against_the_kubernetes_api_schemas() -> None:
    kustomization = _committed("base/kustomization.yaml")[0]
    objects = [(f, o) for f in kustomization["resources"] for o in _committed(f"base/{f}")]
    assert {o["kind"] for _, o in objects} == {"Deployment", "Service", "PersistentVolumeClaim", "Job"}
    for file, obj in objects:
        _validate(obj, f"deploy/k8s/base/{file}")
    secured = _secure_objects()
    for obj in secured:
        _validate(obj, "deploy/k8s/overlays/secure")
    assert len(secured) == len(objects) + 7  # the CA's Secret and one per identity


def test_the_secured_overlay_gives_each_process_its_own_certificate_over_tls() -> None:
    objects = {(o["kind"], o["metadata"]["name"]): o for o in _secure_objects()}
    generated = {name for kind, name in objects if kind == "Secret"}
    identities = {"agos-router": "router", "agos-evaluator": "evaluator", "agos-agent-uav": "agent-uav",
                  "agos-agent-ugv": "agent-ugv", "agos-world": "world", "agos-eval": "orchestrator"}
    for (kind, name), obj in objects.items():
        if kind not in ("Deployment", "Job"):
            continue
        pod = obj["spec"]["template"]["spec"]
        (container,) = pod["containers"]
        env = {e["name"]: e.get("value") for e in container["env"]}
        assert env["AGOS_ZENOH__CONNECT"] == "tls/agos-router:7447"
        assert env["AGOS_ZENOH__KEY_FILE"] == "/certs/identity.key"
        (certs,) = [v for v in pod["volumes"] if v["name"] == "certs"]
        used = {s["secret"]["name"]: {i["key"]: i["path"] for i in s["secret"]["items"]} for s in certs["projected"]["sources"]}
        identity = identities[name]
        assert used == {"agos-ca": {"ca.pem": "ca.pem"},
                        f"agos-cert-{identity}": {f"{identity}.pem": "identity.pem", f"{identity}.key": "identity.key"}}
        assert set(used) <= generated
        assert {"name": "certs", "mountPath": "/certs", "readOnly": True} in container["volumeMounts"]
        for init in pod.get("initContainers", []):  # the wait for the router asks the TLS port
            assert {"name": "AGOS_ZENOH__CONNECT", "value": "tls/agos-router:7447"} in init["env"]
    assert {e["name"]: e["value"] for e in objects["Deployment", "agos-router"]["spec"]["template"]["spec"]
            ["containers"][0]["env"]}["AGOS_ZENOH__LISTEN"] == "tls/0.0.0.0:7447"
    generators = _committed("overlays/secure/kustomization.yaml")[0]["secretGenerator"]
    assert not any(f.endswith("ca.key") for g in generators for f in g["files"]), "ca.key must stay off the cluster"


def test_the_manifests_follow_the_compose_settings(tmp_path: Path) -> None:
    env = tmp_path / ".env"
    # A three-host deploy/.env: its router address names a host, which on Kubernetes is the Service.
    env.write_text("AGOS_RUN=val-2\nAGOS_WORLDS=8\nAGOS_PORT=7500\nAGOS_ROUTER_HOST=10.0.0.1\n"
                   "AGOS_IMAGE=registry.example.org/agos:0.1\n", encoding="utf-8")
    variables = render.read_env_file(ROOT / "deploy" / ".env.example") | render.read_env_file(env)
    files = render.render(variables)
    objects = [o for relative, text in files.items() if relative.startswith("base/") and relative != "base/kustomization.yaml"
               for o in _documents(text)]
    compose = yaml.safe_load((ROOT / "deploy" / "compose.yaml").read_text(encoding="utf-8"))["services"]
    for obj in objects:
        if obj["kind"] not in ("Deployment", "Job"):
            continue
        service = obj["metadata"]["labels"]["app.kubernetes.io/component"]
        (container,) = obj["spec"]["template"]["spec"]["containers"]
        env_values = {e["name"]: e.get("value") for e in container["env"]}
        assert env_values["AGOS_RUN__RUN_ID"] == "val-2"
        assert env_values["AGOS_ZENOH__CONNECT"] == "tcp/agos-router:7500"
        assert container["image"] == "registry.example.org/agos:0.1"
        assert container["args"] == [a.replace("$$", "$") for a in compose[service]["command"]]
    world = next(o for o in objects if o["metadata"]["name"] == "agos-world")
    assert world["spec"]["replicas"] == 8
    service = next(o for o in objects if o["kind"] == "Service")
    assert service["spec"]["ports"][0]["port"] == 7500
    job = next(o for o in objects if o["kind"] == "Job")
    assert job["spec"]["template"]["spec"]["containers"][0]["command"] == ["/bin/sh", "-c"]
    assert 'exec agos eval --connect "$AGOS_ZENOH__CONNECT"' in job["spec"]["template"]["spec"]["containers"][0]["args"][0]


def test_what_the_renderer_cannot_map_stops_it_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    variables = render.read_env_file(ROOT / "deploy" / ".env.example")
    text = (ROOT / "deploy" / "compose.yaml").read_text(encoding="utf-8")
    ported = tmp_path / "ported.yaml"
    ported.write_text(text.replace('    command: ["router"]\n', '    command: ["router"]\n    ports: ["7447:7447"]\n'),
                      encoding="utf-8")
    with pytest.raises(render.RenderError, match=r"^compose.yaml: router: key 'ports' has no Kubernetes mapping"):
        render.render(variables, compose=ported)
    unknown = tmp_path / "unknown.yaml"
    unknown.write_text(text.replace("${AGOS_COMM:-ideal}", "${AGOS_CHANNEL:-ideal}"), encoding="utf-8")
    with pytest.raises(render.RenderError, match=r"\$\{AGOS_CHANNEL\} is not in deploy/.env.example"):
        render.render(variables, compose=unknown)
    bad_env = tmp_path / "bad.env"
    bad_env.write_text("AGOS_RUN val-2\n", encoding="utf-8")
    assert render.main(["--env-file", str(bad_env), "--out", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err == f"render: {bad_env}:1: not NAME=VALUE: 'AGOS_RUN val-2'\n"


def test_check_names_the_files_that_differ(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "k8s"
    assert render.main(["--out", str(out)], out=lambda line: None) == 0
    assert render.main(["--out", str(out), "--check"]) == 0
    (out / "base" / "world.yaml").write_text("edited\n", encoding="utf-8")
    assert render.main(["--out", str(out), "--check"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("render: base/world.yaml in ") and err.count("\n") == 1


def _with_gpu(objects: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """``objects`` with the patches of the GPU component (deploy/k8s/components/gpu) applied."""
    component = _committed("components/gpu/kustomization.yaml")[0]
    assert component["kind"] == "Component"
    objects = list(objects)
    for entry in component["patches"]:
        patch = _committed(f"components/gpu/{entry['path']}")[0]
        target = [o for o in objects if (o["kind"], o["metadata"]["name"]) == (patch["kind"], patch["metadata"]["name"])]
        assert len(target) == 1, f"{entry['path']} patches {patch['kind']} {patch['metadata']['name']}: not one object"
        objects[objects.index(target[0])] = _merge(target[0], patch)
    return objects


def test_the_gpu_overlays_give_world_workers_a_gpu_with_graphics_and_the_run_egl() -> None:
    assert _committed("overlays/gpu/kustomization.yaml")[0]["resources"] == ["../../base"]
    assert _committed("overlays/secure-gpu/kustomization.yaml")[0]["resources"] == ["../secure"]
    base = [o for f in _committed("base/kustomization.yaml")[0]["resources"] for o in _committed(f"base/{f}")]
    for where, objects in (("overlays/gpu", _with_gpu(base)), ("overlays/secure-gpu", _with_gpu(_secure_objects()))):
        for obj in objects:
            _validate(obj, where)
        by_name = {o["metadata"]["name"]: o for o in objects if o["kind"] in ("Deployment", "Job")}
        (world,) = by_name["agos-world"]["spec"]["template"]["spec"]["containers"]
        assert world["resources"]["limits"] == {"nvidia.com/gpu": "1"}
        assert world["resources"]["requests"] == render.RESOURCES["world"]
        env = {e["name"]: e.get("value") for e in world["env"]}
        assert "graphics" in env["NVIDIA_DRIVER_CAPABILITIES"].split(",")
        assert env["AGOS_ZENOH__CONNECT"].startswith("tls/" if "secure" in where else "tcp/")
        (job,) = by_name["agos-eval"]["spec"]["template"]["spec"]["containers"]
        assert {"name": "AGOS_WORLD__RENDERER", "value": "egl"} in job["env"]  # the run's renderer: the orchestrator's
        others = [c for name, o in by_name.items() if name != "agos-world" for c in o["spec"]["template"]["spec"]["containers"]]
        assert not any("limits" in c["resources"] for c in others)


def test_a_compose_gpu_request_renders_as_a_gpu_limit(tmp_path: Path) -> None:
    variables = render.read_env_file(ROOT / "deploy" / ".env.example")
    text = (ROOT / "deploy" / "compose.yaml").read_text(encoding="utf-8")
    replicas = "    deploy:\n      replicas: ${AGOS_WORLDS:-1}\n"
    assert replicas in text

    def world_with(request: str) -> Path:
        path = tmp_path / "compose.yaml"
        path.write_text(text.replace(replicas, replicas + request), encoding="utf-8")
        return path

    gpus = ("      resources:\n        reservations:\n          devices:\n            - driver: nvidia\n"
            "              count: COUNT\n              capabilities: [gpu, graphics]\n")
    files = render.render(variables | {"AGOS_WORLDS": "3"}, compose=world_with(gpus.replace("COUNT", "2")))
    (world,) = _documents(files["base/world.yaml"])
    _validate(world, "base/world.yaml with a GPU request")
    (container,) = world["spec"]["template"]["spec"]["containers"]
    assert world["spec"]["replicas"] == 3
    assert container["resources"]["limits"] == {"nvidia.com/gpu": "2"}
    assert {"name": "NVIDIA_DRIVER_CAPABILITIES", "value": "graphics"} in container["env"]
    files = render.render(variables, compose=world_with(gpus.replace("COUNT", "all")))
    (world,) = _documents(files["base/world.yaml"])  # all: the host's GPUs for each container; one per pod here
    assert world["spec"]["template"]["spec"]["containers"][0]["resources"]["limits"] == {"nvidia.com/gpu": "1"}
    with pytest.raises(render.RenderError, match=r"device count 'none': give a number of GPUs per pod or all"):
        render.render(variables, compose=world_with(gpus.replace("COUNT", "none")))
    with pytest.raises(render.RenderError, match=r"only driver nvidia with capability gpu"):
        render.render(variables, compose=world_with(gpus.replace("nvidia", "amd")))
    with pytest.raises(render.RenderError, match=r"^compose.yaml: world: deploy.resources.limits has no Kubernetes mapping"):
        render.render(variables, compose=world_with("      resources:\n        limits:\n          cpus: '2'\n"))
    # The GPU overlay follows AGOS_WORLD_GPUS, as compose does.
    files = render.render(variables | {"AGOS_WORLD_GPUS": "4"})
    (patch,) = _documents(files["components/gpu/world.yaml"])
    assert patch["spec"]["template"]["spec"]["containers"][0]["resources"]["limits"] == {"nvidia.com/gpu": "4"}
