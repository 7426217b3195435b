"""Where a run's tasks run: a Dask cluster (local, remote, or batch jobs) or this process, and what every
worker is set to. :class:`Executor` runs task functions and gives their results back as they end;
:func:`executor_for` makes the one a workflow asks for.
"""

from __future__ import annotations

import errno
import logging
import os
import time
from collections.abc import Callable
from contextlib import contextmanager

import numpy as np
from distributed.diagnostics.plugin import WorkerPlugin

from persona.plugins.base import Rejected
from persona.plugins.manager import select, selected
from persona.stores import storage
from persona.stores.chunks import ChunkError
from persona.stores.errors import PersonaError

from .errors import ClusterLost, RunError
from .workflow import TLS, Cluster, Workflow, tls_problem

log = logging.getLogger(__name__)


class Executor:
    """Runs task functions on a Dask cluster (local, remote, or batch jobs: ``batch``, a
    :class:`Cluster` of a batch kind, see :mod:`persona.dag.batch`) or, for "sync", in-process."""

    def __init__(self, scheduler: str, workers: int | None, threads_per_worker: int = 1,
                 memory_limit: str = "auto", batch: Cluster | None = None, storage_options: dict | None = None,
                 tls: TLS | None = None):
        self.scheduler = scheduler
        self.client = None
        self._cluster = None
        self._close_cluster = lambda cluster: cluster.close()
        if scheduler == "sync":
            return
        from distributed import Client, LocalCluster

        if scheduler == "local" and batch is not None:
            from .batch import close, start_batch_cluster

            self._cluster, self.client = start_batch_cluster(batch)
            self._close_cluster = close
        elif scheduler == "local":
            self._cluster = LocalCluster(
                n_workers=workers or os.cpu_count() or 1, threads_per_worker=threads_per_worker,
                processes=True, memory_limit=memory_limit, host="127.0.0.1", dashboard_address="127.0.0.1:0",
                silence_logs=logging.ERROR)
            self.client = Client(self._cluster)
        else:
            if problem := tls_problem(scheduler, tls):  # --scheduler on a workflow with other settings
                raise RunError(f"{problem} (docs/cluster.md, Security)")
            security = None
            if tls is not None:  # mutual TLS: the scheduler checks this certificate, this side the scheduler's
                from distributed.security import Security

                security = Security(tls_ca_file=tls.ca_file, tls_client_cert=tls.cert, tls_client_key=tls.key,
                                    require_encryption=True)
            try:
                self.client = Client(scheduler, timeout="20s", security=security)
            except OSError as exc:
                raise RunError(f"cannot reach the Dask scheduler at {scheduler}: {exc}. Start one with "
                               "`dask scheduler` and `dask worker ADDRESS`, or use --scheduler local"
                               + (" (a tls:// scheduler takes only a certificate its CA signed: cluster.tls)"
                                  if scheduler.startswith("tls://") else "")) from None
        # a lost scheduler: the client logs each reconnection attempt's traceback, and its batched stream
        # the closed connection's (at INFO, when a message was on its way); the run says it once (_lost)
        logging.getLogger("distributed.client").setLevel(logging.CRITICAL)
        logging.getLogger("distributed.batched").setLevel(logging.WARNING)
        # every worker, on any machine: object storage reached as this process does, one thread (one_thread)
        self.client.register_plugin(WorkerSetup(storage_options, local=isinstance(self._cluster, LocalCluster)),
                                    name="persona-worker")

    #: an array argument at least this large (bytes) goes to the cluster once, whatever the number of tasks
    shared_bytes = 1 << 16

    def run(self, fn, argument_lists):
        """Run fn(*args) for each args; yield results as they complete.

        Memory stays flat in the number of tasks. An array argument (of at least
        :attr:`shared_bytes`) is sent once, as a task of its own that every task taking it depends
        on; sent with each task it was one copy per task in this process (the texture cache's 1.1 MB
        mean face, taken by 300 tasks: 0.33 GB). Each task is let go once its result is taken, so no worker
        keeps the results of all of them until the last ends."""
        if self.client is None:
            for args in argument_lists:
                yield _in_one_thread(fn, *args)
            return
        shared = {}

        def send(arg):
            if not (isinstance(arg, np.ndarray) and arg.nbytes >= self.shared_bytes):
                return arg
            if id(arg) not in shared:  # the array kept with its task, so that its id is not reused
                shared[id(arg)] = (arg, self.client.submit(_identity, arg, pure=False))
            return shared[id(arg)][1]

        pending = {self.client.submit(fn, *map(send, args), pure=False) for args in argument_lists}
        try:
            for future in self._as_completed(pending):
                yield self._result(future.result)
        except BaseException:
            self.client.cancel(list(pending))  # the tasks not started yet; a run that goes on must not race them
            raise

    def warm(self, fn, *args) -> None:
        """fn(*args) once on each worker there is now, not waited for and its result dropped: what a later
        step's tasks would load first (:func:`persona.dag.evaluate.warm_up`), loaded while the workers wait
        on the client. Nothing in one process, where it is loaded at first use."""
        if self.client is None:
            return
        from distributed import fire_and_forget

        for address in self.client.scheduler_info()["workers"]:
            fire_and_forget(self.client.submit(fn, *args, workers=[address], allow_other_workers=False, pure=False))

    def compute(self, *collections):
        import dask

        if self.client is None:
            return _in_one_thread(dask.compute, *collections, scheduler="synchronous")
        futures = self.client.compute(list(collections))
        for _ in self._as_completed(set(futures)):
            pass
        return self._result(self.client.gather, futures)

    def _result(self, fetch, *args):
        """fetch(*args), a finished task's result; a RunError, not a traceback, when the scheduler went
        away while it came back (a closed connection, :meth:`_lost`) or when every worker that ran the
        task died under it (Dask's ``KilledWorker``). A task's own error passes."""
        from dask.utils import key_split
        from distributed import KilledWorker
        from distributed.comm.core import CommClosedError

        try:
            return fetch(*args)
        except KilledWorker as exc:
            raise RunError(f"{exc.allowed_failures + 1} Dask workers in turn died while running one task "
                           f"({key_split(exc.task)}; the last on {exc.last_worker.address}): most "
                           "often a worker out of memory, killed by the system or by its nanny. See the workers' "
                           "logs, give each worker more memory (or fewer threads), and re-run the workflow to "
                           "resume (finished shards are kept)") from None
        except OSError as exc:
            if isinstance(exc, CommClosedError) or self.client.status != "running":
                raise self._lost() from None
            raise

    #: seconds the cluster may have no worker at all, with tasks waiting, before the run stops
    workerless_seconds = 120.0

    def _as_completed(self, pending: set):
        """The futures of ``pending`` as they finish, each taken out of it (the set is emptied in
        place: a future held nowhere else is let go once the caller is done with it). When every
        worker is gone (killed, out of walltime) and none comes back within ``workerless_seconds``, or
        the scheduler itself is lost, a RunError rather than a wait without end or a traceback."""
        from concurrent.futures import CancelledError

        from distributed import wait

        gone_since = None
        while pending:
            try:
                done = wait(pending, timeout=2, return_when="FIRST_COMPLETED").done
            except CancelledError:  # Persona cancels none while it waits: the scheduler did, or is gone
                raise self._lost() from None
            except TimeoutError:  # nothing finished in 2 s: is anyone still working?
                if self.client.status != "running":
                    raise self._lost() from None
                if self.client.scheduler_info(n_workers=1).get("workers"):
                    gone_since = None
                elif gone_since is None:
                    gone_since = time.monotonic()
                    log.warning("the Dask scheduler has no worker left; waiting %.0f s for one to come back",
                                self.workerless_seconds)
                elif time.monotonic() - gone_since > self.workerless_seconds:
                    raise ClusterLost(f"every Dask worker left the scheduler ({self.scheduler}) and none came "
                                      f"back within {self.workerless_seconds:.0f} s; the run stops here. Finished "
                                      "shards are kept: start workers again (or run locally) and re-run the "
                                      "workflow to resume") from None
                continue
            pending -= done
            while done:  # popped, so that a future the caller is done with is held by nothing here
                yield done.pop()

    def _lost(self) -> RunError:
        return ClusterLost(f"the run lost the connection to its Dask scheduler ({self.scheduler}): it stopped, or "
                           "the network between them did. Finished shards are kept: start the scheduler and its "
                           "workers again (or run locally) and re-run the workflow to resume")

    def close(self):
        if self.client is not None:
            self.client.close()
        if self._cluster is not None:
            self._close_cluster(self._cluster)


