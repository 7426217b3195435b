"""Dask workers as batch jobs (``cluster: {kind: slurm | pbs | sge | lsf}``) through dask-jobqueue.

Persona runs the Dask scheduler in its own process, listening on ``cluster.host`` (default:
the address of this machine's hostname), submits ``cluster.jobs`` jobs, each running one
single-threaded worker process per core, and waits until the first worker joins. The
scheduler runs whatever pickled code reaches its port: ``host`` must be an address only the
cluster's machines reach. docs/cluster.md has the whole story.
"""

from __future__ import annotations

import logging
import shutil
import socket
import subprocess
import time
from pathlib import Path

from .errors import RunError
from .workflow import Cluster

log = logging.getLogger(__name__)

#: kind: (dask_jobqueue's cluster class, the command that shows the jobs {ids})
JOBQUEUE = {
    "slurm": ("SLURMCluster", "`squeue -j {ids}` (once they ended: `sacct -j {ids}`)"),
    "pbs": ("PBSCluster", "`qstat -x {ids}`"),
    "sge": ("SGECluster", "`qstat -j {ids}`"),
    "lsf": ("LSFCluster", "`bjobs {ids}`"),
}


def scheduler_host() -> str:
    """The address of this machine's hostname: where worker nodes find the scheduler by default."""
    name = socket.gethostname()
    try:
        return socket.gethostbyname(name)
    except OSError:
        raise RunError(f"this machine's hostname {name!r} has no address; set cluster.host to an address "
                       "of this machine that the worker nodes reach") from None


def start_batch_cluster(config: Cluster):
    """(the dask-jobqueue cluster, a Client of it), once a worker of its jobs has joined; the
    jobs are cancelled and a RunError raised when none joins within ``config.start_timeout``."""
    kind = config.kind
    try:
        import dask_jobqueue
    except ImportError:
        raise RunError(f"cluster.kind {kind} needs dask-jobqueue, which is not installed: "
                       "pip install dask-jobqueue (in Persona's environment, e.g. .venv/bin/pip)") from None
    from distributed import Client

    class_name, show_jobs = JOBQUEUE[kind]
    cluster_class = getattr(dask_jobqueue, class_name)
    submit = cluster_class.job_cls.submit_command.split()[0]
    if shutil.which(submit) is None:
        raise RunError(f"cluster.kind {kind} submits worker jobs with `{submit}`, which is not on PATH: run "
                       f"Persona on a machine that submits {kind} jobs (a login node), or use another "
                       "cluster.kind. A single-node SLURM for tests: bash .ci/slurm-up.sh")
    host = config.host or scheduler_host()
    logs = Path(config.log_directory).expanduser()
    logs.mkdir(parents=True, exist_ok=True)
    try:  # dask-jobqueue turns a scheduler that cannot listen into an unrelated error: checked first
        socket.create_server((host, 0)).close()
    except OSError as exc:
        raise RunError(f"the Dask scheduler cannot listen on {host} ({exc.strerror or exc}): set cluster.host to "
                       "an address of this machine that the worker nodes reach") from None
    cluster = cluster_class(**job_options(config), log_directory=str(logs),
                            scheduler_options={"host": host, "dashboard_address": "127.0.0.1:0"})
    script = logs / "job.sh"  # what every job runs, for whoever wants to try it by hand
    script.write_text(cluster.job_script())
    try:
        cluster.scale(jobs=config.jobs)
        client = Client(cluster)
        _wait_for_a_worker(cluster, client, config, show_jobs, submit, script)
    except BaseException:
        close(cluster)
        raise
    log.info("%s jobs %s: workers joined the scheduler at %s", kind, _job_ids(cluster), cluster.scheduler_address)
    return cluster, client


