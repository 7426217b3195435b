"""The graph of a run: every stage of every collection and drive of a workflow, and what each reads.

A node is a (stage, target) pair: a stage of :data:`persona.dag.stages.STAGES` on one collection of
the store (``puppet``, ``people/bea``, ``videos/clip``) or one drive (``drive``, ``drives/bea_al_clip``).
Its edges come from the stage's ``needs``, resolved against the drive's :class:`Cast`. :func:`build`
makes the graph of a workflow; the runner runs each target's nodes in the graph's order, the plan
(``persona run --dry-run``, ``persona plan``) lists and draws them, and :func:`status` reads from a
store which of them are done.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cached_property

from persona.plugins.manager import default_registry
from persona.stores import storage
from persona.stores.layout import OK, PENDING, Cast, Collection
from persona.stores.provenance import Provenance, cache_key

from . import evaluate as evaluation
from .stages import STAGES, Stage
from .workflow import CollectionPlan, DrivePlan, Workflow

#: a node's status in a store: made with what it reads now; to be made (or made again); failed
DONE, TO_RUN, FAILED = "done", "to run", "failed"


@dataclass(frozen=True)
class Node:
    """One stage on one collection or drive (``target``, its path in the store)."""

    stage: str
    target: str

    def __str__(self) -> str:
        return f"{self.target} {self.stage}"


@dataclass
class Target:
    """One collection or drive while its stages run: what the stages of a target hand each other.

    ``made``: the provenance of each stage run so far on it, by stage name (a later stage's cache key
    takes an earlier one's); ``pictures``: the files its stages wrote into the output folder, for
    the report. A collection's ``sources`` are its resolved photos; a drive's ``cast`` and ``output``
    say where its collections are and where its files go."""

    path: str
    sources: list | None = None
    cast: Cast | None = None
    output: str = ""
    made: dict[str, Provenance] = field(default_factory=dict)
    pictures: dict[str, str] = field(default_factory=dict)


@dataclass
class Graph:
    """The nodes of a run in the order it runs them (each target's in :data:`STAGES` order, every
    collection before the drives) and its edges (from a node read to the node reading it)."""

    nodes: list[Node]
    edges: list[tuple[Node, Node]]
    #: each target's role: puppet, driver, video or drive
    roles: dict[str, str]
    collections: list[CollectionPlan]
    drives: list[DrivePlan]

    def of(self, target: str) -> list[Node]:
        """The nodes of one collection or drive, in the order they run."""
        return self._by_target.get(target, [])

    def needs(self, node: Node) -> list[Node]:
        """The nodes ``node`` reads."""
        return self._needs.get(node, [])

    @cached_property
    def _by_target(self) -> dict[str, list[Node]]:  # indexed once: a batch of a thousand drives has 20,000 nodes
        out: dict[str, list[Node]] = {}
        for node in self.nodes:
            out.setdefault(node.target, []).append(node)
        return out

    @cached_property
    def _needs(self) -> dict[Node, list[Node]]:
        out: dict[Node, list[Node]] = {}
        for a, b in self.edges:
            out.setdefault(b, []).append(a)
        return out


def role(plan: CollectionPlan) -> str:
    """What a collection is to the run: a video's frames (no 3D shape), a puppet (the expression-dependent
    texture too), or a driver."""
    return "video" if plan.video else "puppet" if plan.texture else "driver"


def uses_mesh(wf: Workflow) -> bool:
    """Whether the workflow's renderer draws the 3D puppet, which the stages marked ``mesh`` make."""
    return default_registry().get("render", wf.stage("render")[0]).uses_mesh