class WorkerSetup(WorkerPlugin):
    """A Dask worker plugin, on every worker present and future: the run's storage options
    (:func:`persona.stores.storage.configure`; sent to the workers, never written anywhere), the
    run's choice of third-party plugins (``PERSONA_PLUGINS``, :func:`persona.plugins.manager.select`),
    OpenCV on one thread (Dask runs a task per worker thread already; OpenCV's own pool of a thread
    per core on top oversubscribes the cores, as Dask's nanny says of OpenMP and BLAS),
    :func:`malloc_for_arrays`, :func:`no_profile` and dask.array imported; in the workers of the run's
    own local cluster, whose scheduler is in the run's process, :class:`_LostConnections`."""

    def __init__(self, options: dict | None, local: bool = False):
        self.options, self.local = options, local
        self.plugins = selected()

    def setup(self, worker) -> None:
        # dask.array imported whole before any task runs: when a worker first imports it in one thread
        # (a graph of dask.array's arriving: the subspace's SVD, the texture basis's), a task's scipy in another,
        # which looks dask.array up in sys.modules, failed on the half-imported module (AttributeError)
        import dask.array  # noqa: F401

        one_thread()  # for the worker's life
        malloc_for_arrays()
        storage.configure(self.options)
        select(self.plugins)
        no_profile(worker)
        quiet_handled_failures()
        if self.local:
            worker_log = logging.getLogger("distributed.worker")
            if not any(isinstance(f, _LostConnections) for f in worker_log.filters):
                worker_log.addFilter(_LostConnections())

    def __repr__(self) -> str:  # no secrets in logs
        return "WorkerSetup(...)"


