"""The stages: glue that reads a shard of inputs from the store, maps a backend over
its photos, and writes the outputs and the per-photo status back.

Every function here that runs on a Dask worker takes plain arguments (store URL,
collection path, photo range, backend name and params) and opens the store itself,
so the same task runs in a local process or on another machine.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np

from persona.plugins.base import Backend, Rejected
from persona.plugins.face.template import CANONICAL_HEIGHT, CANONICAL_WIDTH, IDX49
from persona.plugins.kinds import POSE_FIELDS, Pose
from persona.plugins.manager import default_registry
from persona.stores import media
from persona.stores.layout import OK, PENDING, REJECTED, UPSTREAM, Collection, open_store

log = logging.getLogger(__name__)

H, W = CANONICAL_HEIGHT, CANONICAL_WIDTH


@dataclass(frozen=True)
class Output:
    name: str
    tail: tuple[int, ...]
    dtype: str
    dims: tuple[str, ...]


@dataclass(frozen=True)
class PhotoStage:
    """A stage that processes each photo on its own.

    ``compute(backend, inputs)`` gets one photo's input arrays by name and returns
    its outputs by name, or raises :class:`Rejected`.
    """

    name: str
    kind: str
    upstream: str
    inputs: tuple[str, ...]
    outputs: tuple[Output, ...]
    compute: Callable[[Backend, dict], dict] = field(repr=False)


def _photo(inputs: dict) -> np.ndarray:
    h, w = inputs["photos/size"]
    return inputs["photos/rgb"][:h, :w]


def _landmarks(backend, inputs):
    found = backend.detect(_photo(inputs), inputs["photos/hint"])
    return {"landmarks/points": found.points, "landmarks/fiducials": found.points[list(IDX49)],
            "landmarks/box": found.box, "landmarks/n_faces": found.n_faces}


def _pose(backend, inputs):
    pose = backend.estimate(inputs["landmarks/points"].astype(np.float64), tuple(inputs["photos/size"]))
    return {"pose": pose.as_vector()}


def _frontalize(backend, inputs):
    front = backend.frontalize(_photo(inputs), inputs["landmarks/points"].astype(np.float64),
                               Pose.from_vector(inputs["pose"]))
    return {"aligned/rgb": front.rgb, "aligned/mask": front.mask,
            "aligned/landmarks": front.landmarks, "aligned/fiducials": front.landmarks[list(IDX49)]}


PHOTO_STAGES = {
    s.name: s for s in (
        PhotoStage("landmarks", "landmarks", "ingest", ("photos/rgb", "photos/size", "photos/hint"), (
            Output("landmarks/points", (68, 2), "float32", ("photo", "point", "xy")),
            Output("landmarks/fiducials", (49, 2), "float32", ("photo", "point", "xy")),
            Output("landmarks/box", (4,), "float32", ("photo", "ltrb")),
            Output("landmarks/n_faces", (), "int16", ("photo",)),
        ), _landmarks),
        PhotoStage("pose", "pose", "landmarks", ("landmarks/points", "photos/size"), (
            Output("pose", (len(POSE_FIELDS),), "float64", ("photo", "field")),
        ), _pose),
        PhotoStage("frontalize", "frontalize", "pose",
                   ("photos/rgb", "photos/size", "landmarks/points", "pose"), (
            Output("aligned/rgb", (H, W, 3), "uint8", ("photo", "y", "x", "channel")),
            Output("aligned/mask", (H, W), "bool", ("photo", "y", "x")),
            Output("aligned/landmarks", (68, 2), "float32", ("photo", "point", "xy")),
            Output("aligned/fiducials", (49, 2), "float32", ("photo", "point", "xy")),
        ), _frontalize),
    )
}


def make_backend(kind: str, name: str, params: dict) -> Backend:
    return default_registry().get(kind, name)(params)


def _fill(dtype: str):
    return np.nan if np.dtype(dtype).kind == "f" else 0


def run_photo_shard(url: str, path: str, stage_name: str, start: int, stop: int,
                    backend_name: str, params: dict) -> dict:
    """Run one stage on photos [start, stop) of a collection; write outputs, then status."""
    t0 = time.perf_counter()
    stage = PHOTO_STAGES[stage_name]
    coll = Collection(open_store(url), path)
    backend = make_backend(stage.kind, backend_name, params)
    ready = coll.array(f"status/{stage.upstream}/state")[start:stop] == OK
    inputs = {name: coll.array(name)[start:stop] for name in stage.inputs}
    n = stop - start
    outputs = {o.name: np.full((n, *o.tail), _fill(o.dtype), dtype=o.dtype) for o in stage.outputs}
    state = np.full(n, UPSTREAM, np.int8)
    reasons = [""] * n
    for j in np.flatnonzero(ready):
        try:
            result = stage.compute(backend, {k: v[j] for k, v in inputs.items()})
        except Rejected as exc:
            state[j], reasons[j] = REJECTED, exc.reason
            continue
        except Exception as exc:  # one odd photo must not end a long run; the reason says it all
            log.warning("%s %s photo %d: unexpected %s", path, stage_name, start + j, exc, exc_info=True)
            state[j], reasons[j] = REJECTED, f"unexpected error in {backend_name}: {type(exc).__name__}: {exc}"
            continue
        for name, value in result.items():
            outputs[name][j] = value
        state[j] = OK
    for name, value in outputs.items():
        coll.array(name)[start:stop] = value
    coll.write_status(stage_name, start, state, reasons)
    return _summary(state, time.perf_counter() - t0)


def _summary(state: np.ndarray, seconds: float) -> dict:
    return {"n": int(len(state)), "ok": int((state == OK).sum()),
            "rejected": int((state == REJECTED).sum()), "seconds": seconds}


# -- ingest ---------------------------------------------------------------------------

INGEST_OUTPUTS = (
    Output("photos/size", (2,), "int32", ("photo", "hw")),
    Output("photos/hint", (68, 2), "float32", ("photo", "point", "xy")),
    Output("photos/sha256", (), "str", ("photo",)),
)


def _fit(image: np.ndarray, canvas: tuple[int, int]) -> np.ndarray:
    """Place an image at the top-left of a zero canvas (images never exceed it)."""
    out = np.zeros((*canvas, 3), np.uint8)
    h, w = image.shape[:2]
    out[:h, :w] = image
    return out


def ingest_image_shard(url: str, path: str, start: int, stop: int, params: dict) -> dict:
    """Decode photos [start, stop) of an image collection into the store."""
    t0 = time.perf_counter()
    coll = Collection(open_store(url), path)
    canvas = tuple(coll.attrs["canvas"])
    sources = coll.array("photos/source")[start:stop]
    n = stop - start
    rgb = np.zeros((n, *canvas, 3), np.uint8)
    size = np.zeros((n, 2), np.int32)
    hint = np.full((n, 68, 2), np.nan, np.float32)
    sha = [""] * n
    state = np.full(n, OK, np.int8)
    reasons = [""] * n
    for j, source in enumerate(sources):
        try:
            image = media.decode_image(source, **params)
            if image.shape[0] > canvas[0] or image.shape[1] > canvas[1]:
                raise media.PhotoRejected(f"image {image.shape[1]}x{image.shape[0]} larger than the "
                                          f"collection canvas {canvas[1]}x{canvas[0]}: changed on disk since the run started?")
            points = media.read_landmark_sidecar(source)
            if points is not None:
                points = points * (image.shape[1] / media.probe_image(source, **_probe(params)).width)
                hint[j] = points
            sha[j] = media.sha256_file(source)
        except media.PhotoRejected as exc:
            state[j], reasons[j] = REJECTED, exc.reason
            continue
        rgb[j] = _fit(image, canvas)
        size[j] = image.shape[:2]
    _write_ingest(coll, start, rgb, size, hint, sha, state, reasons)
    return _summary(state, time.perf_counter() - t0)


def _probe(params: dict) -> dict:
    return {k: params[k] for k in ("max_pixels", "min_side")}


def ingest_video(url: str, path: str, params: dict) -> dict:
    """Decode the frames of a video collection shard by shard (one sequential pass)."""
    t0 = time.perf_counter()
    coll = Collection(open_store(url), path)
    canvas = tuple(coll.attrs["canvas"])
    video = coll.attrs["video"]
    frames = coll.array("photos/frame")[:]
    done = coll.state("ingest") != PENDING
    wanted = {int(f): i for i, f in enumerate(frames)}
    shards = {s: e for s, e in coll.shard_ranges()}
    buffer: dict[int, np.ndarray] = {}
    with media.VideoReader(video["path"]) as reader:
        for index, image in reader.frames(video["start"], video["stop"], video["step"]):
            i = wanted.get(index)
            if i is None or done[i]:
                continue
            buffer[i] = image
            start = i - i % coll.shard
            stop = shards[start]
            if all(k in buffer for k in range(start, stop)):
                n = stop - start
                rgb = np.stack([_resize(buffer.pop(k), canvas) for k in range(start, stop)])
                size = np.tile(np.array(canvas, np.int32), (n, 1))
                hint = np.full((n, 68, 2), np.nan, np.float32)
                state = np.full(n, OK, np.int8)
                _write_ingest(coll, start, rgb, size, hint, [""] * n, state, [""] * n)
    missing = np.flatnonzero(coll.state("ingest") == PENDING)
    if len(missing):  # the container promised frames it did not deliver
        for start, stop in coll.shard_ranges():
            idx = [i for i in missing if start <= i < stop]
            if idx:
                state = coll.state("ingest")[start:stop]
                reasons = list(coll.reasons("ingest")[start:stop])
                for i in idx:
                    state[i - start], reasons[i - start] = REJECTED, "frame could not be decoded"
                coll.write_status("ingest", start, state, reasons)
    return _summary(coll.state("ingest"), time.perf_counter() - t0)


def _resize(image: np.ndarray, canvas) -> np.ndarray:
    """A video frame at the collection's canvas size (videos above max_side are downscaled)."""
    if image.shape[:2] == tuple(canvas):
        return image
    return cv2.resize(image, (canvas[1], canvas[0]), interpolation=cv2.INTER_AREA)


def _write_ingest(coll, start, rgb, size, hint, sha, state, reasons):
    stop = start + len(state)
    coll.array("photos/rgb")[start:stop] = rgb
    coll.array("photos/size")[start:stop] = size
    coll.array("photos/hint")[start:stop] = hint
    coll.array("photos/sha256")[start:stop] = np.asarray(sha, dtype=object).astype(str)
    coll.write_status("ingest", start, state, reasons)
