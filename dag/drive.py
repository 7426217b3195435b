"""Driving the puppet: the driver's video frames -> the puppet's frames -> videos.

``retarget`` (in this process): the driver's per-frame pose and pose-corrected fiducials,
frames without a face bridged by interpolation, and the target fiducials for the puppet
(its neutral plus the driver's offsets, scaled to its proportions). ``texture``: B's face
for each frame's expression (video mode, :mod:`.texture`). ``render`` (Dask
tasks over shards of frames): the chosen render backend draws each frame. Both live in
the ``drive`` collection, whose photo axis is the driver's frame axis.
"""

from __future__ import annotations

import logging
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from persona.plugins.face import gaze
from persona.plugins.face.composite import alone
from persona.plugins.face.dynamics import smooth_in_time
from persona.plugins.face.fiducials import rest_shape
from persona.plugins.face.tracks import bridge, steadied
from persona.plugins.face.warp import retarget
from persona.stores import media, storage
from persona.stores.layout import OK, PENDING, Cast, Collection, open_store

from . import stages as st
from .context import RunContext
from .graph import Target

log = logging.getLogger(__name__)


def run_retarget(runner: RunContext, stage: st.Stage, target: Target) -> None:
    """``retarget``: the driver's smoothed poses and pose-corrected fiducials, frames without a face bridged,
    and B's target fiducials; creates the drive's collection (``target.path``, one item per frame)."""
    cast = target.cast
    frames = Collection(runner.root, cast.frames)
    puppet = Collection(runner.root, cast.puppet)
    found = st.accepted(frames)
    inputs = {"frames": frames.provenance("status/screen/state").key,
              "puppet": puppet.provenance("aligned/mean").key}
    motion = runner.motion_params()
    sigma, lips, steady, widen = motion["pose_sigma"], motion["lips"], motion["steady"], motion["widen"]
    neutral, share = driver_neutral(motion["neutral"], cast), motion["neutral_share"]
    if neutral == "collection":
        inputs["driver"] = Collection(runner.root, cast.driver).provenance("aligned/mean").key
    # lips at the paper's 'mean', steady off, widen at 'opening' and the clip's neutral are left out of the
    # key: stores made before the switches existed stay valid
    prov = st.provenance(stage.name, params={"pose_sigma": sigma, **({"lips": lips} if lips != "mean" else {}),
                                             **({"steady": steady} if steady else {}),
                                             **({"widen": widen} if widen != "opening" else {}),
                                             **({"neutral": neutral} if neutral != "clip" else {}),
                                             **({"neutral_share": share} if share != 1 else {})},
                         inputs=inputs, persona_version=runner.version)
    drive = Collection(runner.root, cast.drive)
    # the status is created before the targets and written after them: done only when no frame is pending
    if not st.is_done(drive, prov, *stage.done) or (drive.state("retarget") == PENDING).any():
        _retarget(runner, cast, drive, frames, puppet, found, prov, sigma, lips, steady, widen, neutral, share)
    target.made[stage.name] = prov


def run_render(runner: RunContext, stage: st.Stage, target: Target) -> None:
    """``render``: the render backend draws every frame (Dask tasks over shards of frames); a renderer of
    the 3D puppet takes B's meshes, mouth and teeth too (:data:`persona.dag.stages.RENDER_3D`)."""
    drive, made = Collection(runner.root, target.path), target.made
    inputs = {"retarget": made["retarget"].key, "texture": made["frame textures"].key}
    photo = st.RENDER
    if runner.uses_mesh():
        inputs["mesh"] = made["motion"].key
        inputs["mouth"] = Collection(runner.root, target.cast.puppet).provenance("texture/lips").key
        inputs["teeth"] = made["teeth"].key
        photo = st.RENDER_3D
    drive.group.attrs["stages"] = ["retarget", *(["dynamics"] if photo is st.RENDER_3D else []), photo.name,
                                   "composite"]
    render = runner.prepare_stage(drive, photo, inputs)
    runner.tasks.run_stage_tasks(drive, [(photo.name, render.backend, render.params)])
    made[stage.name] = render


def run_composite(runner: RunContext, stage: st.Stage, target: Target) -> None:
    """``composite``: B's rendered face blended into each of the driver's frames by the ``composite``
    backend (Dask tasks over shards). Its cache key takes the light backend's params too, each as
    ``light_<name>``, as it did when they were ``stages.composite``'s: stores made before stay valid."""
    drive = Collection(runner.root, target.path)
    backend, params = runner.wf.stage("composite")
    light = {f"light_{name}": value for name, value in runner.wf.stage("light")[1].items()}
    composite = runner.prepare_stage(drive, st.COMPOSITE, {"render": target.made["render"].key,
                                                           "light": target.made["light"].key},
                                     (backend, params), key_params=light)
    runner.tasks.run_stage_tasks(drive, [("composite", backend, params)])
    target.made[stage.name] = composite


