"""``cluster: {kind: slurm}``: Dask workers as SLURM batch jobs (dask-jobqueue), on a real SLURM.

CI starts a single-node SLURM with .ci/slurm-up.sh (called by `bash setup.sh test`); without
`sbatch` or an idle node these tests skip with the reason.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest

from persona.dag.batch import scheduler_host
from persona.dag.collection import mean_face
from persona.dag.errors import RunError
from persona.dag.executor import executor_for
from persona.dag.inputs import resolve_inputs
from persona.dag.runner import Runner, run_workflow
from persona.dag.workflow import Cluster, WorkflowError, load_workflow, parse_workflow

from pipeline import PERSONA, assert_same_store, write_photos, write_workflow


def _slurm_problem() -> str | None:
    """Why no job can run on SLURM here, or None."""
    if shutil.which("sbatch") is None:
        return "sbatch not found: start a single-node SLURM with `bash .ci/slurm-up.sh` (root, Debian)"
    states = subprocess.run(["sinfo", "-h", "-o", "%T"], capture_output=True, text=True, timeout=30)
    if not {"idle", "mixed"} & set(states.stdout.split()):
        return f"no idle SLURM node (sinfo: {(states.stdout + states.stderr).strip() or 'nothing'}): bash .ci/slurm-up.sh"
    return None


_PROBLEM = _slurm_problem()
needs_slurm = pytest.mark.skipif(_PROBLEM is not None, reason=str(_PROBLEM))

SLURM = {"kind": "slurm", "jobs": 1, "cores": 1, "memory": "2GiB", "start_timeout": 120}


def _queued() -> set[str]:
    """The ids of the jobs in SLURM's queue."""
    return set(subprocess.run(["squeue", "-h", "-o", "%i"], capture_output=True, text=True).stdout.split())


def _listed(jobs: str) -> str:
    """`squeue`'s lines (id, state) for the jobs ``jobs`` (ids, comma-separated)."""
    return subprocess.run(["squeue", "-h", "-j", jobs, "-o", "%i %T"], capture_output=True, text=True).stdout


@pytest.mark.parametrize("kind, line", [("slurm", "#SBATCH -A faces"), ("pbs", "#PBS -A faces"),
                                        ("sge", "#$ -P faces"), ("lsf", '#BSUB -P "faces"')])
def test_the_account_and_queue_reach_each_kind_of_job_script(kind, line):
    """cluster.account charges the jobs (SLURM, PBS: account; SGE, LSF: project), as the job script says."""
    import dask_jobqueue

    from persona.dag.batch import JOBQUEUE, job_options

    config = Cluster(kind=kind, account="faces", queue="compute", cores=2)
    job = getattr(dask_jobqueue, JOBQUEUE[kind][0]).job_cls(scheduler="tcp://127.0.0.1:1", **job_options(config))
    script = job.job_script()
    assert line in script.splitlines(), script
    assert "compute" in script


def test_a_batch_kind_and_a_scheduler_address_do_not_mix():
    base = {"name": "x", "store": "s.zarr", "output": "o", "puppet": {"photos": "p"}}
    with pytest.raises(WorkflowError, match='kind "slurm" starts its own scheduler'):
        parse_workflow({**base, "cluster": {"kind": "slurm", "scheduler": "tcp://10.0.0.5:8786"}})
    with pytest.raises(WorkflowError, match="cluster.kind"):
        parse_workflow({**base, "cluster": {"kind": "kubernetes"}})
    with pytest.raises(WorkflowError, match='cluster.memory: .*"lots" is not an amount of memory'):
        parse_workflow({**base, "cluster": {"kind": "slurm", "memory": "lots"}})
    old = parse_workflow({**base, "cluster": {"scheduler": "local", "workers": 2}})  # workflows before kind
    assert (old.cluster.kind, old.cluster.workers) == ("local", 2)