def _handled(cls=PersonaError) -> set[str]:
    """The names of the errors a run handles itself, with one line of its own: Persona's and a rejection."""
    return {cls.__name__, *(name for sub in cls.__subclasses__() for name in _handled(sub))}


#: how a worker's log gives a task's error when the disk is full (the run says it in one line: ``persona run``)
DISK_FULL = tuple(f"OSError({code}," for code in (errno.ENOSPC, errno.EDQUOT))


def disk_full(exc: BaseException) -> bool:
    """The disk (or the user's quota) is full."""
    return isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT)


def stops_the_run(exc: BaseException) -> bool:
    """An error that stops a whole version-2 run rather than failing the drives that need the person or
    video it met: a damaged chunk (:meth:`Runner.run` recovers it and starts again), a full disk, on which
    no other person, video or drive can be written either (``persona run`` says so, once), or a lost
    scheduler or workers, without which none can be computed."""
    return isinstance(exc, (ChunkError, ClusterLost)) or disk_full(exc)


class _HandledFailures(logging.Filter):
    """Drops a worker's "Compute Failed" log record (the task, its exception and its traceback) when the
    exception is one the run handles itself (:func:`_handled`), or a full disk: the run says it in one line,
    and the dump before it reads as a crash. A task's unexpected error is still logged in full."""

    def __init__(self):
        super().__init__()
        self.names = _handled() | {Rejected.__name__}

    def filter(self, record: logging.LogRecord) -> bool:
        if not str(record.msg).startswith("Compute Failed") or not isinstance(record.args, tuple):
            return True
        text = str(record.args[3]) if len(record.args) > 3 else ""
        return not any(text.startswith(f"{name}(") for name in self.names) and not text.startswith(DISK_FULL)


