"""``make slurm-test``: deploy/slurm/agos-eval.sbatch for real, on a 3-node Slurm cluster on this machine.

Not part of ``make test`` (pytest does not collect this file; it needs root and Debian's slurm-wlm and
munge, which .ci/run installs). The cluster (tests/support/slurm.py) starts once; phases, each timed:

  cluster     munged, slurmctld and three slurmd (nodes of 4 CPUs on this host, proctrack/cgroup)
  split       two hard grid-s7 episodes of different lengths (flat look, seed 5), the eval split and
              the dataset split; `agos dataset shard` deals the dataset split into 2 shards
  local       beside the cluster, on one host: `agos eval` of the split (heuristic, flat look) and
              `agos dataset build` of the dataset split (flat look, views every 50 m)
  scancel     the eval job (-N3, one world worker per node) is cancelled once its first record is
              stored: the job leaves the queue, no process of it is left, its cgroups are gone, one
              episode is stored and the other is not
  resume      the same sbatch again resumes the run: it plays only the episode not stored; one finished
              record per episode, each equal to the local run's (wall time, worker, run id and
              provenance aside); a world worker on every node joined
  dataset     the dataset build job (-N3, submitted beside the eval job) wrote the same files, byte for
              byte (sha256), as the one-host build; a world worker on every node joined
  sharded     the sharded build: an array job (--array=0-1, -N1 a task, AGOS_DATASET_SHARDS) built one
              shard per task, and a job depending on it (afterok) ran `agos dataset merge`: the merged
              dataset has the same files, byte for byte, as the one-host build
  cleanup     the daemons stopped by pid, the nodes' cgroups removed, no process of the test left

A step that cannot be done fails the test with the reason (exit 1); nothing is skipped. The cluster
tracks a job's processes with proctrack/cgroup where cgroup v1 is mounted, else proctrack/pgid;
SLURM_TEST_PROCTRACK=pgid (or cgroup) picks one.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from collections.abc import Collection
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

from support.phases import Failed, phase, print_phases  # noqa: E402
from support.records import by_episode  # noqa: E402
from support.slurm import SlurmCluster, SlurmError, free_port  # noqa: E402

SCRIPT = ROOT / "deploy" / "slurm" / "agos-eval.sbatch"
AGOS = ROOT / ".venv" / "bin" / "agos"
JOB_TIMEOUT_S = 300.0
DATASET_ARGS = ["--look", "flat", "--capture-every", "50"]


def tail(path: Path, lines: int = 25) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").rstrip().splitlines()[-lines:])
    except OSError:
        return f"({path}: not written)"


def clean_env(**extra: str) -> dict[str, str]:
    """This process's environment without AGOS_* settings (a developer's shell must not leak in), plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("AGOS_")}
    env.update(extra)
    return env


def sample_split(work: Path) -> tuple[Path, Path, list[str]]:
    """The eval split (two hard episodes: a short and a longer one) and the dataset split (the same two,
    its own file: a dataset build's run id is its split's hash)."""
    split = work / "split.jsonl"
    out = subprocess.run([str(AGOS), "episodes", "sample", "--town", "grid-s7", "--difficulty", "hard", "-n", "2",
                          "--seed", "5", "--look", "flat", "--out", str(split)], env=clean_env(), capture_output=True,
                         text=True, timeout=180, check=False)
    if out.returncode != 0:
        raise Failed(f"agos episodes sample: exit {out.returncode}\n{out.stdout}{out.stderr}")
    lines = split.read_text().splitlines()
    dataset = work / "dataset-split.jsonl"
    dataset.write_text("".join(line + "\n" for line in lines))
    return split, dataset, [json.loads(line)["episode_id"] for line in lines]


def stored(db: Path) -> list[dict]:
    """Every record in an evaluator's results file (none while it does not exist)."""
    if not db.exists():
        return []
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=10)
    try:
        return [json.loads(r) for (r,) in con.execute("SELECT record_json FROM episodes")]
    except sqlite3.OperationalError:  # the table is not made yet
        return []
    finally:
        con.close()


