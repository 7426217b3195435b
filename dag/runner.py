"""Run a workflow: build each collection's stage graph and execute it with Dask.

Stages run in order; each maps its backend over the shards of a collection that are
not done yet. A shard is done when its status is written, which happens after its
outputs, so an interrupted run, run again, resumes where it stopped. A stage whose
cache key (backend, version, params, inputs) changed starts over.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import sys
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
from distributed.diagnostics.plugin import WorkerPlugin

from persona.plugins.base import Rejected
from persona.plugins.face.fiducials import mean_shape
from persona.plugins.hookspecs import hookimpl
from persona.plugins.manager import get_plugin_manager, select, selected
from persona.stores import lock, media, output, storage, verify
from persona.stores.chunks import ChunkError
from persona.stores.errors import InputError, PersonaError
from persona.stores.layout import OK, PENDING, REJECTED, Cast, Collection, open_store, rejections
from persona.stores.paths import item
from persona.stores.provenance import Provenance, cache_key

from . import graph as dag_graph
from . import stages as st
from .drive import write_videos
from .errors import ClusterLost, RunError
from .evaluate import evaluate
from .export import write_drive_glb
from .graph import Target
from .report import write_batch_page, write_run_report
from .workflow import TLS, Cluster, VideoRange, Workflow, tls_problem

log = logging.getLogger(__name__)


def persona_version() -> str:
    import importlib.metadata

    try:
        return importlib.metadata.version("persona")
    except importlib.metadata.PackageNotFoundError:
        return "0+unknown"


# -- executing tasks ---------------------------------------------------------------------

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
    :func:`malloc_for_arrays` and :func:`no_profile`; in the workers of the run's own local cluster, whose
    scheduler is in the run's process, :class:`_LostConnections`."""

    def __init__(self, options: dict | None, local: bool = False):
        self.options, self.local = options, local
        self.plugins = selected()

    def setup(self, worker) -> None:
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


def _stops_the_run(exc: BaseException) -> bool:
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


# -- lifecycle hooks: timing ---------------------------------------------------------------

@dataclass
class StageTimer:
    """A built-in plugin that records every stage's times and counts.

    ``wall_seconds``: from the stage's start to its end (per-photo stages run fused per
    shard, so they share one wall time); ``task_seconds``: the stage's own compute time
    summed over all tasks and workers.
    """

    records: list = field(default_factory=list)
    _start: dict = field(default_factory=dict)

    @hookimpl
    def persona_before_stage(self, stage, collection, info):
        self._start[(stage, collection)] = time.perf_counter()

    @hookimpl
    def persona_after_stage(self, stage, collection, summary):
        seconds = time.perf_counter() - self._start.pop((stage, collection), time.perf_counter())
        self.records.append({"stage": stage, "collection": collection, "wall_seconds": round(seconds, 3),
                             "task_seconds": round(summary.get("seconds", 0.0), 3),
                             **{k: v for k, v in summary.items() if k != "seconds"}})


# -- the run -----------------------------------------------------------------------------

class _Lines:
    """Progress for a log file or a batch job: one timestamped line when a step starts and one when
    it ends, instead of a bar redrawn with carriage returns."""

    def __init__(self, what: str, total: int, unit: str, initial: int):
        self.what, self.total, self.unit, self.done = " ".join(what.split()), total, unit, initial
        self.start = time.monotonic()
        self._say(f"started: {total} {self.units}" + (f", {initial} done before" if initial else ""))

    @property
    def units(self) -> str:
        return self.unit if self.total == 1 else f"{self.unit}s"

    def _say(self, text: str) -> None:
        print(f"{time.strftime('%H:%M:%S')} {self.what}: {text}", file=sys.stderr, flush=True)

    def update(self, n: int = 1) -> None:
        self.done += n

    def close(self) -> None:
        """The step's last line: "done" when every item is counted, "stopped" when the run stopped
        before (an error, a kill of the scheduler, Ctrl-C)."""
        if self.start is not None:
            word = "done" if self.done >= self.total else "stopped"
            self._say(f"{word}: {self.done} of {self.total} {self.units} in {time.monotonic() - self.start:.1f} s")
            self.start = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def progress(what: str, total: int, unit: str = "frame", *, initial: int = 0, enabled: bool = True):
    """A progress display with ``update(n)`` and ``close()`` (also a context manager): a tqdm bar on a
    terminal, :class:`_Lines` when stderr is a file or pipe, nothing when not ``enabled``."""
    from tqdm.auto import tqdm

    if enabled and not sys.stderr.isatty():
        return _Lines(what, total, unit, initial)
    return tqdm(total=total, initial=initial, desc=what, unit=unit, disable=not enabled, leave=True,
                dynamic_ncols=True)


