"""A real Slurm cluster of several nodes on this one machine, for tests of deploy/slurm/.

Debian's slurm-wlm and munge (packages slurmctld, slurmd, slurm-client, munge; .ci/run installs
them). One slurmctld, one ``slurmd -N <node>`` per node, all on this host: every node's address is
127.0.0.1 with a port of its own, and each declares more CPUs than the machine has
(``SlurmdParameters=config_overrides``) so that several one-task-per-node jobs run side by side.
``proctrack/cgroup`` where cgroup v1 is mounted with its freezer (as on this machine): ``scancel``
ends every process of a job's steps, double-forked and SIGTERM-ignoring ones included. Elsewhere
(cgroup v2 without systemd, which Slurm 22.05's cgroup/v2 needs) ``proctrack/pgid``: a job's
processes that leave their process group then escape ``scancel`` (agos's services leave none).

Everything is private to the cluster: its own munge key and daemon socket (``AuthInfo=socket=``),
free ports, state, spool and logs under the work folder, node names with a prefix of this process's
id. Clients (sbatch, squeue, ...) find it through ``SLURM_CONF``: use :meth:`SlurmCluster.env`.
:meth:`SlurmCluster.close` cancels what is left, stops the daemons by their pid (never by name) and
removes the cgroups the nodes made. Needs root (slurmd runs jobs as their user and makes cgroups).
"""

from __future__ import annotations

import contextlib
import os
import pwd
import re
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

PACKAGES = ("slurmctld", "slurmd", "slurm-client", "munge")
BINARIES = {"slurmctld": "slurmctld", "slurmd": "slurmd", "sbatch": "slurm-client", "munged": "munge",
            "mungekey": "munge"}
CGROUP_ROOT = Path("/sys/fs/cgroup")
FREEZER = CGROUP_ROOT / "freezer"


class SlurmError(RuntimeError):
    """The cluster could not be started or used; the message says which step and why."""