def run_light(runner: RunContext, stage: st.Stage, target: Target) -> None:
    """``composite/light``: the light planes the render fitted on each frame (``render/light``), as the
    ``light`` backend makes them (the default: steady in time)."""
    drive = Collection(runner.root, target.path)
    name, params = runner.wf.stage("light")
    recorded, version = st.backend_key("light", name)
    prov = st.provenance(stage.name, backend=recorded, backend_version=version, params=params,
                         inputs={"render": target.made["render"].key}, persona_version=runner.version)
    if not st.is_done(drive, prov, *stage.done):
        planes = st.default_registry().get("light", name)(params).light(drive.array("render/light")[:])
        drive.create("composite/light", (4, 3), "float32", ("frame", "term", "channel"), prov, pending=True)[:] = planes
        drive.mark_done("composite/light", prov)  # after the data: a run killed before this does it again
    target.made[stage.name] = prov


def run_gaze(runner: RunContext, stage: st.Stage, target: Target) -> None:
    """``eyes/gaze`` (frame, eye, along / across): how far the driver's irises sit from where they usually do
    in the clip, in eye widths (:func:`driver_irises` on the workers, gaze.gaze_shift); frames without a face
    look where they usually do."""
    drive, frames = Collection(runner.root, target.path), Collection(runner.root, target.cast.frames)
    prov = st.provenance(stage.name, params={}, inputs={"frames": frames.provenance("status/screen/state").key},
                         persona_version=runner.version)
    if not st.is_done(drive, prov, *stage.done):
        shards = runner.tasks.map_shards(drive, "irises", driver_irises)
        offsets = np.concatenate([shards[start] for start in sorted(shards)])
        drive.create("eyes/gaze", (2, 2), "float32", ("frame", "eye", "axis"), prov,
                     pending=True)[:] = gaze.gaze_shift(offsets)
        drive.mark_done("eyes/gaze", prov)  # after the data: a run killed before this does it again
    target.made[stage.name] = prov


def driver_irises(url: str, path: str, start: int, stop: int) -> np.ndarray:
    """One shard's task: (stop - start, 2, 2) where the driver's irises sit in frames [start, stop) of the drive
    at ``path`` (gaze.iris_offsets of each frame and its landmarks), NaN in a frame without a face."""
    root = open_store(url, mode="r")
    frames = Collection(root, Cast.of(root, path).frames)
    found = st.accepted(frames)[start:stop]
    rgb, size, points = (frames.array(array)[start:stop] for array in ("photos/rgb", "photos/size", "landmarks/points"))
    offsets = np.full((stop - start, 2, 2), np.nan)
    for i, (image, (h, w), lm) in enumerate(zip(rgb, size, points)):
        if found[i]:
            offsets[i] = gaze.iris_offsets(image[:h, :w], lm)
    return offsets


def run_teeth(runner: RunContext, stage: st.Stage, target: Target) -> None:
    """``mouth/teeth``: how much of B's teeth (rather than B's cavity) each frame's mouth shows, as the
    ``mouth`` backend finds it in the driver's own mouth, made steady in time (the render's ``mouth_sigma``);
    1 in every frame unless the render draws it and the puppet has both interiors (``mouth_choice: driver``).
    Its key takes the backend through the mouth stage's, which records it."""
    drive = Collection(runner.root, target.path)
    frames, puppet = Collection(runner.root, target.cast.frames), Collection(runner.root, target.cast.puppet)
    params = runner.render_params()
    sigma, both = params.mouth_sigma, params.mouth and puppet.has("texture/mouth_cavity")
    name, settings = runner.wf.stage("mouth")
    prov = st.provenance(stage.name, backend=st.backend_key("mouth", name)[0], params={"sigma": sigma} if both else {},
                         inputs={"mouth": puppet.provenance("texture/lips").key,
                                 "frames": frames.provenance("status/screen/state").key},
                         persona_version=runner.version)
    if not st.is_done(drive, prov, *stage.done):
        share = np.ones(drive.n)
        if both:
            rgb, size, points = (frames.array(array) for array in ("photos/rgb", "photos/size", "landmarks/points"))
            share = st.default_registry().get("mouth", name)(settings).teeth(
                ((image[:h, :w], lm) for start, stop in drive.shard_ranges()
                 for image, (h, w), lm in zip(rgb[start:stop], size[start:stop], points[start:stop])), sigma)
        drive.create("mouth/teeth", (), "float32", ("frame",), prov, pending=True)[:] = share
        drive.mark_done("mouth/teeth", prov)  # after the data: a run killed before this does it again
    target.made[stage.name] = prov


