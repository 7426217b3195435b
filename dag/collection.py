"""The stages every collection goes through, photos or video frames alike: the per-photo chain
(ingest to frontalize, one Dask task per shard), the screen, and the collection's mean face.

Each is a stage's ``run`` (:data:`persona.dag.stages.STAGES`), called as ``run(runner, stage, target)``;
:func:`open_collection` opens or creates a collection of resolved photos, :func:`mean_face` makes its mean.
"""

from __future__ import annotations

import numpy as np

from persona.plugins.face.fiducials import mean_shape
from persona.stores import media, storage
from persona.stores.layout import Collection
from persona.stores.provenance import Provenance, cache_key

from . import stages as st
from .context import RunContext
from .errors import RunError
from .graph import Target
from .inputs import canvas_of
from .report import collection_pictures


def run_chain_stages(runner: RunContext, stage: st.Stage, target: Target) -> None:
    """``ingest`` and the per-photo chain after it (landmarks, pose, frontalize), fused per shard: the
    collection is opened, or created anew when its photos or ingest params changed."""
    photo_chain(runner, *open_collection(runner, target.path, target.sources))


def run_screen(runner: RunContext, stage: st.Stage, target: Target) -> None:
    """``screen``: photos far from the collection's median shape, and copies, rejected. A collection
    none of whose photos got through ends the build here."""
    coll = Collection(runner.root, target.path)
    target.made[stage.name] = screen(runner, coll)
    if not st.accepted(coll).any():
        raise RunError(f"{target.path}: no photo of the {coll.n} got through to an aligned face; "
                       f"see `persona inspect {runner.wf.store}` for each photo's reason")


def photo_chain(runner: RunContext, coll: Collection, video: bool) -> None:
    """The per-photo chain on every shard of ``coll`` not finished yet; a video's frames are decoded in one
    sequential pass first, then go through the chain without ingest."""
    steps = runner.steps(coll)
    if video:
        runner.tasks.run_tasks(coll, steps[:1], [(runner.wf.store, coll.path, steps[0][2])], st.ingest_video)
        steps = steps[1:]
    runner.tasks.run_stage_tasks(coll, steps)
    coll.group.attrs["stages"] = list(st.COLLECTION_STAGES)  # stores made before the screen existed


def screen(runner: RunContext, coll: Collection) -> Provenance:
    """The screen on every shard of ``coll`` not screened yet (it needs every photo's fiducials first)."""
    prov = runner.prepare_stage(coll, st.SCREEN, {"frontalize": coll.provenance("status/frontalize/state").key})
    runner.tasks.run_stage_tasks(coll, [("screen", prov.backend, prov.params)])
    return prov


def run_mean(runner: RunContext, stage: st.Stage, target: Target) -> None:
    """``mean``: the collection's mean aligned face (:func:`mean_face`), and its
    pictures in the output folder (the mean face, a contact sheet)."""
    coll = Collection(runner.root, target.path)
    mean = mean_face(runner, coll)
    target.pictures.update(collection_pictures(coll, mean, runner.wf.output))
    target.made[stage.name] = coll.provenance("aligned/mean")


def open_collection(runner: RunContext, path: str,
                    sources: list[media.Source]) -> tuple[Collection, bool]:
    """Open (or create anew, when its sources or ingest params changed) a collection of the
    resolved ``sources`` (:func:`resolve_inputs`)."""
    params = runner.ingest_params()
    # the frames of one video are decoded in one sequential pass; a mix of photos, videos and
    # video ranges photo by photo (a frame decoded from the start of its video: exact)
    video = sources[0].path if all(s.frame is not None and s.path == sources[0].path for s in sources) else None
    stats = [(s.path, s.frame, *storage.signature(s.path)) for s in sources]
    prov = st.provenance("ingest", params=params, inputs={"sources": cache_key(sources=stats)},
                         persona_version=runner.version)
    coll = Collection(runner.root, path)
    if not st.is_done(coll, prov, *st.STAGES["ingest"].done):
        _create_collection(runner, coll, sources, video, params, prov)
    return coll, video is not None


def _create_collection(runner: RunContext, coll, sources, video, params, prov):
    """The collection's group (its canvas: the video's frame or the smallest that holds every photo), its
    photos' ids, files and frames, and ingest's outputs, every photo pending."""
    group = runner.root.require_group(coll.path)
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
        canvas = canvas_of(sources, params)
    group.attrs.update({"n_photos": n, "photos_per_shard": runner.wf.photos_per_shard,
                        "canvas": canvas, "stages": list(st.COLLECTION_STAGES)})
    coll.create("photos/ids", (), str, ("photo",), prov)[:] = np.array([s.id for s in sources])
    coll.create("photos/source", (), str, ("photo",), prov)[:] = np.array([media.stored_path(s.path) for s in sources])
    coll.create("photos/frame", (), "int64", ("photo",), prov, fill_value=-1)[:] = np.array(
        [-1 if s.frame is None else s.frame for s in sources], dtype=np.int64)
    create_outputs(coll, st.INGEST, prov)


def create_outputs(coll: Collection, stage: st.PhotoStage, prov: Provenance) -> None:
    """A per-photo stage's outputs and status, every photo pending, made by ``prov``."""
    for o in stage.outputs:
        coll.create(o.name, st.output_tail(o, coll.attrs["canvas"]),
                    str if o.dtype == "str" else o.dtype, o.dims, prov)
    coll.create_status(stage.name, prov)


def mean_face(runner: RunContext, coll: Collection) -> np.ndarray | None:
    """The mean aligned face over accepted photos, weighted by visibility, and their mean
    fiducials (each point over the photos that see it); None if none.

    A map over shards (each task sums its shard) and a sum of the parts."""
    ok = st.accepted(coll)
    if not ok.any():
        return None
    prov = st.provenance("mean", params={}, inputs={"screen": coll.provenance("status/screen/state").key},
                         persona_version=runner.version)
    if st.is_done(coll, prov, *st.STAGES["mean"].done):
        return coll.array("aligned/mean")[...]
    sums = runner.tasks.fold_shards(coll, "mean face", st.aligned_sum, st.add_sums)
    count = sums["count"]
    mean = (sums["sum"] / np.maximum(count, 1)[..., None]).astype(np.float32)
    coll.create_single("aligned/mean", mean, ("y", "x", "channel"), prov)
    coll.create_single("aligned/coverage", (count / ok.sum()).astype(np.float32), ("y", "x"), prov)
    fiducials = mean_shape(coll.array("aligned/fiducials")[:][ok])
    coll.create_single("aligned/mean_fiducials", fiducials, ("fiducial", "xy"), prov)
    return mean