def missing_packages() -> list[str]:
    """The Debian packages of :data:`PACKAGES` whose programs are not on PATH (sbin included)."""
    path = os.pathsep.join([os.environ.get("PATH", ""), "/usr/sbin", "/sbin"])
    return sorted({pkg for binary, pkg in BINARIES.items() if shutil.which(binary, path=path) is None})


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _tail(path: Path, lines: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return f"({path} not written)"


class SlurmCluster:
    """``nodes`` slurmd nodes (``<prefix>n1`` ...) of ``cpus_per_node`` CPUs each, in partition
    ``debug``, started under ``work``. A context manager; :meth:`start` waits until every node is idle."""

    def __init__(self, work: Path, *, nodes: int = 3, cpus_per_node: int = 4, kill_wait_s: int = 5,
                 proctrack: str | None = None) -> None:
        """``proctrack``: ``cgroup`` or ``pgid`` (default: cgroup where cgroup v1's freezer is mounted)."""
        self.work = work
        self.proctrack = proctrack or ("cgroup" if (FREEZER / "cgroup.procs").exists() else "pgid")
        self.prefix = f"a{os.getpid()}"
        self.nodes = [f"{self.prefix}n{k}" for k in range(1, nodes + 1)]
        self.cpus_per_node, self.kill_wait_s = cpus_per_node, kill_wait_s
        self.conf = work / "etc" / "slurm.conf"
        self.logs = work / "log"
        self.munge_socket = work / "munge" / "munge.socket"
        self.daemons: dict[str, subprocess.Popen[bytes]] = {}

    # ----- start ------------------------------------------------------------------------------------------------
    def start(self, timeout_s: float = 60.0) -> None:
        if os.geteuid() != 0:
            raise SlurmError("a Slurm cluster on this machine needs root (slurmd starts jobs as their user and makes "
                             "cgroups); run the test as root")
        missing = missing_packages()
        if missing:
            raise SlurmError(f"missing Debian packages {' '.join(missing)}: apt-get install -y {' '.join(PACKAGES)} "
                             "(.ci/run installs them)")
        os.chmod(self.work, 0o755)  # munged runs as user munge and must reach its folder
        for folder in ("etc", "log", "state"):
            (self.work / folder).mkdir(exist_ok=True)
        self._start_munge()
        self._write_conf()
        self._spawn("slurmctld", ["slurmctld", "-D", "-f", str(self.conf)])
        for node in self.nodes:
            self._spawn(f"slurmd-{node}", ["slurmd", "-D", "-N", node, "-f", str(self.conf)])
        deadline = time.monotonic() + timeout_s
        while self.idle_nodes() != len(self.nodes):
            self._check_daemons()
            if time.monotonic() > deadline:
                raise SlurmError(f"{self.idle_nodes()} of {len(self.nodes)} nodes idle after {timeout_s:.0f} s; "
                                 f"{self.logs}/slurmctld.log:\n{_tail(self.logs / 'slurmctld.log')}")
            time.sleep(0.2)

    def _start_munge(self) -> None:
        munge = pwd.getpwnam("munge")
        folder = self.munge_socket.parent
        folder.mkdir(mode=0o700)
        key = folder / "munge.key"
        subprocess.run(["mungekey", "--create", f"--keyfile={key}"], check=True, capture_output=True)
        for path in (folder, key):
            os.chown(path, munge.pw_uid, munge.pw_gid)
        os.chmod(key, 0o600)
        os.chmod(folder, 0o755)  # the socket is reached by slurm's daemons and the jobs' commands
        self._spawn("munged", ["runuser", "-u", "munge", "--", "munged", "--foreground", f"--socket={self.munge_socket}",
                               f"--key-file={key}", f"--pid-file={folder / 'munged.pid'}",
                               f"--seed-file={folder / 'munged.seed'}", f"--log-file={folder / 'munged.log'}"])
        deadline = time.monotonic() + 15
        while not self.munge_socket.exists():
            self._check_daemons()
            if time.monotonic() > deadline:
                raise SlurmError(f"munged made no socket within 15 s:\n{_tail(folder / 'munged.log')}")
            time.sleep(0.05)

    def _write_conf(self) -> None:
        w = self.work
        host = socket.gethostname()
        lines = [
            "ClusterName=agostest", f"SlurmctldHost={host}(127.0.0.1)", f"SlurmctldPort={free_port()}",
            "SlurmUser=root", "SlurmdUser=root", "AuthType=auth/munge", "CredType=cred/munge",
            f"AuthInfo=socket={self.munge_socket}",
            f"StateSaveLocation={w / 'state'}", f"SlurmdSpoolDir={w / 'spool-%n'}",
            f"SlurmctldPidFile={w / 'slurmctld.pid'}", f"SlurmdPidFile={w / 'slurmd-%n.pid'}",
            f"SlurmctldLogFile={self.logs / 'slurmctld.log'}", f"SlurmdLogFile={self.logs / 'slurmd-%n.log'}",
            f"ProctrackType=proctrack/{self.proctrack}", "TaskPlugin=task/none",
            "SelectType=select/cons_tres", "SelectTypeParameters=CR_Core", "SlurmdParameters=config_overrides",
            "ReturnToService=2", "MpiDefault=none", "AccountingStorageType=accounting_storage/none",
            "JobAcctGatherType=jobacct_gather/none", f"KillWait={self.kill_wait_s}", "MinJobAge=600",
        ]
        lines += [f"NodeName={node} NodeHostname={host} NodeAddr=127.0.0.1 Port={free_port()} "
                  f"CPUs={self.cpus_per_node} RealMemory=2000 State=UNKNOWN" for node in self.nodes]
        lines.append("PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP")
        self.conf.write_text("\n".join(lines) + "\n")
        if self.proctrack == "cgroup":
            (self.conf.parent / "cgroup.conf").write_text("CgroupPlugin=cgroup/v1\nCgroupAutomount=yes\n")

    def _spawn(self, name: str, argv: list[str]) -> None:
        with (self.logs / f"{name}.out").open("ab") as out:
            self.daemons[name] = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, env=self.env(),
                                                  start_new_session=True)

    def _check_daemons(self) -> None:
        dead = {n: p.returncode for n, p in self.daemons.items() if p.poll() is not None}
        if dead:
            name = next(iter(dead))
            log = self.logs / (f"{name}.log" if name.startswith("slurm") else f"{name}.out")
            raise SlurmError(f"{name} exited with {dead[name]}; {log}:\n{_tail(log)}\n{_tail(self.logs / f'{name}.out')}")

    # ----- use --------------------------------------------------------------------------------------------------
    def env(self, extra: dict[str, str] | None = None) -> dict[str, str]:
        """This process's environment with ``SLURM_CONF`` naming the cluster, without another cluster's
        ``SLURM_*`` variables or the caller's ``AGOS_*`` settings, plus ``extra``."""
        env = {k: v for k, v in os.environ.items() if not k.startswith(("SLURM_", "AGOS_"))}
        env["SLURM_CONF"] = str(self.conf)
        env["PATH"] = os.pathsep.join([env.get("PATH", ""), "/usr/sbin", "/sbin"])
        env.update(extra or {})
        return env

    def run(self, *argv: str, timeout_s: float = 30.0) -> str:
        """A Slurm client command against this cluster; its stdout (SlurmError when it fails)."""
        try:
            done = subprocess.run(argv, env=self.env(), capture_output=True, text=True, timeout=timeout_s, check=False)
        except subprocess.TimeoutExpired:
            raise SlurmError(f"{' '.join(argv)}: no answer within {timeout_s:.0f} s") from None
        if done.returncode != 0:
            raise SlurmError(f"{' '.join(argv)}: exit {done.returncode}: {(done.stderr or done.stdout).strip()}")
        return done.stdout

    def idle_nodes(self) -> int:
        try:
            out = self.run("sinfo", "-h", "-t", "idle,mixed", "-o", "%D", timeout_s=10).split()
        except SlurmError:
            return 0
        return sum(int(n) for n in out if n.isdigit())

    def sbatch(self, script: Path, *args: str, env: dict[str, str] | None = None, cwd: Path | None = None) -> int:
        """Submit ``script`` with ``args`` (before the script) and ``env`` on top of :meth:`env`; the job id."""
        done = subprocess.run(["sbatch", "--parsable", *args, str(script)], env=self.env(env), cwd=cwd,
                              capture_output=True, text=True, timeout=30, check=False)
        if done.returncode != 0:
            raise SlurmError(f"sbatch {script.name}: exit {done.returncode}: {(done.stderr or done.stdout).strip()}")
        return int(done.stdout.strip().split(";")[0])

    def job(self, job_id: int) -> dict[str, str]:
        """``scontrol show job``'s fields of ``job_id`` (JobState, ExitCode, NodeList ...); {} once forgotten."""
        try:
            out = self.run("scontrol", "show", "job", "-o", str(job_id), timeout_s=10)
        except SlurmError:
            return {}
        return dict(re.findall(r"(\w+)=(\S*)", out))

    def queued(self) -> list[int]:
        """Jobs in the queue (pending, running or completing); an array job by its base id (squeue's
        ``<base>_<task>`` or ``<base>_[0-1]``) while any of its tasks is."""
        return sorted({int(j.split("_")[0]) for j in self.run("squeue", "-h", "-o", "%i", timeout_s=10).split()})

    def array_tasks(self, job_id: int) -> list[dict[str, str]]:
        """``scontrol show job``'s fields of each task of array job ``job_id`` (JobId, ArrayTaskId,
        JobState, ExitCode, NodeList ...), in task order; [] once forgotten."""
        try:
            out = self.run("scontrol", "show", "job", "-o", str(job_id), timeout_s=10)
        except SlurmError:
            return []
        tasks = [dict(re.findall(r"(\w+)=(\S*)", line)) for line in out.splitlines() if line.strip()]
        return sorted(tasks, key=lambda t: int(t.get("ArrayTaskId", "0") or 0))

    def wait_gone(self, job_id: int, timeout_s: float) -> float:
        """Seconds until ``job_id`` left the queue (SlurmError after ``timeout_s``)."""
        start = time.monotonic()
        while job_id in self.queued():
            if time.monotonic() - start > timeout_s:
                raise SlurmError(f"job {job_id} still in the queue after {timeout_s:.0f} s: {self.job(job_id)}")
            time.sleep(0.2)
        return time.monotonic() - start

    def job_cgroups(self, job_id: int) -> list[Path]:
        """The cgroup folders of ``job_id`` that still exist (every controller, every node)."""
        return sorted(p for p in CGROUP_ROOT.glob(f"*/slurm_*/uid_*/job_{job_id}") if p.is_dir())

    def daemon_pids(self) -> set[int]:
        """The pids of the cluster's daemons and of their descendants (munged under runuser)."""
        parents: dict[int, int] = {}
        for stat in Path("/proc").glob("[0-9]*/stat"):
            with contextlib.suppress(OSError, ValueError, IndexError):
                parents[int(stat.parent.name)] = int(stat.read_text().rsplit(")", 1)[1].split()[1])
        found = {p.pid for p in self.daemons.values() if p.poll() is None}
        grew = True
        while grew:
            more = {pid for pid, parent in parents.items() if parent in found} - found
            found |= more
            grew = bool(more)
        return found

    # ----- stop -------------------------------------------------------------------------------------------------
    def close(self) -> list[str]:
        """Cancel every job left, stop the daemons (SIGTERM, then SIGKILL after 15 s), remove the nodes'
        cgroups; what could not be cleaned, one line each (empty when all went)."""
        problems: list[str] = []
        if "slurmctld" in self.daemons and self.daemons["slurmctld"].poll() is None:
            with contextlib.suppress(SlurmError, OSError):
                left = self.queued()
                if left:
                    self.run("scancel", *map(str, left))
                    deadline = time.monotonic() + self.kill_wait_s + 15
                    while self.queued() and time.monotonic() < deadline:
                        time.sleep(0.2)
        order = [f"slurmd-{n}" for n in self.nodes] + ["slurmctld", "munged"]
        for name in order:
            proc = self.daemons.get(name)
            if proc is not None and proc.poll() is None:
                proc.terminate()
            if proc is not None:
                try:
                    proc.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(timeout=5)
                    problems.append(f"{name} (pid {proc.pid}) ignored SIGTERM for 15 s: killed")
        for node in self.nodes:
            for top in sorted(CGROUP_ROOT.glob(f"*/slurm_{node}")):
                for folder in sorted((p for p in top.rglob("*") if p.is_dir()), key=lambda p: -len(p.parts)) + [top]:
                    try:
                        folder.rmdir()
                    except OSError as exc:
                        problems.append(f"cgroup {folder}: {exc.strerror}")
        return problems

    def __enter__(self) -> SlurmCluster:
        try:
            self.start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def main(argv: list[str]) -> int:
    """``python tests/support/slurm.py DIR [NODES]``: a cluster under DIR until Ctrl-C or SIGTERM (to try
    deploy/slurm/ by hand: docs/DEPLOY.md, "Slurm")."""
    import signal

    if not argv:
        print("usage: python tests/support/slurm.py DIR [NODES]", file=sys.stderr)
        return 2
    work = Path(argv[0]).resolve()
    work.mkdir(parents=True, exist_ok=True)
    stop = False

    def on_signal(*_: object) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    cluster = SlurmCluster(work, nodes=int(argv[1]) if len(argv) > 1 else 3)
    try:
        cluster.start()
        print(f"nodes {', '.join(cluster.nodes)} idle; in another shell: export SLURM_CONF={cluster.conf}", flush=True)
        while not stop:
            time.sleep(0.5)
    except SlurmError as exc:
        print(f"slurm: {exc}", file=sys.stderr)
        return 1
    finally:
        for problem in cluster.close():
            print(f"cleanup: {problem}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