def driver_neutral(choice: str, cast: Cast) -> str:
    """``stages.motion.params.neutral`` for this drive: 'auto' is 'collection' where the driver is the puppet
    (its collection's mean is then the puppet's neutral itself) and the paper's 'clip' otherwise."""
    if choice != "auto":
        return choice
    return "collection" if cast.driver == cast.puppet else "clip"


def _retarget(runner: RunContext, cast, drive, frames, puppet, found, prov, sigma: float, lips: str,
              steady: int, widen: str, neutral: str, share: float) -> None:
    n = frames.n
    group = runner.root.require_group(cast.drive)
    cast.record(group)
    group.attrs.update({"n_photos": n, "photos_per_shard": runner.wf.photos_per_shard,
                        "canvas": frames.attrs["canvas"], "fps": frames.attrs["fps"]})
    fiducials = frames.array("aligned/fiducials")[:].astype(np.float64)
    pose = bridge(frames.array("pose")[:], found)
    pose[:, :6] = smooth_in_time(pose[:, :6], sigma)  # rvec, tvec
    driver_fiducials = bridge(steadied(fiducials, frames.in_order("aligned/rgb"), found, steady), found)
    collection = Collection(runner.root, cast.driver)
    driver_neutral = rest_shape(fiducials[found] if neutral == "clip" else _photo_fiducials(collection), share)
    puppet_neutral = rest_shape(_photo_fiducials(puppet), share)
    target = retarget(driver_fiducials, driver_neutral, puppet_neutral, lips=lips, widen=widen)
    for name, value, tail, dims in (
            ("target", target, (49, 2), ("frame", "fiducial", "xy")),
            ("pose", pose, (10,), ("frame", "field")),
            ("bridged", ~found, (), ("frame",))):
        drive.create(name, tail, value.dtype, dims, prov)[:] = value
    drive.create("photos/ids", (), str, ("frame",), prov)[:] = frames.array("photos/ids")[:]
    drive.create_status("retarget", prov)
    drive.write_status("retarget", 0, np.full(n, OK, np.int8), [""] * n)


def _photo_fiducials(coll: Collection) -> np.ndarray:
    """(n, 49, 2) the fiducials of a collection's accepted photos, those its mean fiducials are made of."""
    return coll.array("aligned/fiducials")[:][st.accepted(coll)].astype(np.float64)


def driver_sound(frames: Collection, fps: float) -> media.Audio | None:
    """The driver video's sound over the frames used (a frame range cuts it to match), or None:
    when the video has none, or the frames skip (``step`` > 1) and no sound can follow them."""
    index = frames.array("photos/frame")[:]
    sources = set(frames.array("photos/source")[:].tolist())
    if len(sources) != 1 or len(index) == 0 or np.any(np.diff(index) != 1):
        log.info("the driver's frames are not one continuous stretch of one video: the videos have no sound")
        return None
    return media.read_audio(sources.pop(), index[0] / fps, (index[-1] + 1) / fps)


def write_videos(drive: Collection, frames: Collection, output, stop: threading.Event | None = None) -> dict[str, str]:
    """puppet.mp4 (the puppet's face alone, on grey), side_by_side.mp4 (driver | puppet) and
    composite.mp4 (the ``composite`` stage's frames: B's face in A's light and frame), at the video's
    fps, with the driver video's sound (:func:`driver_sound`). Once ``stop`` is set (the run stops), they
    stop at the next shard of frames and none of the files is written."""
    fps = float(drive.attrs["fps"])
    arrays = [drive.array("render/rgb"), drive.array("render/mask"), frames.array("photos/rgb"),
              drive.array("composite/rgb")]

    def shard(start, stop):
        """A shard's frames, each as its three images."""
        out = []
        for rendered, mask, photo, composite in zip(*(a[start:stop] for a in arrays)):
            face = alone(rendered, st.render_alpha(mask))
            out.append((face, np.concatenate([photo, face], axis=1), composite))
        return out

    def images():
        """Every frame's three images, the next shard read and made in a thread while this one is encoded."""
        ranges = drive.shard_ranges()
        if not ranges:
            return
        with ThreadPoolExecutor(1) as reader:
            ahead = reader.submit(shard, *ranges[0])
            for following in ranges[1:] + [None]:
                made = ahead.result()
                if stop is not None and stop.is_set():
                    raise RuntimeError(f"{drive.path}: the videos were stopped before their last frame")
                if following is not None:
                    ahead = reader.submit(shard, *following)
                yield from made

    files = {name: storage.join(output, f"{name}.mp4") for name in ("puppet", "side_by_side", "composite")}
    media.write_videos_mp4(list(files.values()), images(), fps, driver_sound(frames, fps))
    return {name: str(file) for name, file in files.items()}