def build(wf: Workflow) -> Graph:
    """The graph of every person, video and drive of the workflow (:mod:`persona.dag.graph`)."""
    mesh = uses_mesh(wf)

    def stages(where: str) -> list[Stage]:
        return [s for s in STAGES.values() if where in s.where and (mesh or not s.mesh)]

    nodes, edges, roles = [], [], {}
    collections, drives = wf.collections(), wf.drive_plans()
    puppets = {plan.cast.puppet for plan in drives}
    for plan in collections:
        roles[plan.path] = role(plan)
        for stage in stages(roles[plan.path]):
            if stage.mesh and plan.path not in puppets:  # what only a 3D drive of this puppet reads
                continue
            node = Node(stage.name, plan.path)
            nodes.append(node)
            edges += [(Node(need, plan.path), node) for need in stage.needs]
    for plan in drives:
        c = plan.cast
        roles[c.drive] = "drive"
        where = {"puppet": c.puppet, "driver": c.driver, "video": c.frames}
        for stage in stages("drive"):
            node = Node(stage.name, c.drive)
            nodes.append(node)
            for need in stage.needs:
                of, _, name = need.rpartition(":")
                edges.append((Node(name, where[of] if of else c.drive), node))
    present = set(nodes)
    edges = [(a, b) for a, b in edges if a in present]  # a 2D render needs no motion; a video no shape
    return Graph(nodes, list(dict.fromkeys(edges)), roles, collections, drives)


def status(graph: Graph, root, wf: Workflow) -> dict[Node, str]:
    """Each node's status in the store ``root`` (None: no store yet), read from provenance. ``done``:
    its arrays (the stage's ``done``) carry the provenance a finished stage writes, no item is still
    pending, and every node it reads is done; ``failed``: every item was rejected, or the last run
    recorded its drive as failed (the output's metrics.json); ``to run`` otherwise. The drive's videos
    and evaluation are done when its output's metrics.json was written for the composite the store
    holds (:func:`outputs_key`). A changed setting shows only when the run compares cache keys."""
    out: dict[Node, str] = {}
    failed_drives = _failed_drives(wf)
    mesh = uses_mesh(wf)
    for node in graph.nodes:
        stage = STAGES[node.stage]
        coll = Collection(root, node.target) if root is not None else None
        if coll is None or not coll.exists():
            out[node] = TO_RUN
        elif not stage.done:
            out[node] = DONE if _outputs_done(wf, graph, coll) else TO_RUN
        else:
            out[node] = _made(coll, stage, mesh)
        if out[node] == DONE and any(out[n] != DONE for n in graph.needs(node)):
            out[node] = TO_RUN
        if out[node] != DONE and graph.roles[node.target] == "drive" and node.target in failed_drives:
            out[node] = FAILED
    return out


def _made(coll: Collection, stage: Stage, mesh: bool) -> str:
    """A stage's status from its arrays in ``coll`` (:func:`status`)."""
    names = stage.done
    if len(stage.photo) > 1:  # the render: the status of the renderer the workflow draws with
        names = (f"status/{stage.photo[-1 if mesh else 0].name}/state",)
    if any(coll.provenance(name) is None for name in names):
        return TO_RUN
    for name in names:
        if name.startswith("status/"):
            state = coll.array(name)[:]
            if (state == PENDING).any():
                return TO_RUN
            if len(state) and not (state == OK).any():
                return FAILED
    return DONE


def _outputs_done(wf: Workflow, graph: Graph, drive: Collection) -> bool:
    plan = next(p for p in graph.drives if p.cast.drive == drive.path)
    prov = drive.provenance("composite/rgb")
    if prov is None:
        return False
    metrics = storage.join(plan.output, "metrics.json")
    if not storage.isfile(metrics):
        return False
    return json.loads(storage.read_text(metrics)).get("outputs_key") == outputs_key(wf, prov)


def outputs_key(wf: Workflow, composite: Provenance) -> str:
    """The cache key of a drive's videos and evaluation: the composite's key and the evaluation's
    settings. A drive's metrics.json records it (``outputs_key``); a run whose key is the same keeps them."""
    return cache_key(composite=composite.key, identity=wf.stage("identity"),
                     evaluate=wf.evaluate.model_dump(mode="json"), figures=evaluation.VERSION)


def _failed_drives(wf: Workflow) -> set[str]:
    """The drives (their store paths) the last run of a version-2 workflow recorded as failed."""
    metrics = storage.join(wf.output, "metrics.json")
    if wf.version != 2 or not storage.isfile(metrics):
        return set()
    drives = json.loads(storage.read_text(metrics)).get("drives", {})
    paths = {p.name: p.cast.drive for p in wf.drive_plans()}
    return {paths[name] for name, d in drives.items() if "error" in d and name in paths}
