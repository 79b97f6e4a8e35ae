"""``make deploy-test``: the compose deployment (deploy/compose.yaml), for real, on a Docker engine.

Not part of ``make test`` (pytest does not collect this file). Phases, each timed:

  tools       apt-get installs docker.io, docker-compose and debootstrap when they are missing
  engine      a running engine, or dockerd started here without its bridge and without iptables
  base image  agos-base:bookworm made by debootstrap (kept between runs), or AGOS_DEPLOY_BASE_IMAGE
  wheelhouse  every locked dependency (requirements.lock.txt) as a wheel in .wheels/ (kept while it does
              not change)
  image       `compose build` of the agos image from that base and wheelhouse (no package index)
  one host    router, evaluator, two agents and 2 world replicas in one project; the eval job runs a
              split to the end; exactly one finished record per episode in the bind-mounted
              results.sqlite, and the world workers exit when the run is over
  three hosts the same compose file as three projects, as on three hosts (core: router, evaluator,
              eval job; worlds: 2 replicas; agents), here on loopback; one world container is killed
              (docker kill) once the first episode is stored; the run still ends with exactly one
              finished record per episode
  secure      compose.secure.yaml: mutual TLS and default-deny access control with `agos certs`
              credentials; a run completes, plain TCP is refused, ca.key is mounted nowhere
  cleanup     every project down with its volumes, the image and its build layers removed, the
              engine stopped when this script started it

Everything listens on 127.0.0.1, on a free port. A step that cannot be done fails the test with the
reason (exit 1); nothing is skipped.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import sqlite3
import subprocess
import sys
import tempfile
import time
import tomllib
from collections import Counter
from pathlib import Path
from typing import ClassVar

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

from support.phases import Failed, phase, print_phases  # noqa: E402

COMPOSE_FILE = ROOT / "deploy" / "compose.yaml"
SECURE_FILE = ROOT / "deploy" / "compose.secure.yaml"
AGOS = ROOT / ".venv" / "bin" / "agos"
WHEELS = ROOT / ".wheels"
IMAGE = "agos:deploy-test"
DEBOOTSTRAP_BASE = "agos-base:bookworm"
BASE_IMAGE = os.environ.get("AGOS_DEPLOY_BASE_IMAGE", DEBOOTSTRAP_BASE)
CONTAINER_UID = 10001
"""The image's user (Dockerfile); bind-mounted folders and keys are handed to it."""
HEALTH_INTERVAL = "5s"
EVAL_TIMEOUT_S = 420


def tail(text: str | bytes | None, lines: int = 30) -> str:
    if isinstance(text, bytes):
        text = text.decode(errors="replace")
    return "\n".join((text or "").rstrip().splitlines()[-lines:])


def sh(cmd: list[str] | str, *, timeout: float = 300, check: bool = True, env: dict[str, str] | None = None,
       log: Path | None = None, what: str | None = None) -> subprocess.CompletedProcess[str]:
    """Run a command; its output goes to ``log`` (appended) when given, else is captured."""
    shell = isinstance(cmd, str)
    what = what or (cmd if shell else " ".join(cmd))
    try:
        if log is not None:
            with log.open("a") as out:
                out.write(f"\n$ {what}\n")
                out.flush()
                proc = subprocess.run(cmd, shell=shell, executable="/bin/bash" if shell else None, env=env, text=True,
                                      stdout=out, stderr=subprocess.STDOUT, timeout=timeout, check=False)
        else:
            proc = subprocess.run(cmd, shell=shell, executable="/bin/bash" if shell else None, env=env, text=True,
                                  capture_output=True, timeout=timeout, check=False)
    except subprocess.TimeoutExpired:
        where = f"; log {log}:\n{tail(log.read_text())}" if log else ""
        raise Failed(f"{what}: still running after {timeout:.0f} s{where}") from None
    if check and proc.returncode != 0:
        output = log.read_text() if log is not None else (proc.stdout or "") + (proc.stderr or "")
        raise Failed(f"{what}: exit {proc.returncode}\n{tail(output)}")
    return proc


def ok(cmd: list[str], timeout: float = 30) -> bool:
    try:
        return subprocess.run(cmd, capture_output=True, timeout=timeout, check=False).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ----- tools, engine, images ----------------------------------------------------------------------------------------