def processes_of(job_ids: set[int], folder: Path, *, but: Collection[int] = ()) -> list[str]:
    """Processes still alive, other than this one and ``but``, that belong to one of ``job_ids``
    (SLURM_JOB_ID in their environment), or work in ``folder`` (their current directory or command line
    is there: the one-host runs and their children): 'pid command' each."""
    found = []
    wanted = {f"SLURM_{kind}={j}".encode() for j in job_ids for kind in ("JOB_ID", "ARRAY_JOB_ID")}
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or int(proc.name) == os.getpid() or int(proc.name) in but:
            continue
        try:
            environ = set((proc / "environ").read_bytes().split(b"\0"))
            cmdline = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
            cwd = os.readlink(proc / "cwd")
        except OSError:  # gone meanwhile, or a kernel thread
            continue
        if cmdline and (environ & wanted or str(folder) in cmdline or Path(cwd).is_relative_to(folder)):
            found.append(f"{proc.name} {cmdline[:160]}")
    return found


def wait_job(cluster: SlurmCluster, job: int, what: str, work: Path) -> dict[str, str]:
    """Until ``job`` left the queue; its final state (Failed unless it COMPLETED with exit 0)."""
    try:
        cluster.wait_gone(job, JOB_TIMEOUT_S)
    except SlurmError as exc:
        raise Failed(f"{what}: {exc}\n{tail(work / f'agos-{job}.out')}") from None
    info = cluster.job(job)
    if info.get("JobState") != "COMPLETED" or info.get("ExitCode") != "0:0":
        raise Failed(f"{what}: job {job} ended {info.get('JobState')} exit {info.get('ExitCode')}; "
                     f"{work / f'agos-{job}.out'}:\n{tail(work / f'agos-{job}.out')}")
    return info


def worlds_of(logs: Path) -> dict[str, str]:
    """World worker id -> node name, from the world logs of one job (``<node>-<local id>-j<job>`` ids)."""
    found = {}
    for log in sorted(logs.glob("world-*.log")):
        m = re.search(r"world worker (\S+)-(\d+)-j\d+ serving run", log.read_text())
        if m:
            found[f"{m.group(1)}-{m.group(2)}"] = m.group(1)
    return found


def played(logs: Path) -> list[str]:
    """Episodes the job's world workers started (an episode twice if it was started twice)."""
    return [m.group(1) for log in sorted(logs.glob("world-*.log"))
            for m in re.finditer(r"episode (\S+) \(\w+\) starts", log.read_text())]


def tree_hashes(root: Path, skip: str) -> dict[str, str]:
    """sha256 of every file under ``root`` by relative path, the folder ``skip`` (the build's run) left out."""
    out = {}
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root)
        if path.is_file() and rel.parts[0] != skip:
            out[rel.as_posix()] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def start_local(args: list[str], log: Path, **env: str) -> subprocess.Popen[bytes]:
    """``agos ARGS --port <free>`` on this host, in the work folder (``log``'s), output into ``log``."""
    with log.open("wb") as out:
        return subprocess.Popen([str(AGOS), *args, "--port", str(free_port())], cwd=log.parent, stdout=out,
                                stderr=subprocess.STDOUT, env=clean_env(**env))