def job_options(config: Cluster) -> dict:
    """What each worker job asks of the batch scheduler, as dask-jobqueue's job classes take it: the
    account is SLURM's and PBS's ``account`` and SGE's and LSF's ``project``."""
    charged = {} if config.account is None else {
        "account" if config.kind in ("slurm", "pbs") else "project": config.account}
    return dict(cores=config.cores, processes=config.cores, memory=config.memory, queue=config.queue,
                walltime=config.walltime, job_extra_directives=config.job_extra_directives,
                job_script_prologue=config.job_script_prologue, job_name="persona-worker", **charged)


def close(cluster) -> None:
    """Cancel the jobs and stop the scheduler. distributed asserts on closing that every job it
    created is closing, closed or failed, which dask-jobqueue's jobs do not say themselves: each
    is marked so first (failed: its submission failed), then closing cancels it."""
    from distributed.core import Status

    for job in cluster._created:
        if job.status == Status.created:
            job.status = Status.failed
        elif job.status == Status.running:
            job.status = Status.closing
    cluster.close()


def _job_ids(cluster) -> list[str]:
    return [job.job_id for job in cluster.workers.values() if getattr(job, "job_id", None)]


#: why SLURM holds a pending job (squeue's %r) when it will never start it as it was submitted, and what that means
NEVER_STARTS = {
    "PartitionConfig": "it asks more than the partition allows: more CPUs or memory than any of its nodes has",
    "PartitionNodeLimit": "it asks more nodes than the partition allows",
    "PartitionTimeLimit": "its walltime is over the partition's time limit",
    "BadConstraints": "no node satisfies its constraints",
}


def never_starts(kind: str, ids: list[str]) -> str | None:
    """Why the batch system will never start any of the jobs ``ids`` as submitted (SLURM only: the reason
    each of them waits for, from `squeue`); None when one of them may yet start, or it cannot tell."""
    if kind != "slurm" or not ids:
        return None
    try:
        listed = subprocess.run(["squeue", "-h", "-j", ",".join(ids), "-o", "%T %r"], capture_output=True,
                                text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    rows = [line.split() for line in listed.splitlines() if line.strip()]
    if len(rows) < len(ids) or not all(row[0] == "PENDING" and row[-1] in NEVER_STARTS for row in rows):
        return None
    reason = rows[0][-1]
    return f"{reason}: {NEVER_STARTS[reason]}"


def _wait_for_a_worker(cluster, client, config: Cluster, show_jobs: str, submit: str, script: Path) -> None:
    deadline = time.monotonic() + config.start_timeout
    asked = 0.0  # when the batch system was last asked why the jobs wait
    while not client.scheduler_info(n_workers=1)["workers"]:
        submitted = len(cluster.workers) == config.jobs  # every submission returned, with or without a job id
        if submitted and not _job_ids(cluster):
            raise RunError(f"`{submit}` refused every worker job (its error is printed above). The job script "
                           f"is {script}; fix cluster.queue, cores, memory, walltime or job_extra_directives, "
                           f"or try it by hand: {submit} {script}")
        if submitted and time.monotonic() - asked > 2:
            asked, ids = time.monotonic(), _job_ids(cluster)
            if why := never_starts(config.kind, ids):
                raise RunError(
                    f"{config.kind} will never start the worker jobs {','.join(ids)} as they are: they "
                    f"wait for {why}. Ask for what a node of the partition has (cluster.cores {config.cores}, "
                    f"memory {config.memory}, walltime {config.walltime}, queue, job_extra_directives; "
                    "`sinfo -o '%P %c %m %l'` gives each partition's CPUs, memory and time limit). "
                    f"The job script is {script}. The jobs are cancelled now.")
        if time.monotonic() > deadline:
            ids = ",".join(_job_ids(cluster))
            raise RunError(
                f"no Dask worker joined within {config.start_timeout:.0f} s (cluster.start_timeout) from the "
                f"{config.kind} jobs {ids or '(none submitted yet)'}: they may still wait in the queue, or "
                f"have failed. See them with {show_jobs.format(ids=ids)} and their logs in {script.parent}. "
                f"The scheduler listens on {cluster.scheduler_address}: the worker nodes must reach it "
                "(cluster.host). The jobs are cancelled now.")
        time.sleep(0.5)