def resolve_inputs(wf: Workflow, *, keep_going: bool = False) -> dict[str, list[media.Source] | InputError]:
    """Every collection's photos and video frames, resolved before any work is done or any file
    created: paths that do not exist, empty folders and frame ranges, files that are not videos
    where a video is needed and videos that do not open raise an :class:`InputError` naming them
    (with ``keep_going``, the error is that collection's value instead: a batch's drives that do
    not use it still run). Takes a second or two (a video's frames are counted, not decoded). The
    buckets of a store and an output in object storage are reached first
    (:func:`persona.stores.storage.check`)."""
    storage.check(wf.store, "store")
    storage.check(wf.output, "output")
    resolved = {}
    for plan in wf.collections():
        try:
            sources = media.resolve_sources(_media_spec(plan.photos), wf.base_dir)
            if plan.video and any(s.frame is None for s in sources):
                where = "driver.video" if wf.version == 1 else "drives: video"
                raise InputError(f"{where}: {sources[0].path} is not a video; give a video file (.mp4, .mov, "
                                 "...) or a range {video: PATH, start: 0, stop: N}")
        except InputError as exc:
            if not keep_going:
                raise
            resolved[plan.path] = exc
            continue
        resolved[plan.path] = sources
    return resolved


def _media_spec(spec):
    if isinstance(spec, list):
        return [_media_spec(item) for item in spec]
    return spec.model_dump() if isinstance(spec, VideoRange) else spec