def finish_local(proc: subprocess.Popen[bytes], what: str, log: Path) -> None:
    try:
        code = proc.wait(timeout=JOB_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise Failed(f"{what}: still running after {JOB_TIMEOUT_S:.0f} s; {log}:\n{tail(log)}") from None
    if code != 0:
        raise Failed(f"{what}: exit {code}; {log}:\n{tail(log)}")


def stop_on_sigterm(*_: object) -> None:
    """SIGTERM (an interrupted CI kills the test's process group) cleans up as Ctrl-C does: the cluster's
    daemons run in sessions of their own and would outlive this process otherwise."""
    raise KeyboardInterrupt


def main() -> int:
    signal.signal(signal.SIGTERM, stop_on_sigterm)
    signal.signal(signal.SIGHUP, stop_on_sigterm)
    if not AGOS.exists():
        print(f"slurm-test: {AGOS} is missing; run `make .venv/.installed` first", file=sys.stderr)
        return 1
    work = Path(tempfile.mkdtemp(prefix="agos-slurm-test-"))
    cluster = SlurmCluster(work, proctrack=os.environ.get("SLURM_TEST_PROCTRACK"))
    locals_: list[subprocess.Popen[bytes]] = []
    jobs: set[int] = set()
    failure: str | None = None
    total = time.monotonic()
    try:
        with phase("cluster: munged, slurmctld, 3 slurmd"):
            cluster.start()
            print(f"nodes {', '.join(cluster.nodes)} idle (proctrack/{cluster.proctrack}); SLURM_CONF={cluster.conf}",
                  flush=True)
        with phase("split"):
            split, dataset_split, episodes = sample_split(work)
            sharded = work / "ds-sharded"
            cut = subprocess.run([str(AGOS), "dataset", "shard", "--split", str(dataset_split), "--shards", "2", "--out",
                                  str(sharded)], env=clean_env(), capture_output=True, text=True, timeout=60, check=False)
            if cut.returncode != 0:
                raise Failed(f"agos dataset shard: exit {cut.returncode}\n{cut.stdout}{cut.stderr}")
            print(f"eval split {episodes}; dataset split the same, in 2 shards: {sharded}", flush=True)
        run_dir = work / "runs" / "slurm-eval"
        eval_env = {"AGOS": str(AGOS), "AGOS_RUN_DIR": str(run_dir), "AGOS_SPLIT": str(split),
                    "AGOS_POLICY": "heuristic", "AGOS_WORLD__LOOK": "flat"}
        dataset_env = {"AGOS": str(AGOS), "AGOS_DATASET_OUT": str(work / "ds-slurm"), "AGOS_SPLIT": str(dataset_split),
                       "AGOS_DATASET_ARGS": " ".join(DATASET_ARGS)}
        sharded_env = {"AGOS": str(AGOS), "AGOS_DATASET_SHARDS": str(sharded), "AGOS_DATASET_ARGS": " ".join(DATASET_ARGS)}
        sbatch_args = ["-N3", "--ntasks-per-node=1"]
        with phase("submit: eval job, dataset job, shards' array job and merge; one-host eval and build beside them"):
            first = cluster.sbatch(SCRIPT, *sbatch_args, env=eval_env, cwd=work)
            build = cluster.sbatch(SCRIPT, *sbatch_args, env=dataset_env, cwd=work)
            array = cluster.sbatch(SCRIPT, "--array=0-1", "-N1", "--ntasks-per-node=1", env=sharded_env, cwd=work)
            merge = int(cluster.run("sbatch", "--parsable", f"--dependency=afterok:{array}", "-J", "agos-merge",
                                    f"--output={work}/agos-%j.out", "--wrap",
                                    f"{AGOS} dataset merge {sharded} --out {work / 'ds-merged'}").split(";")[0])
            jobs |= {first, build, array, merge}
            local_eval_log, local_ds_log = work / "local-eval.out", work / "local-dataset.out"
            locals_.append(start_local(["eval", "--split", str(split), "--policy", "heuristic", "--workers", "2",
                                        "--run-dir", str(work / "local" / "eval")], local_eval_log, AGOS_WORLD__LOOK="flat"))
            locals_.append(start_local(["dataset", "build", "--split", str(dataset_split), "--out", str(work / "ds-local"),
                                        *DATASET_ARGS], local_ds_log))
            print(f"eval job {first}, dataset job {build}, shards' array job {array}, merge job {merge}; local eval and "
                  "build started", flush=True)

        db = run_dir / "results.sqlite"
        with phase("scancel mid-run"):
            deadline = time.monotonic() + JOB_TIMEOUT_S
            while not stored(db):
                if first not in cluster.queued():
                    raise Failed(f"eval job {first} ended before it stored a record:\n{tail(work / f'agos-{first}.out')}")
                if time.monotonic() > deadline:
                    raise Failed(f"no record stored within {JOB_TIMEOUT_S:.0f} s:\n{tail(work / f'agos-{first}.out')}")
                time.sleep(0.1)
            cancelled_at = time.monotonic()
            cluster.run("scancel", str(first))
            gone_s = cluster.wait_gone(first, 60)
            state = cluster.job(first).get("JobState")
            left = processes_of({first}, run_dir)
            cgroups = cluster.job_cgroups(first)
            kept = sorted(r["episode_id"] for r in stored(db))
            print(f"first record stored; scancel {first}: out of the queue in {gone_s:.1f} s ({state}); "
                  f"processes left {len(left)}, cgroups left {len(cgroups)}; stored {kept}", flush=True)
            if state != "CANCELLED":
                raise Failed(f"job {first} ended {state}, not CANCELLED: the run was over before scancel")
            if left or cgroups:
                raise Failed(f"after scancel of job {first}: processes {left}, cgroups {cgroups}")
            if len(kept) != 1:
                raise Failed(f"stored before the resume: {kept}; expected one of the two episodes (the cancel came "
                             f"{time.monotonic() - cancelled_at:.1f} s after the first record)")

        with phase("resume: the same sbatch again"):
            second = cluster.sbatch(SCRIPT, *sbatch_args, env=eval_env, cwd=work)
            jobs.add(second)
            wait_job(cluster, second, "the resumed eval job", work)
            out = (work / f"agos-{second}.out").read_text()
            if "resume of run slurm-eval" not in out or "1 of 2 episodes already finished" not in out:
                raise Failed(f"job {second} did not resume the run:\n{tail(work / f'agos-{second}.out')}")
            records = stored(db)
            ids = [r["episode_id"] for r in records]
            if sorted(ids) != sorted(episodes) or any(r["status"] != "finished" for r in records):
                raise Failed(f"{db}: records {[(r['episode_id'], r['status']) for r in records]}; expected one finished "
                             f"record for each of {episodes}")
            replayed = played(run_dir / "logs" / f"slurm-{second}")
            if replayed != [e for e in episodes if e not in kept]:
                raise Failed(f"job {second} played {replayed}; only {set(episodes) - set(kept)} was not stored")
            nodes = set(worlds_of(run_dir / "logs" / f"slurm-{second}").values())
            if nodes != set(cluster.nodes):
                raise Failed(f"job {second}: world workers joined from {sorted(nodes)}, not from every node")
            finish_local(locals_[0], "the one-host agos eval", local_eval_log)
            local = by_episode(stored(work / "local" / "eval" / "results.sqlite"), also=("provenance",))
            if by_episode(records, also=("provenance",)) != local:
                differ = [e for e in episodes if by_episode(records, also=("provenance",)).get(e) != local.get(e)]
                raise Failed(f"records differ from the one-host run's for {differ}")
            print(f"job {second}: resumed, played {replayed}; one finished record per episode, equal to the one-host "
                  f"run's; world workers on {sorted(nodes)}", flush=True)

        with phase("dataset: the Slurm build against the one-host build"):
            wait_job(cluster, build, "the dataset build job", work)
            finish_local(locals_[1], "the one-host agos dataset build", local_ds_log)
            run_name = f"dataset-{hashlib.sha256(dataset_split.read_bytes()).hexdigest()[:8]}"
            on_slurm = tree_hashes(work / "ds-slurm", run_name)
            on_host = tree_hashes(work / "ds-local", run_name)
            if not on_host or on_slurm != on_host:
                differ = sorted(k for k in on_slurm.keys() | on_host.keys() if on_slurm.get(k) != on_host.get(k))
                raise Failed(f"the Slurm build differs from the one-host build in {len(differ)} files: {differ[:10]}")
            nodes = set(worlds_of(work / "ds-slurm" / run_name / "logs" / f"slurm-{build}").values())
            if nodes != set(cluster.nodes):
                raise Failed(f"dataset job {build}: world workers joined from {sorted(nodes)}, not from every node")
            print(f"dataset job {build}: {len(on_slurm)} files, the same sha256 as the one-host build's; world workers "
                  f"on {sorted(nodes)}", flush=True)

        with phase("sharded: 2 array tasks, merged, against the one-host build"):
            try:
                cluster.wait_gone(array, JOB_TIMEOUT_S)
            except SlurmError as exc:
                raise Failed(f"the shards' array job: {exc}") from None
            tasks = cluster.array_tasks(array)
            jobs |= {int(t["JobId"]) for t in tasks}
            for t in tasks:
                if t.get("JobState") != "COMPLETED" or t.get("ExitCode") != "0:0":
                    out = work / f"agos-{t.get('JobId')}.out"
                    raise Failed(f"array task {t.get('ArrayTaskId')} (job {t.get('JobId')}) ended {t.get('JobState')} "
                                 f"exit {t.get('ExitCode')}; {out}:\n{tail(out)}")
            if len(tasks) != 2:
                raise Failed(f"array job {array}: {len(tasks)} tasks, not 2")
            wait_job(cluster, merge, "the merge job", work)
            merged = tree_hashes(work / "ds-merged", run_name)
            if merged != on_host:
                differ = sorted(k for k in merged.keys() | on_host.keys() if merged.get(k) != on_host.get(k))
                raise Failed(f"the merged shards differ from the one-host build in {len(differ)} files: {differ[:10]}; "
                             f"{work / f'agos-{merge}.out'}:\n{tail(work / f'agos-{merge}.out')}")
            shard_episodes = [sorted(json.loads((sharded / "shards" / str(k) / "manifest.json").read_text())["episodes"])
                              for k in (0, 1)]
            print(f"array job {array}: tasks {[(t['ArrayTaskId'], t['JobId'], t['NodeList']) for t in tasks]} built "
                  f"shards {shard_episodes}; merge job {merge}: {len(merged)} files, the same sha256 as the one-host "
                  "build's", flush=True)

        with phase("no process left"):
            left = processes_of(jobs, work, but=cluster.daemon_pids())
            cgroups = [c for j in jobs for c in cluster.job_cgroups(j)]
            if left or cgroups:
                raise Failed(f"left after the jobs: processes {left}, cgroups {cgroups}")
            print(f"jobs {sorted(jobs)}: no process and no cgroup left", flush=True)
    except (Failed, SlurmError) as exc:
        failure = str(exc)
    except KeyboardInterrupt:
        failure = "interrupted"
    finally:
        with phase("cleanup"):
            for proc in locals_:
                if proc.poll() is None:
                    proc.terminate()
                    with contextlib.suppress(subprocess.TimeoutExpired):
                        proc.wait(timeout=20)
                    if proc.poll() is None:
                        proc.kill()
            problems = cluster.close()
            problems += [f"cgroup {p} left" for n in cluster.nodes for p in Path("/sys/fs/cgroup").glob(f"*/slurm_{n}")]
            problems += [f"process left: {p}" for p in processes_of(jobs, work)]
            if problems and failure is None:
                failure = "cleanup: " + "; ".join(problems)
            elif not problems:
                print("daemons stopped, cgroups of the nodes removed, no process of the test left", flush=True)
            if failure is None:
                shutil.rmtree(work, ignore_errors=True)
    print_phases("slurm-test", time.monotonic() - total)
    if failure:
        print(f"\nslurm-test FAILED: {failure}\n(work folder kept: {work})", file=sys.stderr)
        return 1
    print("\nslurm-test: passed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