class _LostConnections(logging.Filter):
    """A worker of the run's own local cluster (its log is the run's console) logs no traceback for a
    connection lost in a way the run handles. Its scheduler is in the run's process, so it loses it only
    when the run closes the cluster: a heartbeat on its way then printed a traceback just before the run's
    own message (a full disk had stopped a batch while tasks still ran; about 1 run in 10); dropped. Another
    worker that died (killed, out of memory) while this one fetched a task's result from it, or sent it one:
    Dask computes the result again and the run goes on; the line stays, its traceback goes."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = str(record.msg)
        if message.startswith("Failed to communicate with scheduler during heartbeat"):
            return False
        if message.startswith(("Worker stream died during communication", "failed during get data with")):
            record.exc_info = record.exc_text = None
        return True


def quiet_handled_failures() -> None:
    """Install :class:`_HandledFailures` on this process's Dask worker log (once)."""
    worker_log = logging.getLogger("distributed.worker")
    if not any(isinstance(f, _HandledFailures) for f in worker_log.filters):
        worker_log.addFilter(_HandledFailures())


def no_profile(worker) -> None:
    """The worker's statistical profiler stopped (it shows in the dashboard only, which nobody
    reads). Every 10 ms it takes every thread's stack with ``sys._current_frames()``, and on CPython
    3.11 before 3.11.9 that can deadlock the worker for good: a garbage collection inside it waits
    for the GIL while holding the interpreter's lock on its threads, which a thread being started
    (zarr starts decoder threads as it reads) holds the GIL to take (python/cpython#106883,
    dask/distributed#8616). A run hung so, every thread of a worker waiting, in a mean face's task."""
    for name in ("profile", "profile-cycle"):
        callback = worker.periodic_callbacks.pop(name, None)
        if callback is not None:
            callback.stop()


def one_thread() -> Callable[[], None]:
    """OpenCV and the BLAS/OpenMP pools set to one thread, in a worker (for good) and around each
    task in-process ("sync"); returns the function that puts the earlier counts back. Dask runs a
    task per worker thread already; a pool of a thread per core on top of it oversubscribes the
    cores. And a task must give the same bytes whatever runs it: a BLAS sum split over two threads
    adds in another order, and the driver's dynamics (a least-squares fit, then a flow that
    amplifies its last bits) differed by up to 0.1 px between a run on Dask workers (BLAS on one
    thread, as Dask's nanny sets it) and one in-process (two threads)."""
    import cv2
    from threadpoolctl import threadpool_limits

    before, limits = cv2.getNumThreads(), threadpool_limits(1)
    cv2.setNumThreads(1)

    def restore() -> None:
        limits.restore_original_limits()
        cv2.setNumThreads(before)
    return restore


def _identity(value):
    """A task that gives back its argument: how :meth:`Executor.run` sends a shared array once."""
    return value


def _in_one_thread(fn, *args, **kwargs):
    """fn(*args, **kwargs) in this process under :func:`one_thread`, the thread counts put back after."""
    restore = one_thread()
    try:
        return fn(*args, **kwargs)
    finally:
        restore()


def malloc_for_arrays() -> None:
    """glibc's malloc set to keep freed blocks of up to 32 MiB for reuse, as its own adaptive rule
    does after the first large free. Dask's nanny starts workers with ``MALLOC_TRIM_THRESHOLD_`` set,
    which turns that rule off: every array of 128 KiB or more (a 244 x 194 float64 image is 370 KiB)
    is then mapped from the kernel and zeroed afresh, and the driver's dynamics ran 1.6 times slower
    in a worker than in a plain process (184 against 117 ms per frame). A no-op off glibc."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.mallopt(-3, 32 << 20)  # M_MMAP_THRESHOLD: blocks below it come from the heap
        libc.mallopt(-1, 64 << 20)  # M_TRIM_THRESHOLD: free heap above it goes back to the kernel
    except (OSError, AttributeError):
        pass


@contextmanager
def executor_for(wf: Workflow, scheduler: str | None = None, workers: int | None = None):
    """The workflow's executor; ``scheduler`` (--scheduler) replaces its cluster.scheduler and kind."""
    c = wf.cluster
    batch = None
    if scheduler is None and c.kind != "local":
        logs = c.log_directory or str(storage.join(wf.output, "worker-logs"))
        batch = c.model_copy(update={"log_directory": logs})
    ex = Executor(scheduler or c.scheduler, workers or c.workers, c.threads_per_worker, c.memory_limit, batch,
                  wf.storage_options.fsspec(), c.tls)
    try:
        yield ex
    finally:
        ex.close()
