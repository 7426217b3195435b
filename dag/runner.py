"""Run a workflow: each collection's and each drive's stages, in the order of the run's graph
(:mod:`persona.dag.graph`), their tasks on a Dask cluster (:mod:`persona.dag.executor`).

A stage maps its backend over the shards of a collection that are not done yet, or runs once over a
collection or a drive. A shard is done when its status is written, which happens after its outputs,
so an interrupted run, run again, resumes where it stopped. A stage whose cache key (backend, version,
params, inputs) changed starts over. A version-2 workflow's people, videos and drives are scheduled by
:mod:`persona.dag.schedule`; what a drive writes into the output folder, by :mod:`persona.dag.outputs`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

from persona.plugins.base import Rejected
from persona.plugins.manager import get_plugin_manager
from persona.stores import lock, media, output, storage, verify
from persona.stores.chunks import ChunkError
from persona.stores.layout import Cast, Collection, open_store, rejections
from persona.stores.provenance import Provenance

from . import graph as dag_graph
from . import stages as st
from .collection import create_outputs, open_collection, photo_chain, screen
from .evaluate import evaluate, warm_up
from .executor import Executor, executor_for
from .graph import Target
from .inputs import resolve_inputs
from .outputs import drive_outputs, write_outputs
from .progress import StageTimer
from .schedule import run_batch
from .tasks import Tasks
from .workflow import Workflow

log = logging.getLogger(__name__)


def persona_version() -> str:
    import importlib.metadata

    try:
        return importlib.metadata.version("persona")
    except importlib.metadata.PackageNotFoundError:
        return "0+unknown"


@dataclass
class Runner:
    """One run of a workflow on an executor: each collection's and each drive's stages in the order of
    the run's graph (:attr:`graph`), its tasks through :attr:`tasks`; the :class:`~persona.dag.context.RunContext` every
    stage's ``run`` gets."""

    wf: Workflow
    executor: Executor
    progress: bool = True
    pm: object = None
    timer: StageTimer = field(default_factory=StageTimer)
    #: why a collection has no 3D shape in this run (its arrays from an earlier run must not be used)
    shape_problems: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.pm is None:
            self.pm = get_plugin_manager()[0]
        self.pm.register(self.timer)
        self.root = open_store(self.wf.store)
        self.version = persona_version()
        self.graph = dag_graph.build(self.wf)
        self.tasks = Tasks(self.wf.store, self.executor, self.pm, self.progress)

    def ingest_params(self) -> dict:
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
        """The collection at ``path`` of the resolved ``sources``, opened or created anew
        (:func:`persona.dag.collection.open_collection`)."""
        return open_collection(self, path, sources)

    def steps(self, coll: Collection) -> list[tuple[str, str, dict]]:
        """(stage, backend, params) of every per-photo stage; (re)creates the outputs of
        each stage whose cache key changed, so that it starts over."""
        steps = [("ingest", "-", self.ingest_params())]
        upstream = coll.provenance("status/ingest/state")
        for stage in st.CHAIN:
            upstream = self.prepare_stage(coll, stage, {stage.upstream: upstream.key})
            steps.append((stage.name, upstream.backend, upstream.params))
        return steps

    def prepare_stage(self, coll: Collection, stage: st.PhotoStage, inputs: dict[str, str],
                      choice: tuple[str, dict] | None = None, key_params: dict | None = None) -> Provenance:
        """The provenance of a stage's next run; its outputs are (re)created when the key
        changed, so that the stage starts over rather than mixing old and new results.
        ``choice`` = (backend, params) overrides the workflow's backend of the stage's kind;
        ``key_params``: more params the key records besides the backend's."""
        if stage.kind is None:  # a stage without backends: its params are the workflow's stages.<name>
            backend, params, version = "-", self.wf.backendless(stage.name), None
        else:
            name, params = choice or self.wf.stage(stage.kind)
            backend, version = st.backend_key(stage.kind, name)
        prov = st.provenance(stage.name, backend=backend, backend_version=version,
                             params={**params, **(key_params or {})}, inputs=inputs, persona_version=self.version)
        # outputs another stage wrote since (the 2D and 3D renderers share render/*) count as stale
        if not st.is_done(coll, prov, f"status/{stage.name}/state", *(o.name for o in stage.outputs)):
            create_outputs(coll, stage, prov)
        return prov

    def run_photo_stages(self, coll: Collection, video: bool) -> None:
        """Every per-photo stage and the screen on a collection :meth:`collection` opened."""
        photo_chain(self, coll, video)
        screen(self, coll)

    def run(self, inputs: dict[str, list[media.Source]]) -> dict:
        """Every stage of the workflow on its resolved ``inputs`` (:func:`resolve_inputs`).

        Chunks of finished arrays that are lost or damaged (checked before the stages start: every
        chunk listed and read back by the workers against its checksum, as ``persona inspect --verify``
        does) or found damaged on the way (a :class:`ChunkError`) are recomputed, with everything made from them:
        :mod:`persona.stores.verify`, one logged line per problem. A run that ends well leaves a store
        that verifies, the arrays no stage reads again (a drive's composite) included. The temporary
        files of writes a killed run left unfinished are deleted first."""
        if left := verify.clear_unfinished_writes(self.root):
            log.warning("%d unfinished write(s) a stopped run left in the store deleted (%s)", len(left),
                        ", ".join(left[:3]) + (", ..." if len(left) > 3 else ""))
        self.recover(verify.check(self.root, read=True, run=self.executor.run, url=self.wf.store))
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
            write_outputs(self, self.wf.output, report, part.get("series"), Cast() if plans else None)
            return report
        return run_batch(self, inputs, report)

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
        as one step of the hooks and the progress lines (:meth:`Tasks.step`), the per-photo and per-frame ones
        timed by their tasks. The per-photo stages of the chain run inside ``ingest``'s."""
        run = stage.function()
        if run is None:
            return
        if stage.per in ("photo", "frame"):
            run(self, stage, target)
            return
        with self.tasks.step(stage.name, target.path):
            run(self, stage, target)

    def uses_mesh(self) -> bool:
        """Whether the workflow's renderer draws the 3D puppet (:func:`persona.dag.graph.uses_mesh`)."""
        return dag_graph.uses_mesh(self.wf)

    def drive(self, plan) -> dict:
        """One drive: its stages in the graph's order, its videos and its evaluation (``videos``,
        ``speed``, ``evaluation`` and the per-frame ``series`` of the report's plots). The videos and the
        evaluation are kept from the last run when nothing they are made from changed
        (:func:`persona.dag.outputs.kept_outputs`); the drive's speed is this run's whenever it rendered every frame, the last
        run's otherwise."""
        t0 = time.perf_counter()
        self.executor.warm(warm_up)  # the evaluation's models, while the workers wait on the retargeting
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
        return drive_outputs(self, plan, speed)

    def evaluate(self, cast: Cast = Cast(), progress=lambda frames: None) -> dict:
        """Every figure of the drive of ``cast`` (:func:`persona.dag.evaluate.evaluate`); the people's descriptor
        centroids it computes are kept in the store."""
        e = self.wf.evaluate
        return evaluate(self.wf.store, self.executor, identity=self.wf.stage("identity"),
                        threshold=e.threshold, collection_sample=e.collection_sample,
                        identity_frames=e.identity_frames, self_reenactment=e.self_reenactment, cast=cast,
                        progress=progress, keep_in=self.root, version=self.version)


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