def compose_command() -> list[str] | None:
    if ok(["docker", "compose", "version"]):
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    return None


def engine_running() -> bool:
    return ok(["docker", "info"], timeout=20)


def ensure_tools(work: Path) -> list[str]:
    """Install what is missing (Debian packages); return the compose command."""
    missing = []
    if not shutil.which("docker") or (not engine_running() and not shutil.which("dockerd")):
        missing.append("docker.io")
    if compose_command() is None:
        missing.append("docker-compose")
    if BASE_IMAGE == DEBOOTSTRAP_BASE and not shutil.which("debootstrap"):
        missing.append("debootstrap")
    if missing:
        if os.geteuid() != 0 or not shutil.which("apt-get"):
            raise Failed(f"missing {', '.join(missing)} and cannot install them here (needs root and apt-get)")
        print(f"installing {', '.join(missing)} (apt-get)", flush=True)
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        sh(["apt-get", "update", "-q"], env=env, log=work / "apt.log", timeout=300)
        sh(["apt-get", "install", "-y", "-q", *missing], env=env, log=work / "apt.log", timeout=600)
    else:
        print("docker, compose and debootstrap are installed", flush=True)
    compose = compose_command()
    if compose is None:
        raise Failed("no compose: neither `docker compose` nor `docker-compose` works after installing docker-compose")
    print("compose: " + sh([*compose, "version"]).stdout.splitlines()[0], flush=True)
    return compose


def start_engine(work: Path) -> subprocess.Popen[bytes] | None:
    """The engine, started here when none runs: no default bridge, no iptables (all services use the
    host network). Returns the dockerd process this script must stop, or None."""
    if engine_running():
        print("a Docker engine is running: using it", flush=True)
        return None
    if os.geteuid() != 0:
        raise Failed("no Docker engine is running and starting dockerd needs root")
    dockerd = shutil.which("dockerd")
    if dockerd is None:
        raise Failed("no Docker engine is running and there is no dockerd to start")
    log_path = work / "dockerd.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen([dockerd, "--bridge=none", "--iptables=false"], stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True)
    deadline = time.monotonic() + 60
    while not engine_running():
        if proc.poll() is not None:
            raise Failed(f"dockerd exited with {proc.returncode} before it answered; {log_path}:\n"
                         f"{tail(log_path.read_text())}")
        if time.monotonic() > deadline:
            stop_engine(proc)
            raise Failed(f"dockerd did not answer `docker info` within 60 s; {log_path}:\n{tail(log_path.read_text())}")
        time.sleep(0.5)
    print(f"started dockerd (pid {proc.pid}; --bridge=none --iptables=false)", flush=True)
    return proc


def stop_engine(proc: subprocess.Popen[bytes]) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=40)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=10)
    print(f"stopped dockerd (pid {proc.pid})", flush=True)


def image_ids() -> set[str]:
    return set(sh(["docker", "images", "-a", "-q", "--no-trunc"]).stdout.split())


def container_ids() -> set[str]:
    return set(sh(["docker", "ps", "-a", "-q", "--no-trunc"]).stdout.split())


def containers_since(before: set[str]) -> list[str]:
    return sorted(container_ids() - before)


def container_image(container: str) -> str:
    return sh(["docker", "inspect", "--format", "{{.Image}}", container], check=False).stdout.strip()


def ensure_base_image(work: Path) -> None:
    if ok(["docker", "image", "inspect", BASE_IMAGE]):
        print(f"{BASE_IMAGE}: present (kept from an earlier run)", flush=True)
        return
    if BASE_IMAGE != DEBOOTSTRAP_BASE:
        print(f"{BASE_IMAGE}: not here; the build pulls it", flush=True)
        return
    rootfs = work / "rootfs"
    log = work / "debootstrap.log"
    try:
        sh(["debootstrap", "--variant=minbase", "--include=python3,python3-venv,python3-pip,ca-certificates",
            "bookworm", str(rootfs)], log=log, timeout=600)
        sh(f"set -o pipefail; tar -C {rootfs} -c . | docker import - {DEBOOTSTRAP_BASE}", log=log, timeout=300)
    finally:
        shutil.rmtree(rootfs, ignore_errors=True)
    print(f"{BASE_IMAGE}: made by debootstrap", flush=True)