def test_no_sbatch_no_dask_jobqueue_or_a_host_not_here_says_so(tmp_path, synthetic_photos, monkeypatch):
    photos = write_photos(tmp_path / "photos", synthetic_photos[:1])
    wf = load_workflow(write_workflow(tmp_path, str(photos), cluster=SLURM))
    with monkeypatch.context() as m:
        m.setenv("PATH", str(tmp_path))  # no sbatch here
        with pytest.raises(RunError, match=r"`sbatch`, which is not on PATH.*slurm-up\.sh"):
            run_workflow(wf, progress=False)
    if shutil.which("sbatch"):
        elsewhere = load_workflow(write_workflow(tmp_path, str(photos), cluster={**SLURM, "host": "192.0.2.1"}))
        with pytest.raises(RunError, match="cannot listen on 192.0.2.1 .*set cluster.host"):
            run_workflow(elsewhere, progress=False)
    monkeypatch.setitem(sys.modules, "dask_jobqueue", None)  # import dask_jobqueue fails
    with pytest.raises(RunError, match="needs dask-jobqueue, which is not installed: pip install dask-jobqueue"):
        run_workflow(wf, progress=False)


@needs_slurm
def test_a_refused_job_and_a_job_that_never_starts_stop_the_run_with_what_to_do(tmp_path, synthetic_photos):
    photos = write_photos(tmp_path / "photos", synthetic_photos[:1])
    refused = load_workflow(write_workflow(tmp_path, str(photos), cluster={**SLURM, "queue": "no-such-partition"}))
    with pytest.raises(RunError, match=r"`sbatch` refused every worker job.*sbatch .*job\.sh"):
        run_workflow(refused, progress=False)
    # a job held in the queue for an hour: no worker within the timeout, the job cancelled
    queued = load_workflow(write_workflow(tmp_path, str(photos), cluster={
        **SLURM, "start_timeout": 3, "job_extra_directives": ["--begin=now+3600"]}))
    with pytest.raises(RunError, match=r"no Dask worker joined within 3 s .* slurm jobs (\d+).*squeue -j") as err:
        run_workflow(queued, progress=False)
    job = err.value.args[0].split("slurm jobs ")[1].split(":")[0]
    assert str(tmp_path / "out" / "worker-logs") in str(err.value)
    listed = _listed(job)
    assert "PENDING" not in listed, listed  # cancelled (squeue may still show it CANCELLED for a moment)


@needs_slurm
def test_a_job_larger_than_any_node_stops_the_run_at_once_with_what_to_ask(tmp_path, synthetic_photos):
    """A worker job of more cores than any node of the partition has: SLURM queues it, to wait for ever
    ("PartitionConfig"); the run stops within seconds, not after cluster.start_timeout, saying what to
    change, and cancels the job."""
    cpus = max(int(c.rstrip("+")) for c in subprocess.run(["sinfo", "-h", "-o", "%c"], capture_output=True,
                                                          text=True).stdout.split())
    photos = write_photos(tmp_path / "photos", synthetic_photos[:1])
    wf = load_workflow(write_workflow(tmp_path, str(photos), cluster={**SLURM, "cores": cpus + 1}))
    start = time.monotonic()
    with pytest.raises(RunError, match=r"slurm will never start the worker jobs (\d+) as they are: they wait for "
                                       r"PartitionConfig: .* than any of its nodes has\. .*cluster\.cores") as err:
        run_workflow(wf, progress=False)
    assert time.monotonic() - start < SLURM["start_timeout"] / 2
    job = err.value.args[0].split("worker jobs ")[1].split(" ")[0]
    listed = _listed(job)
    assert "PENDING" not in listed, listed


