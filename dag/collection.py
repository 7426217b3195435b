"""The stages every collection goes through, photos or video frames alike: the per-photo chain
(ingest to frontalize, one Dask task per shard), the screen, and the collection's mean face.

Each is a stage's ``run`` (:data:`persona.dag.stages.STAGES`), called as ``run(runner, stage, target)``.
"""

from __future__ import annotations

from .errors import RunError
from persona.stores.layout import Collection

from . import stages as st
from .graph import Target
from .report import collection_pictures


def run_chain_stages(runner, stage, target: Target) -> None:
    """``ingest`` and the per-photo chain after it (landmarks, pose, frontalize), fused per shard: the
    collection is opened, or created anew when its photos or ingest params changed."""
    coll, video = runner.collection(target.path, target.sources)
    steps = runner.steps(coll)
    if video:  # frames come from one sequential decoding pass, then the chain without ingest
        runner.run_tasks(coll, steps[:1], [(runner.wf.store, coll.path, steps[0][2])], st.ingest_video)
        steps = steps[1:]
    runner.run_stage_tasks(coll, steps)
    coll.group.attrs["stages"] = list(st.COLLECTION_STAGES)  # stores made before the screen existed


def run_screen(runner, stage, target: Target) -> None:
    """``screen``: photos far from the collection's median shape, and copies, rejected. A collection
    none of whose photos got through ends the build here."""
    coll = Collection(runner.root, target.path)
    screen = runner.prepare_stage(coll, st.SCREEN, {"frontalize": coll.provenance("status/frontalize/state").key})
    runner.run_stage_tasks(coll, [("screen", screen.backend, screen.params)])
    target.made[stage.name] = screen
    if not st.accepted(coll).any():
        raise RunError(f"{target.path}: no photo of the {coll.n} got through to an aligned face; "
                       f"see `persona inspect {runner.wf.store}` for each photo's reason")


def run_mean(runner, stage, target: Target) -> None:
    """``mean``: the collection's mean aligned face (:meth:`persona.dag.runner.Runner.mean_face`), and its
    pictures in the output folder (the mean face, a contact sheet)."""
    coll = Collection(runner.root, target.path)
    mean = runner.mean_face(coll)
    target.pictures.update(collection_pictures(coll, mean, runner.wf.output))
    target.made[stage.name] = coll.provenance("aligned/mean")