def ensure_wheelhouse(work: Path) -> None:
    """.wheels/: a wheel of every locked dependency (requirements.lock.txt, exported from uv.lock) and
    of the build backend, for `pip install --no-index` in the image build; agos itself is built from
    the build context."""
    build = sorted(tomllib.loads((ROOT / "pyproject.toml").read_text())["build-system"]["requires"])
    locked = (ROOT / "requirements.lock.txt").read_text()
    wanted = "\n".join([*build, locked])
    stamp = WHEELS / ".requirements"
    if stamp.exists() and stamp.read_text() == wanted and any(WHEELS.glob("*.whl")):
        print(f"{WHEELS.name}/: up to date ({len(list(WHEELS.glob('*.whl')))} wheels)", flush=True)
        return
    WHEELS.mkdir(exist_ok=True)
    sh([sys.executable, "-m", "pip", "wheel", "-q", "-w", str(WHEELS), "-r", str(ROOT / "requirements.lock.txt")],
       log=work / "wheels.log", timeout=600, what="pip wheel (the locked dependencies)")
    sh([sys.executable, "-m", "pip", "wheel", "-q", "-w", str(WHEELS), *build], log=work / "wheels.log", timeout=300,
       what="pip wheel (the build backend)")  # apart: a file with hashes makes pip want a hash for every requirement
    stamp.write_text(wanted)
    print(f"{WHEELS.name}/: {len(list(WHEELS.glob('*.whl')))} wheels", flush=True)


# ----- compose projects ---------------------------------------------------------------------------------------------

class Project:
    """One compose project: a name, its files and the compose variables of this test."""

    live: ClassVar[list[Project]] = []

    def __init__(self, compose: list[str], name: str, files: list[Path], variables: dict[str, str], work: Path) -> None:
        self.compose, self.name, self.files, self.work = compose, name, files, work
        empty = work / "empty.env"  # so that a developer's deploy/.env does not leak into the test
        empty.touch()
        self.env = {k: v for k, v in os.environ.items() if not k.startswith(("AGOS_", "COMPOSE_", "ZENOH_"))}
        self.env.update(variables)
        self.log = work / f"{name}.log"
        self.base = [*compose, "--env-file", str(empty), "-p", name, *(a for f in files for a in ("-f", str(f)))]

    def cmd(self, *args: str) -> list[str]:
        return [*self.base, *args]

    def run(self, *args: str, timeout: float = 300, check: bool = True) -> subprocess.CompletedProcess[str]:
        if self not in Project.live:
            Project.live.append(self)
        return sh(self.cmd(*args), env=self.env, log=self.log, timeout=timeout, check=check,
                  what=f"compose -p {self.name} {' '.join(args)}")

    def containers(self, service: str | None = None) -> list[str]:
        filters = ["--filter", f"label=com.docker.compose.project={self.name}"]
        if service:
            filters += ["--filter", f"label=com.docker.compose.service={service}"]
        return sorted(sh(["docker", "ps", "-a", "--format", "{{.Names}}", *filters]).stdout.split())

    def down(self) -> None:
        self.run("down", "-v", "--remove-orphans", "-t", "30", timeout=180, check=False)
        leftover = self.containers()
        if leftover:
            sh(["docker", "rm", "-f", *leftover], check=False)
        if self in Project.live:
            Project.live.remove(self)


def state(container: str) -> dict:
    out = sh(["docker", "inspect", "--format", "{{json .State}}", container], check=False).stdout
    return json.loads(out) if out.strip() else {}


def run_eval(project: Project, timeout: float = EVAL_TIMEOUT_S) -> str:
    """The eval job to its end; its output."""
    out = project.work / f"{project.name}-eval.log"
    sh(project.cmd("run", "-T", "--rm", "eval"), env=project.env, log=out, timeout=timeout,
       what=f"compose -p {project.name} run --rm eval")
    return out.read_text()


def sample_split(path: Path, per_difficulty: int) -> list[str]:
    path.parent.mkdir(parents=True, exist_ok=True)
    sh([str(AGOS), "episodes", "sample", "--town", "grid-s7", "--per-difficulty", str(per_difficulty), "--out", str(path)],
       timeout=300)
    return [json.loads(line)["episode_id"] for line in path.read_text().splitlines() if line.strip()]