@needs_slurm
def test_a_terminated_run_cancels_its_worker_jobs_and_says_how_to_resume(tmp_path, synthetic_photos):
    """SIGTERM to `persona run` (SLURM's own when the run is itself a job that is cancelled or reaches its
    time limit, `kill`, a timeout) stops it as Ctrl-C does: its worker job, held in the queue here, is
    cancelled, not left there to start later with no scheduler, and the run says how to resume (exit
    status 143)."""
    photos = write_photos(tmp_path / "photos", synthetic_photos[:1])
    workflow = write_workflow(tmp_path, str(photos), cluster={**SLURM, "job_extra_directives": ["--begin=now+3600"]})
    before = _queued()
    run = subprocess.Popen([PERSONA, "run", str(workflow), "--quiet"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 60
        while not (ours := _queued() - before) and time.time() < deadline and run.poll() is None:
            time.sleep(0.2)
        assert ours, "the run submitted no job"
        run.send_signal(signal.SIGTERM)
        err = run.communicate(timeout=120)[1]
    finally:
        run.kill()
    assert run.returncode == 143, err
    assert "The run stopped" in err and "resume with" in err
    listed = _listed(",".join(ours))
    assert "PENDING" not in listed, listed  # cancelled (squeue may still show it CANCELLED for a moment)


@pytest.mark.slow  # 15-30 s: a worker job's start, and every per-photo stage twice
@needs_slurm
def test_slurm_workers_give_the_same_store_as_a_local_run(tmp_path, synthetic_photos):
    """The per-photo stages run on a Dask worker that sbatch started (its SLURM_JOB_ID is seen in a
    task), and the store is the same as a run in this process."""
    photos = write_photos(tmp_path / "photos", synthetic_photos[:6])
    batch, local = tmp_path / "slurm", tmp_path / "local"
    for folder, cluster in ((batch, SLURM), (local, {"scheduler": "sync"})):
        folder.mkdir()
        wf = load_workflow(write_workflow(folder, str(photos), cluster=cluster))
        with executor_for(wf) as ex:
            runner = Runner(wf, ex, progress=False)
            coll, video = runner.collection("puppet", resolve_inputs(wf)["puppet"])
            runner.run_photo_stages(coll, video)
            mean_face(runner, coll)
            if folder == batch:
                scheduler = ex._cluster.scheduler  # on the hostname's address; the dashboard on loopback
                assert scheduler.address.startswith(f"tcp://{scheduler_host()}:")
                assert {s.getsockname()[0] for s in scheduler.http_server._sockets.values()} == {"127.0.0.1"}
                jobs = {job.job_id for job in ex._cluster.workers.values()}
                seen = ex.client.submit(os.getenv, "SLURM_JOB_ID", pure=False).result()
                queue = subprocess.run(["squeue", "-h", "-o", "%i %j %T"], capture_output=True, text=True).stdout
    assert len(jobs) == 1 and seen in jobs, (jobs, seen)
    assert f"{seen} persona-worker RUNNING" in queue, queue
    assert (batch / "out" / "worker-logs" / f"persona-worker-{seen}.err").is_file()
    assert_same_store(batch / "run.zarr", local / "run.zarr")


@needs_slurm
def test_a_batch_of_drives_on_slurm_gives_the_same_store_as_a_local_run(batch, tmp_path):
    """Fig. 8 in small (docs/batch.md): two puppets built once and driven by one driver's video (conftest.py's
    batch), every stage through Dask workers that sbatch started, gives the same store, array for array, as
    the batch's uninterrupted run on a local cluster (whose store is the one a run in this process makes:
    test_people.py's two-at-a-time test)."""
    folder, workflow, _, _ = batch
    wf = load_workflow(workflow, [f"store={tmp_path / 'slurm.zarr'}", f"output={tmp_path / 'slurm'}",
                                  f"cluster={json.dumps(SLURM)}"])
    report = run_workflow(wf, progress=False)
    assert set(report["drives"]) == {"bea_al_al", "cy_al_al"}
    assert (tmp_path / "slurm" / "worker-logs").is_dir()  # the batch jobs' logs
    assert_same_store(tmp_path / "slurm.zarr", folder / "reference.zarr")