@dataclass
class Runner:
    wf: Workflow
    executor: Executor
    progress: bool = True
    pm: object = None
    timer: StageTimer = field(default_factory=StageTimer)
    #: why a collection has no 3D shape in this run (its arrays from an earlier run must not be used)
    shape_problems: dict = field(default_factory=dict)
    #: the collections' descriptor centroids the evaluation computed in this run (dag.evaluate.photo_centroid)
    centroids: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.pm is None:
            self.pm = get_plugin_manager()[0]
        self.pm.register(self.timer)
        self.root = open_store(self.wf.store)
        self.version = persona_version()
        self.graph = dag_graph.build(self.wf)

    def _ingest_params(self) -> dict:
        return self.wf.backendless("ingest")

    def align_params(self) -> dict:
        return self.wf.backendless("align")

    def motion_params(self) -> dict:
        return self.wf.backendless("motion")

    def render_params(self):
        """The render backend's params, validated and with its defaults (the mouth and teeth steps read them)."""
        name, params = self.wf.stage("render")
        return st.default_registry().get("render", name)(params).params

    def collection(self, path: str, sources: list[media.Source]) -> tuple[Collection, bool]:
        """Open (or create anew, when its sources or ingest params changed) a collection of the
        resolved ``sources`` (:func:`resolve_inputs`)."""
        params = self._ingest_params()
        # the frames of one video are decoded in one sequential pass; a mix of photos, videos and
        # video ranges photo by photo (a frame decoded from the start of its video: exact)
        video = sources[0].path if all(s.frame is not None and s.path == sources[0].path for s in sources) else None
        stats = [(s.path, s.frame, *storage.signature(s.path)) for s in sources]
        prov = st.provenance("ingest", params=params, inputs={"sources": cache_key(sources=stats)},
                             persona_version=self.version)
        coll = Collection(self.root, path)
        if not st.is_done(coll, prov, *st.STAGES["ingest"].done):
            self._create_collection(coll, sources, video, params, prov)
        return coll, video is not None

    def _create_collection(self, coll, sources, video, params, prov):
        group = self.root.require_group(coll.path)
        n = len(sources)
        if video:
            with media.VideoReader(video) as reader:
                fps, size = reader.fps, (reader.height, reader.width)
            scale = min(1.0, params["max_side"] / max(size))
            canvas = [int(round(size[0] * scale)), int(round(size[1] * scale))]
            frames = [s.frame for s in sources]
            group.attrs.update({"fps": fps, "video": {
                "path": video, "start": min(frames), "stop": max(frames) + 1,
                "step": frames[1] - frames[0] if n > 1 else 1}})
        else:
            canvas = _canvas(sources, params)
        group.attrs.update({"n_photos": n, "photos_per_shard": self.wf.photos_per_shard,
                            "canvas": canvas, "stages": list(st.COLLECTION_STAGES)})
        coll.create("photos/ids", (), str, ("photo",), prov)[:] = np.array([s.id for s in sources])
        coll.create("photos/source", (), str, ("photo",), prov)[:] = np.array([media.stored_path(s.path) for s in sources])
        coll.create("photos/frame", (), "int64", ("photo",), prov, fill_value=-1)[:] = np.array(
            [-1 if s.frame is None else s.frame for s in sources], dtype=np.int64)
        self._create_outputs(coll, st.INGEST, prov)

    def _create_outputs(self, coll: Collection, stage: st.PhotoStage, prov: Provenance) -> None:
        for o in stage.outputs:
            coll.create(o.name, st.output_tail(o, coll.attrs["canvas"]),
                        str if o.dtype == "str" else o.dtype, o.dims, prov)
        coll.create_status(stage.name, prov)

    def steps(self, coll: Collection) -> list[tuple[str, str, dict]]:
        """(stage, backend, params) of every per-photo stage; (re)creates the outputs of
        each stage whose cache key changed, so that it starts over."""
        steps = [("ingest", "-", self._ingest_params())]
        upstream = coll.provenance("status/ingest/state")
        for stage in st.CHAIN:
            upstream = self.prepare_stage(coll, stage, {stage.upstream: upstream.key})
            steps.append((stage.name, upstream.backend, upstream.params))
        return steps

    def prepare_stage(self, coll: Collection, stage: st.PhotoStage, inputs: dict[str, str],
                      choice: tuple[str, dict] | None = None) -> Provenance:
        """The provenance of a stage's next run; its outputs are (re)created when the key
        changed, so that the stage starts over rather than mixing old and new results.
        ``choice`` = (backend, params) overrides the workflow's backend of the stage's kind."""
        if stage.kind is None:  # a stage without backends: its params are the workflow's stages.<name>
            backend, params, version = "-", self.wf.backendless(stage.name), stage.version
        else:
            backend, params = choice or self.wf.stage(stage.kind)
            version = st.default_registry().get(stage.kind, backend).version
        prov = Provenance.make(stage=stage.name, backend=backend, backend_version=version,
                               params=params, inputs=inputs, persona_version=self.version)
        # outputs another stage wrote since (the 2D and 3D renderers share render/*) count as stale
        if not st.is_done(coll, prov, f"status/{stage.name}/state", *(o.name for o in stage.outputs)):
            self._create_outputs(coll, stage, prov)
        return prov

    def run_photo_stages(self, coll: Collection, video: bool) -> None:
        """Every per-photo stage over every shard not finished yet, with hooks and progress bars;
        then the screen, which needs every photo's fiducials."""
        steps = self.steps(coll)
        if video:  # frames come from one sequential decoding pass, then the chain without ingest
            self.run_tasks(coll, steps[:1], [(self.wf.store, coll.path, steps[0][2])], st.ingest_video)
            steps = steps[1:]
        self.run_stage_tasks(coll, steps)
        coll.group.attrs["stages"] = list(st.COLLECTION_STAGES)  # stores made before the screen existed
        screen = self.prepare_stage(coll, st.SCREEN, {"frontalize": coll.provenance("status/frontalize/state").key})
        self.run_stage_tasks(coll, [("screen", screen.backend, screen.params)])

    def run_stage_tasks(self, coll: Collection, steps: list[tuple[str, str, dict]]) -> None:
        """The chain of ``steps`` on every shard where one of them is not done yet."""
        states = [coll.state(name) for name, _, _ in steps]
        pending = [(s, e) for s, e in coll.shard_ranges() if any((state[s:e] == PENDING).any() for state in states)]
        tasks = [(self.wf.store, coll.path, s, e, steps) for s, e in pending]
        self.run_tasks(coll, steps, tasks, st.run_chain)

    @contextmanager
    def step(self, stage: str, collection: str):
        """A collection-level step (shape, texture, motion, ...) as the lifecycle hooks and the
        timing table see a stage: before, after (with its wall time) or error; and as progress, one
        step that starts and ends (a log gets a line each, with the time taken). ``stage`` is one
        of :data:`persona.dag.stages.STAGES`."""
        if stage not in st.STAGES:
            raise KeyError(f"{stage!r} is not in persona.dag.stages.STAGES, which the plan shows")
        self.pm.hook.persona_before_stage(stage=stage, collection=collection, info={})
        start = time.perf_counter()
        try:
            with self.progress_bar(f"{collection:>13} {stage:<10}", 1, unit="step") as bar:
                yield
                bar.update()
        except BaseException as exc:
            self.pm.hook.persona_stage_error(stage=stage, collection=collection, error=exc)
            raise
        self.pm.hook.persona_after_stage(stage=stage, collection=collection,
                                         summary={"seconds": time.perf_counter() - start})

    def progress_bar(self, what: str, total: int, unit: str = "frame", initial: int = 0):
        """A progress bar (hidden with --quiet): :func:`progress`."""
        return progress(what, total, unit, initial=initial, enabled=self.progress)

    def map_shards(self, coll: Collection, label: str, fn, *args) -> dict[int, object]:
        """``fn(store, path, start, stop, *args)`` on every shard of ``coll`` as tasks on the cluster
        (:func:`persona.dag.stages.on_shard`), with a progress bar; returns each shard's result by
        its first frame."""
        return {start: result for start, result in self._shard_results(coll, label, fn, *args)}

    def fold_shards(self, coll: Collection, label: str, fn, combine, *args):
        """:meth:`map_shards`, the shards' results (None: nothing to add) folded with
        ``combine(a, b)`` in the order of the shards as they arrive: only the results that come
        before their turn are held, and the fold is the same to the bit whichever task ends first."""
        starts = [s for s, _ in coll.shard_ranges()]
        early, total, turn = {}, None, 0
        for start, result in self._shard_results(coll, label, fn, *args):
            early[start] = result
            while turn < len(starts) and starts[turn] in early:
                result = early.pop(starts[turn])
                turn += 1
                if result is not None:
                    total = result if total is None else combine(total, result)
        return total

    def _shard_results(self, coll: Collection, label: str, fn, *args):
        """(first frame, result) of each shard's task as it ends, with a progress bar."""
        tasks = [(fn, self.wf.store, coll.path, s, e, *args) for s, e in coll.shard_ranges()]
        with self.progress_bar(f"{coll.path:>13} {label:<10}", coll.n, item(coll.path)) as bar:
            for start, stop, result in self.executor.run(st.on_shard, tasks):
                bar.update(stop - start)
                yield start, result

    def run_tasks(self, coll, steps, tasks, fn):
        """``fn(*task)`` for each of ``tasks``, the per-photo ``steps`` they run timed, hooked and shown."""
        names = [name for name, _, _ in steps]
        done = {name: int((coll.state(name) != PENDING).sum()) for name in names}
        counts = {name: {"n_done": 0, "n_skipped": done[name], "seconds": 0.0} for name in names}
        for name, backend, params in steps:
            self.pm.hook.persona_before_stage(stage=name, collection=coll.path,
                                              info={"backend": backend, "params": params, "n_items": coll.n})
        bars = {name: self.progress_bar(f"{coll.path:>13} {name:<10}", coll.n, item(coll.path), initial=done[name])
                for name in names}
        try:
            for result in self.executor.run(fn, tasks):
                for name, summary in result.items():
                    if not summary.get("skipped"):
                        counts[name]["n_done"] += summary["n"]
                        counts[name]["seconds"] += summary["seconds"]
                        bars[name].update(summary["n"])
            for name in names:  # shards a task finished before its worker died: its next attempt found them done
                lost = int((coll.state(name) != PENDING).sum()) - done[name] - counts[name]["n_done"]
                if lost > 0:
                    counts[name]["n_done"] += lost
                    bars[name].update(lost)
        except BaseException as exc:
            for name in names:
                self.pm.hook.persona_stage_error(stage=name, collection=coll.path, error=exc)
            raise
        finally:
            for bar in bars.values():
                bar.close()
        for name in names:
            state = coll.state(name)
            self.pm.hook.persona_after_stage(stage=name, collection=coll.path, summary={
                **counts[name], "n_ok": int((state == OK).sum()), "n_rejected": int((state == REJECTED).sum())})

    def mean_face(self, coll: Collection) -> np.ndarray | None:
        """The mean aligned face over accepted photos, weighted by visibility, and their mean
        fiducials (each point over the photos that see it); None if none.

        A map over shards (each task sums its shard) and a sum of the parts."""
        ok = st.accepted(coll)
        if not ok.any():
            return None
        prov = st.provenance("mean", params={}, inputs={"screen": coll.provenance("status/screen/state").key},
                             persona_version=self.version)
        if st.is_done(coll, prov, *st.STAGES["mean"].done):
            return coll.array("aligned/mean")[...]
        sums = self.fold_shards(coll, "mean face", st.aligned_sum, st.add_sums)
        count = sums["count"]
        mean = (sums["sum"] / np.maximum(count, 1)[..., None]).astype(np.float32)
        coll.create_single("aligned/mean", mean, ("y", "x", "channel"), prov)
        coll.create_single("aligned/coverage", (count / ok.sum()).astype(np.float32), ("y", "x"), prov)
        fiducials = mean_shape(coll.array("aligned/fiducials")[:][ok])
        coll.create_single("aligned/mean_fiducials", fiducials, ("fiducial", "xy"), prov)
        return mean

    def run(self, inputs: dict[str, list[media.Source]]) -> dict:
        """Every stage of the workflow on its resolved ``inputs`` (:func:`resolve_inputs`).

        Chunks of finished arrays that are lost or damaged (checked before the stages start: every
        chunk listed and read back against its checksum, as ``persona inspect --verify`` does) or found
        damaged on the way (a :class:`ChunkError`) are recomputed, with everything made from them:
        :mod:`persona.stores.verify`, one logged line per problem. A run that ends well leaves a store
        that verifies, the arrays no stage reads again (a drive's composite) included. The temporary
        files of writes a killed run left unfinished are deleted first."""
        if left := verify.clear_unfinished_writes(self.root):
            log.warning("%d unfinished write(s) a stopped run left in the store deleted (%s)", len(left),
                        ", ".join(left[:3]) + (", ..." if len(left) > 3 else ""))
        self.recover(verify.check(self.root, read=True))
        met = set()
        while True:
            try:
                return self.run_stages(inputs)
            except ChunkError as exc:
                if exc.key in met:  # recomputed and damaged again: not a damaged store, say so
                    raise
                met.add(exc.key)
                self.recover([verify.problem_of(self.root, exc)])

    def recover(self, problems: list[verify.Problem]) -> None:
        """Make the stages recompute what ``problems`` touch, saying so."""
        for line in verify.recover(self.root, problems):
            log.warning("%s", line)

    def run_stages(self, inputs: dict[str, list[media.Source]]) -> dict:
        """Every stage, in order (:meth:`run`): each collection once, then each drive."""
        report = {"workflow": self.wf.name, "store": self.wf.store, "collections": {}}
        if self.wf.version == 1:  # one drive (or none), whose outputs are the run's
            for plan in self.wf.collections():
                report["collections"][plan.path] = self.build_collection(plan, inputs[plan.path], report)
            plans = self.wf.drive_plans()
            part = self.drive(plans[0]) if plans else {}
            report.update({k: v for k, v in part.items() if k != "series"})
            report["stages"] = self.timer.records
            report["report"] = str(storage.join(self.wf.output, "report.html"))
            self.write_outputs(self.wf.output, report, part.get("series"), Cast() if plans else None)
            return report
        return self.run_batch(inputs, report)

    def run_batch(self, inputs: dict, report: dict) -> dict:
        """A version-2 workflow: every person and video once, then every drive, each drive's outputs
        in its own folder and the batch page over them. A person or a video that cannot be built
        fails the drives that use it, a drive that fails fails alone; the run then raises a
        :class:`RunError` naming each failed drive, after the others are done.

        People and videos are built ``cluster.builds`` at a time, in threads of this process whose
        tasks share the cluster; the drives run one after another in this thread, each as soon as
        its puppet, driver and video are built, while the others' builds go on."""
        plans = self.wf.collections()
        for plan in plans:  # every group (and its parents) made here, before the threads write in them
            if not isinstance(inputs[plan.path], InputError):
                self.root.require_group(plan.path)
        # built in the order the drives need them, so that the first drive starts as soon as it can
        needed = [p for d in self.wf.drive_plans() for p in (d.cast.puppet, d.cast.driver, d.cast.frames)]
        first_use = {path: i for i, path in reversed(list(enumerate(needed)))}
        pool = (_OneByOne() if self.executor.client is None or self.wf.cluster.builds == 1
                else ThreadPoolExecutor(self.wf.cluster.builds, thread_name_prefix="persona-build"))
        try:
            builds = {plan.path: pool.submit(self._build, plan, inputs[plan.path], report)
                      for plan in sorted(plans, key=lambda plan: first_use.get(plan.path, len(needed)))}
            failed = self._run_drives(report, builds)
            pool.shutdown()  # the people and videos no drive uses
            for build in builds.values():
                _built(build)  # a damaged chunk met there is recovered as anywhere
        except BaseException as exc:
            # a damaged chunk (run() recovers and starts again) or an error: no build may go on writing
            # meanwhile. Ctrl-C does not wait: closing the cluster then ends the builds' tasks
            pool.shutdown(wait=not isinstance(exc, KeyboardInterrupt), cancel_futures=True)
            raise
        built = report["collections"]  # in the order the builds ended: the workflow's order
        report["collections"] = {plan.path: built[plan.path] for plan in plans if plan.path in built}
        write_json(storage.join(self.wf.output, "metrics.json"), report)
        write_batch_page(self.wf, report)
        if failed:
            raise RunError(f"{len(failed)} of {len(report['drives'])} drives failed: "
                           + "; ".join(f"{name}: {why}" for name, why in failed.items())
                           + f". The others are done (in {self.wf.output}); fix the cause and run again: "
                           "what is done is not redone")
        return report

    def _build(self, plan, sources: list[media.Source] | InputError, report: dict) -> None:
        """:meth:`build_collection` in a build thread, its result into ``report``; an error is logged
        here, when it happens, and raised to the drives that wait for it."""
        try:
            if isinstance(sources, InputError):
                raise sources
            report["collections"][plan.path] = self.build_collection(plan, sources, report)
        except Exception as exc:
            if not _stops_the_run(exc):  # that one is said where the run stops
                log.error("%s: %s", plan.path, _why(exc))
            raise

    def _run_drives(self, report: dict, builds: dict[str, Future]) -> dict[str, str]:
        """Every drive of a version-2 workflow, each once its collections' ``builds`` are done, into
        ``report``; returns why each drive that failed did."""
        report["stages"] = self.timer.records
        report["report"] = str(storage.join(self.wf.output, "index.html"))
        report["drives"], failed = {}, {}
        for plan in self.wf.drive_plans():
            try:
                cause = [f"{p}: {why}" for p in dict.fromkeys((plan.cast.puppet, plan.cast.driver, plan.cast.frames))
                         if (why := _built(builds[p])) is not None]
                if cause:
                    raise RunError("; ".join(cause))
                part = self.drive(plan)
            except Exception as exc:  # one drive that fails does not take the others down
                if _stops_the_run(exc):
                    raise
                failed[plan.name] = _why(exc)
                log.error("drive %s failed: %s", plan.name, failed[plan.name])
                report["drives"][plan.name] = {"output": str(plan.output), "error": failed[plan.name]}
                continue
            own = {"workflow": f"{self.wf.name}: {plan.name}", "store": self.wf.store, "drive": plan.name,
                   "collections": {p: report["collections"][p] for p in (plan.cast.puppet, plan.cast.driver,
                                                                           plan.cast.frames)},
                   **{k: v for k, v in part.items() if k != "series"},
                   "stages": [r for r in self.timer.records if r["collection"] in (plan.cast.drive, plan.cast.puppet)],
                   "report": str(storage.join(plan.output, "report.html"))}
            self.write_outputs(plan.output, own, part["series"], plan.cast)
            report["drives"][plan.name] = {"output": str(plan.output), "report": own["report"],
                                           "evaluation": own["evaluation"]}
        return failed

    def build_collection(self, plan, sources: list[media.Source], report: dict) -> dict:
        """One collection's stages, in the graph's order (:mod:`persona.dag.graph`): the per-photo
        stages, the mean face and its pictures; for photo collections (not a video's frames) their
        alignment and 3D shape, and for puppets their texture cache. A stage only photo collections
        have that is rejected (too few photos for a 3D shape) leaves the collection without a shape,
        and the run goes on. Returns its counts and pictures."""
        target = Target(plan.path, sources=sources)
        shape_seconds = None if plan.video else 0.0
        for node in self.graph.of(plan.path):
            stage = st.STAGES[node.stage]
            t0 = time.perf_counter()
            try:
                self.run_stage(stage, target)
            except Rejected as exc:  # e.g. too few photos for photometric stereo
                if "video" in stage.where:
                    raise
                coll = Collection(self.root, plan.path)
                coll.remove("shape", "texture")  # an earlier run's: nothing later may take them for this one's
                self.shape_problems[plan.path] = exc.reason
                log.warning("%s: no 3D shape: %s", plan.path, exc.reason)
                report.setdefault("warnings", []).append(f"{plan.path}: no 3D shape: {exc.reason}")
                shape_seconds += time.perf_counter() - t0
                break
            if "video" not in stage.where and not stage.mesh:
                shape_seconds += time.perf_counter() - t0
        coll = Collection(self.root, plan.path)
        accepted = int(st.accepted(coll).sum())
        return {"n_photos": coll.n, "accepted": accepted, "rejected": coll.n - accepted,
                "rejections": rejections(coll), "pictures": target.pictures,
                "shape_seconds": None if shape_seconds is None else round(shape_seconds, 3)}

    def run_stage(self, stage: st.Stage, target: Target) -> None:
        """One stage on one collection or drive: its ``run``; a stage over a whole collection or drive
        as one step of the hooks and the progress lines (:meth:`step`), the per-photo and per-frame ones
        timed by their tasks. The per-photo stages of the chain run inside ``ingest``'s."""
        run = stage.function()
        if run is None:
            return
        if stage.per in ("photo", "frame"):
            run(self, stage, target)
            return
        with self.step(stage.name, target.path):
            run(self, stage, target)

    def uses_mesh(self) -> bool:
        """Whether the workflow's renderer draws the 3D puppet (:func:`persona.dag.graph.uses_mesh`)."""
        return dag_graph.uses_mesh(self.wf)

    def drive(self, plan) -> dict:
        """One drive: its stages in the graph's order, its videos and its evaluation (``videos``,
        ``speed``, ``evaluation`` and the per-frame ``series`` of the report's plots). The videos and the
        evaluation are kept from the last run when nothing they are made from changed
        (:meth:`kept_outputs`); the drive's speed is this run's whenever it rendered every frame, the last
        run's otherwise."""
        t0 = time.perf_counter()
        target = Target(plan.cast.drive, cast=plan.cast, output=plan.output)
        for node in self.graph.of(plan.cast.drive):
            self.run_stage(st.STAGES[node.stage], target)
        drive = Collection(self.root, plan.cast.drive)
        drive_seconds = time.perf_counter() - t0
        render = [r for r in self.timer.records if r["stage"] in ("render", "render3d")][-1]
        speed = {}
        if render["n_done"] == drive.n:  # timed only when this run rendered every frame
            speed = {"ms_per_driver_frame": 1000 * drive_seconds / drive.n,
                     "render_ms_per_frame_one_worker": 1000 * render["task_seconds"] / drive.n}
        key = dag_graph.outputs_key(self.wf, drive.provenance("composite/rgb"))
        kept = self.kept_outputs(plan.output, key)
        if kept is not None:
            log.info("%s: nothing new since its videos and evaluation were made: kept", plan.cast.drive)
            kept["speed"].update(speed)  # a drive made again (the same bytes) was timed again
            return kept
        out = {"outputs_key": key, "speed": speed}
        with self.step("videos", plan.cast.drive):  # and a 3D drive's puppet.glb (about 4 s for 269 frames)
            out["videos"] = write_videos(drive, Collection(self.root, plan.cast.frames), plan.output)
            if drive.has("mesh"):
                glb = write_drive_glb(self.root, plan.cast, storage.join(plan.output, "puppet.glb"))
                out["videos"]["glb"] = glb["path"]
        t0 = time.perf_counter()
        with self.step("evaluate", plan.cast.drive), \
                self.progress_bar(f"{plan.cast.drive:>13} {'analyse':<10}", drive.n) as bar:
            evaluation = self.evaluate(plan.cast, progress=bar.update)
        out["speed"]["evaluate_seconds"] = time.perf_counter() - t0
        out["series"] = evaluation.pop("series")
        out["evaluation"] = evaluation
        return out

    @staticmethod
    def kept_outputs(output: str, key: str) -> dict | None:
        """The videos, speed, evaluation and series a drive's last run left in ``output``, when they
        were made from the same frames and evaluation settings (its metrics.json, written last,
        records ``outputs_key``) and every video is still there; else None."""
        metrics, series = storage.join(output, "metrics.json"), storage.join(output, "series.json")
        if not (storage.isfile(metrics) and storage.isfile(series)):
            return None
        last = json.loads(storage.read_text(metrics))
        if last.get("outputs_key") != key or not all(storage.isfile(v) for v in last.get("videos", {}).values()):
            return None
        return {**{k: last[k] for k in ("outputs_key", "videos", "speed", "evaluation")},
                "series": json.loads(storage.read_text(series))}

    def write_outputs(self, output: str, report: dict, series: dict | None, cast: Cast | None) -> None:
        """metrics.json, series.json (the report's plots, should it be made again) and report.html in ``output``."""
        if series is not None:
            write_json(storage.join(output, "series.json"), {k: np.asarray(v, float).tolist() for k, v in series.items()})
        write_json(storage.join(output, "metrics.json"), report)
        write_run_report(self.wf, self.root, report, series, cast=cast, output=output)

    def evaluate(self, cast: Cast = Cast(), progress=lambda frames: None) -> dict:
        e = self.wf.evaluate
        return evaluate(self.wf.store, self.executor, identity=self.wf.stage("identity"),
                        threshold=e.threshold, collection_sample=e.collection_sample,
                        identity_frames=e.identity_frames, self_reenactment=e.self_reenactment, cast=cast,
                        progress=progress, known=self.centroids)