def stored(db: Path, run_id: str) -> list[tuple[str, str, str]]:
    """(episode, status, worker) of every record of the run, read from the evaluator's file."""
    if not db.exists():
        return []
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=10)
    try:
        rows = con.execute("SELECT episode_id, status, record_json FROM episodes WHERE run_id = ?", (run_id,)).fetchall()
    except sqlite3.OperationalError:  # the evaluator has not made the table yet
        return []
    finally:
        con.close()
    return [(e, s, json.loads(r).get("worker_id", "?")) for e, s, r in rows]


def check_records(runs: Path, run_id: str, episodes: list[str]) -> Counter[str]:
    """Exactly one finished record per episode of the split; returns episodes per world worker."""
    db = runs / run_id / "results.sqlite"
    rows = stored(db, run_id)
    ids = [e for e, _, _ in rows]
    if sorted(ids) != sorted(episodes) or len(ids) != len(set(ids)):
        raise Failed(f"{db}: records for {sorted(ids)}, expected one for each of {sorted(episodes)}")
    unfinished = [(e, s) for e, s, _ in rows if s != "finished"]
    if unfinished:
        raise Failed(f"{db}: records not finished: {unfinished}")
    workers = Counter(w for _, _, w in rows)
    print(f"{db}: {len(rows)} records, one finished record per episode; by worker: {dict(workers)}", flush=True)
    return workers


def wait_exited(containers: list[str], timeout_s: float = 60) -> dict[str, int]:
    deadline = time.monotonic() + timeout_s
    while True:
        states = {c: state(c) for c in containers}
        if all(not s.get("Running", False) for s in states.values()) or time.monotonic() > deadline:
            return {c: (-1 if s.get("Running") else int(s.get("ExitCode", -1))) for c, s in states.items()}
        time.sleep(1)


EPISODE_START = re.compile(r"episode (\S+) \(\w+\) starts")
EPISODE_END = re.compile(r"episode (\S+): ")


def busy_world(containers: list[str]) -> str:
    """A world container in the middle of an episode (its last episode line is a start), else the first."""
    for c in containers:
        logs = sh(["docker", "logs", c], check=False)
        last = ""
        for line in (logs.stdout + logs.stderr).splitlines():
            if EPISODE_START.search(line):
                last = "start"
            elif EPISODE_END.search(line):
                last = "end"
        if last == "start":
            return c
    return containers[0]


# ----- phases -------------------------------------------------------------------------------------------------------

def variables(run_id: str, port: int, runs: Path, data: Path, **extra: str) -> dict[str, str]:
    uid = CONTAINER_UID if os.geteuid() == 0 else os.getuid()
    gid = CONTAINER_UID if os.geteuid() == 0 else os.getgid()
    return {"AGOS_IMAGE": IMAGE, "AGOS_PORT": str(port), "AGOS_ROUTER_HOST": "127.0.0.1", "AGOS_LISTEN_HOST": "127.0.0.1",
            "AGOS_RUN": run_id, "AGOS_RUNS": str(runs), "AGOS_DATA": str(data), "AGOS_SPLIT": "split.jsonl",
            "AGOS_UID": str(uid), "AGOS_GID": str(gid), "AGOS_HEALTH_INTERVAL": HEALTH_INTERVAL,
            "AGOS_BASE_IMAGE": BASE_IMAGE, "AGOS_WHEELHOUSE": WHEELS.name, **extra}


def hand_over(path: Path) -> None:
    """Make a bind-mounted path the containers' user's (they do not run as root)."""
    if os.geteuid() == 0:
        os.chown(path, CONTAINER_UID, CONTAINER_UID)


def one_host(compose: list[str], prefix: str, work: Path, runs: Path) -> None:
    data = work / "data-one"
    episodes = sample_split(data / "split.jsonl", per_difficulty=1)
    project = Project(compose, f"{prefix}one", [COMPOSE_FILE], variables("dt-one", free_port(), runs, data), work)
    start = time.monotonic()
    project.run("up", "-d", "--scale", "world=2")
    print(f"up -d --scale world=2: {time.monotonic() - start:.1f} s (router healthy, the others started)", flush=True)
    start = time.monotonic()
    out = run_eval(project)
    print(f"eval job: {time.monotonic() - start:.1f} s for {len(episodes)} episodes (healthchecks of evaluator included)")
    print(tail(out, 14), flush=True)
    worlds = project.containers("world")
    if len(worlds) != 2:
        raise Failed(f"expected 2 world containers, found {worlds}")
    exits = wait_exited(worlds)
    if any(code != 0 for code in exits.values()):
        raise Failed(f"world workers did not exit cleanly after the run: {exits}")
    print(f"world workers exited when the run was over: {exits}", flush=True)
    project.down()  # the evaluator closes its store on SIGTERM: the records are checked after that
    check_records(runs, "dt-one", episodes)


def three_hosts(compose: list[str], prefix: str, work: Path, runs: Path) -> None:
    data = work / "data-hosts"
    episodes = sample_split(data / "split.jsonl", per_difficulty=1)
    base = variables("dt-hosts", free_port(), runs, data)
    core = Project(compose, f"{prefix}core", [COMPOSE_FILE], base, work)
    agents = Project(compose, f"{prefix}agents", [COMPOSE_FILE], base, work)
    worlds = Project(compose, f"{prefix}worlds", [COMPOSE_FILE], base, work)
    start = time.monotonic()
    core.run("up", "-d", "router", "evaluator")
    agents.run("up", "-d", "--no-deps", "agent-uav", "agent-ugv")
    worlds.run("up", "-d", "--no-deps", "--scale", "world=2", "world")
    print(f"three projects up: {time.monotonic() - start:.1f} s", flush=True)
    eval_log = work / f"{core.name}-eval.log"
    db = runs / "dt-hosts" / "results.sqlite"
    with eval_log.open("w") as log:
        job = subprocess.Popen(core.cmd("run", "-T", "--rm", "eval"), env=core.env, stdout=log, stderr=subprocess.STDOUT,
                               text=True)
        try:
            deadline = time.monotonic() + EVAL_TIMEOUT_S
            while not stored(db, "dt-hosts"):
                if job.poll() is not None:
                    raise Failed(f"the eval job ended (exit {job.returncode}) before any episode was stored:\n"
                                 f"{tail(eval_log.read_text())}")
                if time.monotonic() > deadline:
                    raise Failed(f"no episode stored within {EVAL_TIMEOUT_S} s:\n{tail(eval_log.read_text())}")
                time.sleep(0.5)
            first = time.monotonic() - start
            victim = busy_world(worlds.containers("world"))
            sh(["docker", "kill", victim])
            print(f"first episode stored after {first:.1f} s; killed {victim} (docker kill)", flush=True)
            code = job.wait(timeout=max(10.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            job.kill()
            raise Failed(f"the eval job did not end within {EVAL_TIMEOUT_S} s:\n{tail(eval_log.read_text())}") from None
        finally:
            if job.poll() is None:
                job.kill()
    out = eval_log.read_text()
    if code != 0:
        raise Failed(f"the eval job exited {code}:\n{tail(out)}")
    print(tail(out, 16), flush=True)
    killed = state(victim)
    releases = re.search(r"re-leased episodes: \d+", out)
    print(f"{victim}: exit code {killed.get('ExitCode')}, running again: {killed.get('Running')}; "
          f"{releases.group(0) if releases else 'no episode re-leased'}", flush=True)
    for project in (worlds, agents, core):
        project.down()  # the evaluator closes its store on SIGTERM: the records are checked after that
    check_records(runs, "dt-hosts", episodes)


def secure(compose: list[str], prefix: str, work: Path, runs: Path) -> None:
    certs = work / "certs"
    sh([str(AGOS), "certs", "--out", str(certs)])
    for key in certs.glob("*.key"):
        if key.name != "ca.key":
            hand_over(key)  # each container reads its own key (0600) as the image's user
    data = work / "data-one"  # the one-host split
    episodes = [json.loads(line)["episode_id"] for line in (data / "split.jsonl").read_text().splitlines() if line.strip()]
    port = free_port()
    project = Project(compose, f"{prefix}secure", [COMPOSE_FILE, SECURE_FILE],
                      variables("dt-secure", port, runs, data, AGOS_CERTS=str(certs)), work)
    start = time.monotonic()
    project.run("up", "-d", "--scale", "world=2")
    print(f"up -d --scale world=2 (mutual TLS): {time.monotonic() - start:.1f} s", flush=True)
    plain = sh([str(AGOS), "health", "router", "--id", "x", "--connect", f"tcp/127.0.0.1:{port}", "--timeout", "2"],
               check=False, timeout=60, env={**os.environ, "AGOS_ZENOH__CONNECT_TIMEOUT_S": "3"})
    if plain.returncode == 0:
        raise Failed("the secured router answered a plain TCP client")
    print(f"plain TCP client refused: {(plain.stdout + plain.stderr).strip().splitlines()[-1]}", flush=True)
    start = time.monotonic()
    out = run_eval(project)
    print(f"eval job: {time.monotonic() - start:.1f} s for {len(episodes)} episodes")
    print(tail(out, 14), flush=True)
    mounts = []
    for c in project.containers():
        out = sh(["docker", "inspect", "--format", "{{json .Mounts}}", c]).stdout
        mounts += [m["Source"] for m in json.loads(out or "[]")]
    if any(m.endswith("ca.key") for m in mounts):
        raise Failed("ca.key is mounted into a container")
    router_log = sh(["docker", "logs", project.containers("router")[0]], check=False)
    if "mutual TLS" not in router_log.stdout + router_log.stderr:
        raise Failed(f"the router does not say it runs mutual TLS:\n{tail(router_log.stdout + router_log.stderr)}")
    print(f"router: mutual TLS and access control; {len(mounts)} mounts, none of them ca.key", flush=True)
    project.down()
    check_records(runs, "dt-secure", episodes)


def main() -> int:
    if not AGOS.exists():
        print(f"deploy-test: {AGOS} is missing; run `make test` (or make .venv) first", file=sys.stderr)
        return 1
    work = Path(tempfile.mkdtemp(prefix="agos-deploy-test-"))
    os.chmod(work, 0o755)
    runs = work / "runs"
    runs.mkdir()
    hand_over(runs)
    prefix = f"agosdt{os.getpid()}"
    engine: subprocess.Popen[bytes] | None = None
    images_before: set[str] | None = None
    containers_before: set[str] = set()
    failure: str | None = None
    total = time.monotonic()
    try:
        with phase("tools"):
            compose = ensure_tools(work)
        with phase("engine"):
            engine = start_engine(work)
        with phase("base image"):
            ensure_base_image(work)
        with phase("wheelhouse"):
            ensure_wheelhouse(work)
        with phase("image"):
            images_before, containers_before = image_ids(), container_ids()
            build = Project(compose, f"{prefix}build", [COMPOSE_FILE], variables("dt-build", 7447, runs, work), work)
            build.run("build", timeout=900)
            size = sh(["docker", "image", "inspect", "--format", "{{.Size}}", IMAGE]).stdout.strip()
            print(f"{IMAGE}: {int(size) / 1e9:.2f} GB, from {BASE_IMAGE} and {WHEELS.name}/", flush=True)
        with phase("one host: 2 world replicas, eval job"):
            one_host(compose, prefix, work, runs)
        with phase("three hosts (simulated on loopback): a world killed mid-run"):
            three_hosts(compose, prefix, work, runs)
        with phase("secure: mutual TLS, access control"):
            secure(compose, prefix, work, runs)
    except Failed as exc:
        failure = str(exc)
    except KeyboardInterrupt:
        failure = "interrupted"
    finally:
        with phase("cleanup"):
            for project in list(Project.live):
                project.down()
            if images_before is not None:
                new = image_ids() - images_before
                # a failed classic build leaves the container of its failed step behind
                ours = [c for c in containers_since(containers_before) if container_image(c) in new]
                if ours:
                    sh(["docker", "rm", "-f", *ours], check=False)
                sh(["docker", "rmi", "-f", IMAGE], check=False)
                new = image_ids() - images_before
                if new:
                    sh(["docker", "rmi", "-f", *sorted(new)], check=False)
                sh(["docker", "builder", "prune", "-f"], check=False)
            if engine is not None:
                stop_engine(engine)
            shutil.rmtree(work, ignore_errors=True)
    print_phases("deploy-test", time.monotonic() - total, width=62)
    if failure:
        print(f"\ndeploy-test FAILED: {failure}", file=sys.stderr)
        return 1
    print("\ndeploy-test: 3 passed, 0 failed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