class _OneByOne:
    """The builds of :meth:`Runner.run_batch` one after another in this thread, as a pool of one
    thread would run them (the scheduler "sync", or ``cluster.builds`` 1)."""

    @staticmethod
    def submit(fn, *args) -> Future:
        future = Future()
        try:
            future.set_result(fn(*args))
        except Exception as exc:  # raised where the drives wait for it (_built)
            if _stops_the_run(exc):  # at once, as a thread's would stop the run
                raise
            future.set_exception(exc)
        return future

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        pass


def _built(build: Future) -> str | None:
    """Waits for a collection's build (:meth:`Runner._build`): None when it is built, else why not. A
    damaged chunk met there is raised, for :meth:`Runner.run` to recover, and so are a full disk and a lost
    cluster (:func:`_stops_the_run`)."""
    exc = build.exception()
    if exc is not None and (not isinstance(exc, Exception) or _stops_the_run(exc)):
        raise exc
    return None if exc is None else _why(exc)


def _why(exc: Exception) -> str:
    """A failure's reason in a line: a Persona error's own message, else the exception's type too."""
    return str(exc) if isinstance(exc, PersonaError) else f"{type(exc).__name__}: {exc}"


def _canvas(sources, params) -> list[int]:
    """The smallest canvas that holds every readable photo and video frame after downscaling to max_side."""
    h = w = 1
    videos: dict[str, tuple[int, int]] = {}
    for s in sources:
        try:
            if s.frame is None:
                info = media.probe_image(s.path, max_pixels=params["max_pixels"], min_side=params["min_side"])
                height, width = info.height, info.width
            else:
                if s.path not in videos:  # a video's frame size, read once
                    with media.VideoReader(s.path) as reader:
                        videos[s.path] = reader.height, reader.width
                height, width = videos[s.path]
        except (media.PhotoRejected, InputError):
            continue
        scale = min(1.0, params["max_side"] / max(width, height))
        h, w = max(h, int(round(height * scale))), max(w, int(round(width * scale)))
    return [h, w]


def write_json(path, data: dict) -> None:
    """A JSON file (a local path or a URL), written atomically."""
    media.write_bytes(path, json.dumps(data, indent=2, default=str).encode())


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


def run_workflow(wf: Workflow, *, scheduler: str | None = None, workers: int | None = None,
                 progress: bool = True, force: bool = False) -> dict:
    """Run every stage of a workflow; returns the run report (also in OUTPUT/metrics.json). The
    inputs are resolved first (:func:`resolve_inputs`): a bad one stops the run before anything is
    created; so does an output folder that holds files Persona did not write, unless ``force``
    (persona.stores.output)."""
    inputs = resolve_inputs(wf, keep_going=wf.version == 2)  # a batch: a bad input fails its drives only
    with lock.writer(wf.store):  # one run writes a store at a time
        output.claim(wf.output, wf.store, force=force)
        with executor_for(wf, scheduler, workers) as ex:
            return Runner(wf, ex, progress=progress).run(inputs)
