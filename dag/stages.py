"""The per-photo stages: glue that maps a backend over the photos of one shard.

Per-photo stages (ingest, landmarks, pose, frontalize) run as one *chain* per shard:
a single Dask task decodes a shard's photos and passes them through every stage
in memory, so the raw photo is read once. Each stage still writes its own outputs,
its own per-photo status and its own provenance; a stage whose status for the shard
is already written (by an earlier, interrupted run with the same cache key) is not
recomputed, its outputs are read back instead.

Task functions take plain arguments (store URL, collection path, photo range,
backend names and params) and open the store themselves, so the same task runs in
a local process or on another machine.
"""

from __future__ import annotations

import importlib
import logging
import time
from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np

from persona.plugins.base import Backend, Rejected
from persona.plugins.face import mouth
from persona.plugins.face.collection_flow import collection_flow
from persona.plugins.face.composite import light_plane
from persona.plugins.face.fiducials import median_shape, shape_distance
from persona.plugins.face.template import CANONICAL_HEIGHT, CANONICAL_WIDTH, IDX49
from persona.plugins.kinds import POSE_FIELDS, Pose, Puppet
from persona.plugins.manager import default_registry
from persona.stores import media
from persona.stores.errors import InputError
from persona.stores.layout import OK, PENDING, REJECTED, UPSTREAM, Cast, Collection, open_store
from persona.stores.provenance import Provenance

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

    ``compute(backend, params, inputs, context)`` gets one photo's inputs by array name
    and returns its outputs by array name, or raises :class:`Rejected`. Input names are
    relative to the collection, or, for a drive's stages, "@frames/..." (:data:`FRAMES`) for the
    arrays of the driver's frames the drive performs (its :class:`Cast`'s ``frames``, on the same
    frame axis). ``context(root, path)`` loads what every
    photo shares (the collection's canvas is always in it). ``kind`` is the backend kind, or None
    for a stage without backends (ingest).
    """

    name: str
    kind: str | None
    upstream: str | None
    inputs: tuple[str, ...]
    outputs: tuple[Output, ...]
    compute: Callable[..., dict] = field(repr=False)
    context: Callable[..., dict] | None = field(default=None, repr=False)
    #: a stage without backends: the version in its cache key, raised when what it computes changes
    version: str = "1"


def _photo(inputs: dict) -> np.ndarray:
    h, w = inputs["photos/size"]
    return inputs["photos/rgb"][:h, :w]


def _ingest(backend, params, inputs, context):
    canvas = context["canvas"]
    source, frame = media.opened_path(str(inputs["photos/source"])), int(inputs["photos/frame"])
    hint, sha256 = None, ""
    if frame >= 0:  # a frame of a video listed among the photos
        image = media.read_video_frame(source, frame, max_side=params["max_side"])
    else:
        image, sha256 = media.decode_image(source, **params), media.sha256_file(source)
        hint = media.read_landmark_sidecar(source)
        if hint is not None:  # sidecars describe the file; the photo may have been downscaled
            hint = hint * (image.shape[1] / _original_width(source, params))
    if image.shape[0] > canvas[0] or image.shape[1] > canvas[1]:
        raise Rejected(f"{image.shape[1]}x{image.shape[0]} px, larger than the collection canvas "
                       f"{canvas[1]}x{canvas[0]}: the file changed on disk during the run?")
    rgb = np.zeros((*canvas, 3), np.uint8)
    rgb[:image.shape[0], :image.shape[1]] = image
    return {"photos/rgb": rgb, "photos/size": image.shape[:2],
            "photos/hint": np.full((68, 2), np.nan) if hint is None else hint, "photos/sha256": sha256}


def _original_width(source, params) -> int:
    return media.probe_image(source, max_pixels=params["max_pixels"], min_side=params["min_side"]).width


def _landmarks(backend, params, inputs, context):
    found = backend.detect(_photo(inputs), inputs["photos/hint"])
    return {"landmarks/points": found.points, "landmarks/fiducials": found.points[list(IDX49)],
            "landmarks/box": found.box, "landmarks/n_faces": found.n_faces}


def _pose(backend, params, inputs, context):
    pose = backend.estimate(inputs["landmarks/points"].astype(np.float64), tuple(inputs["photos/size"]))
    return {"pose": pose.as_vector()}


def _frontalize(backend, params, inputs, context):
    front = backend.frontalize(_photo(inputs), inputs["landmarks/points"].astype(np.float64),
                               Pose.from_vector(inputs["pose"]))
    return {"aligned/rgb": front.rgb, "aligned/mask": front.mask,
            "aligned/landmarks": front.landmarks, "aligned/fiducials": front.landmarks[list(IDX49)]}


INGEST = PhotoStage("ingest", None, None, ("photos/source", "photos/frame"), (
    Output("photos/rgb", (), "uint8", ("photo", "y", "x", "channel")),  # tail = the canvas
    Output("photos/size", (2,), "int32", ("photo", "hw")),
    Output("photos/hint", (68, 2), "float32", ("photo", "landmark", "xy")),
    Output("photos/sha256", (), "str", ("photo",)),
), _ingest)

LANDMARKS = PhotoStage("landmarks", "landmarks", "ingest", ("photos/rgb", "photos/size", "photos/hint"), (
    Output("landmarks/points", (68, 2), "float32", ("photo", "landmark", "xy")),
    Output("landmarks/fiducials", (49, 2), "float32", ("photo", "fiducial", "xy")),
    Output("landmarks/box", (4,), "float32", ("photo", "ltrb")),
    Output("landmarks/n_faces", (), "int16", ("photo",)),
), _landmarks)

POSE = PhotoStage("pose", "pose", "landmarks", ("landmarks/points", "photos/size"), (
    Output("pose", (len(POSE_FIELDS),), "float64", ("photo", "field")),
), _pose)

FRONTALIZE = PhotoStage("frontalize", "frontalize", "pose", ("photos/rgb", "photos/size", "landmarks/points", "pose"), (
    Output("aligned/rgb", (H, W, 3), "uint8", ("photo", "y", "x", "channel")),
    Output("aligned/mask", (H, W), "bool", ("photo", "y", "x")),
    Output("aligned/landmarks", (68, 2), "float32", ("photo", "landmark", "xy")),
    Output("aligned/fiducials", (49, 2), "float32", ("photo", "fiducial", "xy")),
), _frontalize)

#: the per-photo chain after ingest, in the order a shard's task runs it (one Dask task per shard)
CHAIN = (LANDMARKS, POSE, FRONTALIZE)


def _screen_context(root, path) -> dict:
    """The context of the screen: the median shape of the collection's frontalized photos, and the
    id of the first photo with each file content (byte-identical copies are used once)."""
    coll = Collection(root, path)
    first = {}
    for photo, digest in zip(coll.array("photos/ids")[:], coll.array("photos/sha256")[:]):
        if digest:  # video frames have none
            first.setdefault(str(digest), str(photo))
    return {"median": median_shape(coll.array("aligned/fiducials")[:][coll.state("frontalize") == OK]),
            "first": first}


def _screen(backend, params, inputs, context):
    original = context["first"].get(str(inputs["photos/sha256"]), str(inputs["photos/ids"]))
    if original != str(inputs["photos/ids"]):
        raise Rejected(f"a byte-identical copy of {original}, which is used (a photo counts once)")
    distance = shape_distance(inputs["aligned/fiducials"], context["median"])
    if not distance <= params["max_distance"]:
        raise Rejected(f"fiducials {distance:.0f} px (RMS) from the collection's median shape, more than "
                       f"max_distance {params['max_distance']:g}: its landmarks or pose failed")
    return {"aligned/shape_distance": distance}


#: the collection's screen of its frontalized photos: one whose visible fiducials lie far from the
#: collection's median shape is rejected (docs/fiducials.md), and so is a byte-identical copy of an
#: earlier photo; the photos it accepts are the collection's
SCREEN = PhotoStage("screen", None, "frontalize", ("aligned/fiducials", "photos/sha256", "photos/ids"), (
    Output("aligned/shape_distance", (), "float32", ("photo",)),
), _screen, _screen_context)


def accepted(coll: Collection) -> np.ndarray:
    """(n,) bool: the photos of a collection that every per-photo stage and the screen accepted."""
    return coll.state(SCREEN.name) == OK


def frontalizer(coll: Collection):
    """The frontalize backend, with its params, that made a collection's canonical faces (from its
    provenance): later stages that warp the photos again compose with its map (``canonical_map``)."""
    made = coll.provenance("status/frontalize/state")
    return default_registry().get("frontalize", made.backend)(made.params)


def _subspace(root, path) -> dict:
    """The context of the collection flow: the collection's subspace, mean fiducials, TPS smoothing,
    and the frontalize backend its photos went through, whose map it bends."""
    group = root[f"{path}/subspace"]
    return {"basis": group["basis"][...], "mean_fiducials": root[f"{path}/aligned/mean_fiducials"][...],
            "tps_lambda": float(group.attrs["tps_lambda"]), "frontalize": frontalizer(Collection(root, path))}


def _align(backend, params, inputs, context):
    """Collection flow (:func:`persona.plugins.face.collection_flow.collection_flow`) of one photo."""
    h, w = inputs["photos/size"]
    to_photo = context["frontalize"].canonical_map(Pose.from_vector(inputs["pose"]))
    return collection_flow(inputs["photos/rgb"][:h, :w], to_photo, inputs["aligned/fiducials"], inputs["aligned/mask"],
                           context["mean_fiducials"], context["basis"], context["tps_lambda"], backend)


#: non-rigid alignment by collection flow: runs after the subspace of the frontalized faces
ALIGN = PhotoStage(
    "align", "flow", "screen", ("photos/rgb", "photos/size", "pose", "aligned/fiducials", "aligned/mask"), (
        Output("collection/rgb", (H, W, 3), "uint8", ("photo", "y", "x", "channel")),
        Output("collection/mask", (H, W), "bool", ("photo", "y", "x")),
        Output("collection/map", (H, W, 2), "float32", ("photo", "y", "x", "xy")),
    ), _align, _subspace)


#: the prefix of a drive stage's inputs that are arrays of the driver's frames (:class:`PhotoStage`)
FRAMES = "@frames/"


def _puppet(root, path) -> dict:
    """The context of the render stages: the drive's puppet's average face, fiducials and mouth (each
    interior of B's mouth as its image and its photos' gap, or None), the neutral insets of B's and
    A's inner-lip corners that each frame's are drawn from (mouth.frame_insets; None without B's lips or
    A's landmarks), B's jaw line (the median of B's aligned photos' iBUG 0-16) and B's neutral texture."""
    cast = Cast.of(root, path)
    puppet, driver = Collection(root, cast.puppet), Collection(root, cast.driver)
    group = puppet.group["aligned"]
    fiducials = group["mean_fiducials"][...].astype(np.float64)
    lips = puppet.array("texture/lips")[...] if puppet.has("texture/lips") else None

    def interior(name):
        return ((puppet.array(name)[...].astype(np.float32), float(puppet.array(f"{name}_gap")[0]))
                if puppet.has(name) else None)

    insets = None  # B's and A's neutral inner-lip corners (mouth.frame_insets): B's mean, A's photos' median
    if lips is not None and driver.has("landmarks/points"):
        found = driver.state("landmarks") == OK
        theirs = mouth.landmark_inset(driver.array("landmarks/points")[:][found].astype(np.float64))
        ours = mouth.corner_inset(mouth.outer_corners(fiducials), lips[0, [0, -1]])
        insets = (ours, np.nanmedian(theirs, axis=0)) if len(theirs) else None
    jaw = group["landmarks"][:, :17][puppet.state("align") == OK].astype(np.float64)
    seen = np.isfinite(jaw).all(axis=2).sum(axis=0)  # a point a photo does not see (the far jaw) is NaN there
    jaw = np.nanmedian(jaw, axis=0) if (seen > 0).all() else None
    neutral = puppet.array("texture/neutral")[...] if puppet.has("texture/neutral") else None
    return {"coverage": group["coverage"][...], "fiducials": fiducials, "lips": lips, "insets": insets,
            "mouth": interior("texture/mouth"), "mouth_cavity": interior("texture/mouth_cavity"),
            "jaw": jaw, "neutral": neutral}


def _render(backend, params, inputs, context):
    h, w = inputs["@frames/photos/size"]
    frame = inputs["@frames/photos/rgb"][:h, :w]
    interior, gap = context["mouth"] or (None, np.inf)
    if context["mouth_cavity"] is not None:  # B's teeth or B's cavity, as A's own mouth shows them
        cavity, cavity_gap = context["mouth_cavity"]
        interior, gap = mouth.for_frame(interior, cavity, (gap, cavity_gap), float(inputs["mouth/teeth"]))
    pose, drivers = Pose.from_vector(inputs["pose"]), None
    if getattr(backend.params, "mouth_choice", None) == "frame" and interior is not None:
        drivers = mouth.from_frame(frame, inputs["@frames/landmarks/points"],  # A's own interior, where A's lips part
                                   max_inset=backend.params.frame_inset, min_gap=backend.params.frame_min_gap)
        if drivers is not None:  # its gap in this frame's px, where the renderer draws it
            interior, gap = drivers
        else:  # A's lips closed: none, B's own lips close over the gap the mesh leaves
            interior = None
    insets = None
    if context["insets"] is not None and "@frames/landmarks/points" in inputs:
        insets = mouth.frame_insets(*context["insets"], inputs["@frames/landmarks/points"])
    puppet = Puppet(appearance=inputs["texture/rgb"].astype(np.float32), coverage=context["coverage"],
                    fiducials=context["fiducials"], mesh=inputs.get("mesh"), mouth=interior,
                    lips=context["lips"], mouth_gap=gap, mouth_own=drivers is not None, lip_insets=insets,
                    jaw=context["jaw"], neutral=context["neutral"])
    out = backend.render(puppet, inputs["target"].astype(np.float64), pose, frame)
    mask = np.round(out.mask * 255).astype(np.uint8)
    own = np.zeros_like(mask) if out.own is None else np.round(out.own * 255).astype(np.uint8)
    # A's light at B's edge, fitted here where render and frame are at hand; the drive makes it steady in
    # time before the composite applies it
    return {"render/rgb": out.rgb, "render/mask": mask, "render/own": own,
            "render/light": light_plane(out.rgb, frame, render_alpha(mask))}


def render_alpha(mask: np.ndarray) -> np.ndarray:
    """A stored ``render/mask`` (uint8, as :func:`_render` writes it) as the renderer's alpha, float32 in [0, 1]."""
    return np.asarray(mask).astype(np.float32) / 255


_RENDER_OUTPUTS = (
    Output("render/rgb", (), "uint8", ("frame", "y", "x", "channel")),  # tail = the canvas
    Output("render/mask", (), "uint8", ("frame", "y", "x")),
    Output("render/own", (), "uint8", ("frame", "y", "x")),  # Rendered.own: the driver's own pixels, not relit
    Output("render/light", (4, 3), "float32", ("frame", "term", "channel")),  # composite.light_plane
)
_RENDER_INPUTS = ("target", "pose", "texture/rgb", "@frames/photos/rgb", "@frames/photos/size")

#: the puppet performing the driver's video: one "photo" per driver frame, in the ``drive`` collection
RENDER = PhotoStage("render", "render", "retarget", _RENDER_INPUTS, _RENDER_OUTPUTS, _render, _puppet)
#: the same for renderers of the 3D puppet: B's mesh of each frame (``mesh``, from the motion step) too, and
#: how much of B's teeth its mouth shows (``mouth/teeth``, from the teeth step)
RENDER_3D = PhotoStage("render3d", "render", "retarget", (*_RENDER_INPUTS, "mesh", "mouth/teeth",
                                                          "@frames/landmarks/points"),
                       _RENDER_OUTPUTS, _render, _puppet)


def _composite(backend, params, inputs, context):
    h, w = inputs["@frames/photos/size"]
    return {"composite/rgb": backend.composite(inputs["render/rgb"][:h, :w], inputs["@frames/photos/rgb"][:h, :w],
                                               render_alpha(inputs["render/mask"][:h, :w]),
                                               plane=inputs["composite/light"],
                                               own=render_alpha(inputs["render/own"][:h, :w]),
                                               points=inputs.get("@frames/landmarks/points"))}


#: B's rendered face blended into each driver frame by the ``composite`` backend (composite.mp4's frames), in
#: the light the ``light`` backend made of the render's fits (``composite/light``: drive.run_light); a frame
#: without a render is the driver's own
COMPOSITE = PhotoStage("composite", "composite", None, ("render/rgb", "render/mask", "render/own", "composite/light",
                                                        "@frames/photos/rgb", "@frames/photos/size",
                                                        "@frames/landmarks/points"),
                       (Output("composite/rgb", (), "uint8", ("frame", "y", "x", "channel")),), _composite)


def driver_model(root, path) -> dict:
    """The context of the dynamics stage: the driver's average model and the dynamics params."""
    from persona.plugins.face.dynamics import DriverModel, DynamicsParams

    driver = root[Cast.of(root, path).driver]
    shape, basis = driver["shape"], driver["subspace/basis"]
    return {"model": DriverModel.build(shape["depth"][...], shape["albedo"][...], shape["mask"][...], basis[...],
                                       driver["aligned/mean_fiducials"][...]),
            "dynamics": DynamicsParams.model_validate(root[path].attrs["motion"]["dynamics"])}


def _dynamics(backend, params, inputs, context):
    from persona.plugins.face.dynamics import track_frame

    h, w = inputs["@frames/photos/size"]
    track = track_frame(context["model"], inputs["@frames/photos/rgb"][:h, :w], Pose.from_vector(inputs["pose"]),
                        backend, context["dynamics"], inputs["@frames/landmarks/points"])
    return {"dynamics/flow": track.flow, "dynamics/delta": track.delta}


#: the driver's per-frame 3D flow (ALGORITHMS §9) before temporal smoothing: the flow of the
#: average face into each frame (``flow`` backend) and the depth change along the ray
DYNAMICS = PhotoStage(
    "dynamics", "flow", "retarget", ("pose", "@frames/photos/rgb", "@frames/photos/size",
                                     "@frames/landmarks/points"), (
        Output("dynamics/flow", (H, W, 2), "float32", ("frame", "y", "x", "xy")),
        Output("dynamics/delta", (H, W), "float32", ("frame", "y", "x")),
    ), _dynamics, driver_model)


#: how a stage runs: on each photo of a collection on its own, on each frame of a drive, once over a
#: whole collection, or once for a drive
PER = ("photo", "frame", "collection", "drive")


@dataclass(frozen=True)
class Stage:
    """One stage of a run, declared once; everything that runs, lists, draws or times stages reads it.

    ``where`` it runs: ``puppet``, ``driver``, ``video`` (the driver's frames) or ``drive``.
    ``per``: how it runs (:data:`PER`). ``needs``: the stages it reads, each the name of a stage of
    the same collection or drive, or, for a drive's stage, ``puppet:NAME``, ``driver:NAME`` or
    ``video:NAME`` (that stage of the drive's collection): the edges of the graph
    (:mod:`persona.dag.graph`). ``done``: the arrays whose provenance says the stage is done (the
    last it writes). ``version``: the version in its cache key, raised when what it computes changes,
    for a stage without a backend (a stage with a backend takes its backend's version, and a stage that
    maps a :class:`PhotoStage` keeps it there, as the screen's and the composite's). ``key``: the stage name its
    provenance records, when that differs from ``name``. ``run``: the function that runs it,
    ``"module:function"``, called as ``function(runner, stage, target)`` (:mod:`persona.dag.runner`);
    None for the per-photo stages that run inside ``ingest``'s chain, and for the drive's videos and
    evaluation, which the drive's outputs step makes. ``settings``: the workflow's stage settings it
    reads (``stages.<kind>``); ``makes`` and ``runs`` describe it in the plan; ``mesh``: only
    renderers of the 3D puppet need it (a puppet's such stage runs only when a drive uses the puppet);
    ``photo``: the :class:`PhotoStage` it maps over photos or
    frames (two for the render: 2D and 3D)."""

    name: str
    where: tuple[str, ...]
    settings: tuple[str, ...]
    makes: str
    per: str
    needs: tuple[str, ...] = ()
    done: tuple[str, ...] = ()
    version: str | None = None
    run: str | None = None
    runs: str = "tasks over shards"
    mesh: bool = False
    photo: tuple[PhotoStage, ...] = ()
    key: str = ""

    @property
    def provenance_name(self) -> str:
        """The stage name its provenance (and so its cache key) records."""
        return self.key or self.name

    def function(self) -> Callable | None:
        """The function :attr:`run` names, imported on first use (stage modules import this one)."""
        if self.run is None:
            return None
        module, name = self.run.split(":")
        return getattr(importlib.import_module(module), name)


_COLLECTION = ("puppet", "driver", "video")
_PERSON = ("puppet", "driver")
_CHAIN_RUNS = "the per-photo chain: one task per shard, ingest to frontalize"
STAGES = {stage.name: stage for stage in (
    Stage("ingest", _COLLECTION, ("ingest",), "each photo (or video frame) decoded onto the collection's canvas",
          "photo", done=("status/ingest/state",), version="1", run="persona.dag.collection:run_chain_stages",
          runs=_CHAIN_RUNS + "; a video's frames decoded in one pass first", photo=(INGEST,)),
    Stage("landmarks", _COLLECTION, ("landmarks",), "the face's 68 landmarks and its box", "photo",
          ("ingest",), ("status/landmarks/state",), runs=_CHAIN_RUNS, photo=(LANDMARKS,)),
    Stage("pose", _COLLECTION, ("pose",), "the head's pose and the camera", "photo", ("landmarks",),
          ("status/pose/state",), runs=_CHAIN_RUNS, photo=(POSE,)),
    Stage("frontalize", _COLLECTION, ("frontalize",), "the face warped to the canonical frontal view", "photo",
          ("pose",), ("status/frontalize/state",), runs=_CHAIN_RUNS, photo=(FRONTALIZE,)),
    Stage("screen", _COLLECTION, ("screen",), "photos far from the collection's median shape, and copies, "
          "rejected", "photo", ("frontalize",), ("status/screen/state",), run="persona.dag.collection:run_screen",
          photo=(SCREEN,)),
    Stage("mean", _COLLECTION, (), "the mean face of the accepted photos, its coverage and mean fiducials",
          "collection", ("screen",), ("aligned/mean_fiducials",), "1", run="persona.dag.collection:run_mean",
          runs="tasks over shards (a sum each), then the client"),
    Stage("subspace", _PERSON, ("align",), "the rank-k appearance subspace of the frontalized faces", "collection",
          ("mean",), ("subspace/basis",), "1", run="persona.dag.shape:run_subspace",
          runs="a randomised SVD over shards (dask.array)"),
    Stage("align", _PERSON, ("align", "flow"), "each photo's collection flow to the mean face", "photo",
          ("subspace",), ("status/align/state",), run="persona.dag.shape:run_alignment", photo=(ALIGN,)),
    Stage("shape", _PERSON, ("shape", "integrate"), "depth, albedo and meshes by photometric stereo", "collection",
          ("align",), ("shape/depth",), run="persona.dag.shape:run_shape",
          runs="tasks over shards (the mean), then one task (photometric stereo over the whole collection)"),
    Stage("texture", ("puppet",), ("texture",), "the expression-dependent texture's cache of aligned photos",
          "collection", ("align",), ("texture/neutral",), run="persona.dag.texture:run_texture",
          runs="tasks over shards (warp, basis by products over them, cache), then one task (the neutral texture)"),
    Stage("mouth", ("puppet",), ("render", "mouth"), "the inside of B's mouth from its open photos", "collection",
          ("screen",), ("texture/lips",), run="persona.dag.texture:run_mouth", runs="the client", mesh=True),
    Stage("retarget", ("drive",), ("motion",), "the driver's smoothed poses and B's target fiducials", "drive",
          ("video:screen", "puppet:mean", "driver:mean"), ("status/retarget/state",), "2",
          run="persona.dag.drive:run_retarget", runs="the client"),
    Stage("gaze", ("drive",), ("texture",), "where the driver's irises sit in their eyes in each frame, from the "
          "clip's usual gaze", "drive", ("retarget", "video:screen"), ("eyes/gaze",), "7",
          run="persona.dag.drive:run_gaze", runs="the client"),
    Stage("frame textures", ("drive",), ("texture",), "B's face for each frame's expression and gaze", "drive",
          ("retarget", "gaze", "puppet:texture"), ("texture/rgb",), run="persona.dag.texture:run_frame_textures",
          key="frame_texture"),
    Stage("dynamics", ("drive",), ("flow", "motion"), "the driver's per-frame 3D flow", "frame",
          ("retarget", "driver:shape"), ("status/dynamics/state",), run="persona.dag.motion:run_dynamics",
          mesh=True, photo=(DYNAMICS,)),
    Stage("motion", ("drive",), ("motion", "transfer", "denoise"), "A's meshes, then B's by the motion transfer "
          "(and the meshes the workflow exports)", "drive", ("dynamics", "puppet:shape"), ("mesh",),
          run="persona.dag.motion:run_motion", mesh=True),
    Stage("teeth", ("drive",), ("render", "mouth"), "how much of B's teeth each frame shows, as the driver's mouth "
          "shows them (mouth_choice: driver)", "drive", ("retarget", "puppet:mouth", "video:screen"),
          ("mouth/teeth",), "1", run="persona.dag.drive:run_teeth", runs="the client", mesh=True),
    Stage("render", ("drive",), ("render",), "the puppet's frames", "frame",
          ("retarget", "frame textures", "motion", "teeth"), ("status/render/state",),
          run="persona.dag.drive:run_render", photo=(RENDER, RENDER_3D)),
    Stage("light", ("drive",), ("light",), "A's light at B's edge (fitted with the render), made "
          "steady over the frames around", "drive", ("render",), ("composite/light",),
          run="persona.dag.drive:run_light", runs="the client"),
    Stage("composite", ("drive",), ("composite",), "B's face blended into each of the driver's frames", "frame",
          ("render", "light"), ("status/composite/state",), run="persona.dag.drive:run_composite",
          photo=(COMPOSITE,)),
    Stage("videos", ("drive",), (), "puppet.mp4, side_by_side.mp4, composite.mp4 (encoded)", "drive",
          ("composite",), runs="the client"),
    Stage("evaluate", ("drive",), ("identity",), "metrics.json and report.html", "drive", ("composite",),
          runs="tasks over shards, then the client"),
)}

#: what each per-photo stage computes, by the name its status and provenance carry
PHOTO_STAGES = {photo.name: photo for stage in STAGES.values() for photo in stage.photo}
#: the stages every collection's photos go through, in order: the ``stages`` a collection records
COLLECTION_STAGES = tuple(name for name, stage in STAGES.items() if stage.where == _COLLECTION and stage.photo)


def provenance(name: str, *, params: dict, inputs: dict[str, str], persona_version: str, backend: str = "-",
               backend_version: str | None = None) -> Provenance:
    """The provenance of the next run of the stage ``name`` (of :data:`STAGES`, or of
    :data:`PHOTO_STAGES`, whose name it records as it is): its cache key from the stage's own version (or
    ``backend_version``, a backend's: :func:`backend_key`), ``params`` and ``inputs`` (name -> the cache
    key of what it reads)."""
    if name in PHOTO_STAGES:
        recorded, version = name, PHOTO_STAGES[name].version
    else:
        recorded, version = STAGES[name].provenance_name, STAGES[name].version
    version = version if backend_version is None else backend_version
    if version is None:
        raise ValueError(f"stage {name!r} declares no version and has no backend's to take")
    return Provenance.make(stage=recorded, backend=backend, backend_version=version,
                           params=params, inputs=inputs, persona_version=persona_version)


def backend_key(kind: str, name: str) -> tuple[str, str]:
    """(backend name, version) that cache keys record for the backend ``name`` of ``kind``: its
    ``key_name`` ("-" for a built-in backend of a stage that had none to choose before) or its name."""
    cls = default_registry().get(kind, name)
    return cls.key_name or name, cls.version


def is_done(coll: Collection, prov: Provenance, *names: str) -> bool:
    """Whether the arrays ``names`` of ``coll`` are done and were made with ``prov`` (the same cache key):
    the one test of "nothing to recompute"; a stage left unfinished (an array created pending, its
    provenance written after the data: :meth:`Collection.mark_done`) is not done."""
    return coll.exists() and all(coll.made_by(name, prov) for name in names)


def output_tail(output: Output, canvas) -> tuple[int, ...]:
    """The per-photo shape of an output; frame-sized outputs take the collection's canvas."""
    if output.name in ("photos/rgb", "render/rgb", "composite/rgb"):
        return (*canvas, 3)
    return tuple(canvas) if output.name in ("render/mask", "render/own") else output.tail


def _empty(output: Output, n: int, canvas) -> np.ndarray:
    tail = output_tail(output, canvas)
    if output.dtype == "str":
        return np.full((n, *tail), "", dtype=object)
    fill = np.nan if np.dtype(output.dtype).kind == "f" else 0
    return np.full((n, *tail), fill, dtype=output.dtype)


def _backend(stage: PhotoStage, name: str, params: dict) -> Backend | None:
    return None if stage.kind is None else default_registry().get(stage.kind, name)(params)


#: what the last shard task in this process loaded for its stage, under that stage's cache key
_loaded: dict[str, object] = {}


def per_process(key: str, load: Callable[[], object]):
    """``load()`` once per worker process for the cache key ``key`` (a stage's provenance key, so
    that changed inputs load anew); the shards a worker runs next share it. One entry is kept."""
    if key not in _loaded:
        _loaded.clear()
        _loaded[key] = load()
    return _loaded[key]


def on_shard(fn: Callable, url: str, path: str, start: int, stop: int, *args) -> tuple[int, int, object]:
    """A collection-level stage's task: ``fn(url, path, start, stop, *args)`` on frames [start, stop)
    of one shard, which it reads and writes itself (one writer per shard file); returns the range
    with ``fn``'s result."""
    return start, stop, fn(url, path, start, stop, *args)


def run_chain(url: str, path: str, start: int, stop: int, steps: list[tuple[str, str, dict]]) -> dict:
    """Run stages ``steps`` = [(stage, backend name, params), ...] on photos [start, stop).

    Writes each stage's outputs and then its status. Returns per-stage summaries.
    """
    root = open_store(url)
    coll = Collection(root, path)
    canvas = tuple(coll.attrs["canvas"])
    n = stop - start
    shard: dict[str, np.ndarray] = {}  # this shard's arrays, computed here or read back

    def get(name: str) -> np.ndarray:
        if name not in shard:
            source = Collection(root, Cast.of(root, path).frames) if name.startswith(FRAMES) else coll
            shard[name] = source.array(name.removeprefix(FRAMES))[start:stop]
        return shard[name]

    summaries = {}
    for stage_name, backend_name, params in steps:
        t0 = time.perf_counter()
        stage = PHOTO_STAGES[stage_name]
        status = f"status/{stage_name}/state"
        if not (get(status) == PENDING).any():  # done by an earlier run: keep it
            summaries[stage_name] = _summary(get(status), 0.0, skipped=True)
            continue
        backend = _backend(stage, backend_name, params)
        context = {"canvas": canvas, **(_context(stage, root, url, path) if stage.context else {})}
        ready = np.ones(n, bool) if stage.upstream is None else get(f"status/{stage.upstream}/state") == OK
        inputs = {name: get(name) for name in stage.inputs}
        outputs = {o.name: _empty(o, n, canvas) for o in stage.outputs}
        state = np.full(n, UPSTREAM, np.int8)
        reasons = [""] * n
        for j in np.flatnonzero(ready):
            try:
                result = stage.compute(backend, params, {k: v[j] for k, v in inputs.items()}, context)
            except (Rejected, media.PhotoRejected) as exc:
                state[j], reasons[j] = REJECTED, exc.reason
                continue
            except Exception as exc:  # one odd photo must not end a long run; the reason says it all
                log.warning("%s %s photo %d: unexpected %r", path, stage_name, start + j, exc, exc_info=True)
                state[j], reasons[j] = REJECTED, f"unexpected error in {stage_name}: {type(exc).__name__}: {exc}"
                continue
            for name, value in result.items():
                outputs[name][j] = value
            state[j] = OK
        for name, value in outputs.items():
            coll.array(name)[start:stop] = value.astype(str) if value.dtype == object else value
            shard[name] = value
        coll.write_status(stage_name, start, state, reasons)
        shard[status] = state
        summaries[stage_name] = _summary(state, time.perf_counter() - t0)
    return summaries


def _context(stage: PhotoStage, root, url: str, path: str) -> dict:
    """What every photo of ``stage`` shares (``stage.context``), loaded once per worker process for the
    stage's run (its cache key, :func:`per_process`): the shards a worker runs next reuse it, with what it
    built on first use (the driver model's landmark spline and shading operators, 0.3 s a shard)."""
    key = Collection(root, path).provenance(f"status/{stage.name}/state").key
    return per_process(f"{url} {path} {stage.name} {key}", lambda: stage.context(root, path))


def _summary(state: np.ndarray, seconds: float, skipped: bool = False) -> dict:
    return {"n": int(len(state)), "ok": int((state == OK).sum()), "rejected": int((state == REJECTED).sum()),
            "seconds": seconds, "skipped": skipped}


def aligned_sum(url: str, path: str, start: int, stop: int, group: str = "aligned",
                stage: str = "screen") -> dict | None:
    """Sum of the accepted faces ``group``/rgb of photos [start, stop), weighted by visibility,
    and the per-pixel count: one shard's part of a mean face (None, nothing read, when the shard
    has no accepted photo)."""
    coll = Collection(open_store(url, mode="r"), path)
    ok = coll.array(f"status/{stage}/state")[start:stop] == OK
    if not ok.any():
        return None
    mask = coll.array(f"{group}/mask")[start:stop] & ok[:, None, None]
    rgb = coll.array(f"{group}/rgb")[start:stop]
    return {"sum": np.einsum("nyxc,nyx->yxc", rgb, mask, dtype=np.float64),
            "count": mask.sum(axis=0, dtype=np.int64)}


def add_sums(a: dict, b: dict) -> dict:
    """Two shards' :func:`aligned_sum` together."""
    return {"sum": a["sum"] + b["sum"], "count": a["count"] + b["count"]}


def ingest_video(url: str, path: str, params: dict) -> dict:
    """Decode the frames of a video collection in one sequential pass, shard by shard.

    Shards already ingested (an interrupted run) are decoded past but not rewritten.
    """
    t0 = time.perf_counter()
    coll = Collection(open_store(url), path)
    canvas = tuple(coll.attrs["canvas"])
    video = coll.attrs["video"]
    position = {int(f): i for i, f in enumerate(coll.array("photos/frame")[:])}
    done = coll.state("ingest") != PENDING
    if done.all():  # an earlier run decoded every frame
        return {"ingest": _summary(coll.state("ingest"), 0.0, skipped=True)}
    ends = dict(coll.shard_ranges())
    buffer: dict[int, np.ndarray] = {}
    try:
        with media.VideoReader(video["path"]) as reader:
            for index, image in reader.frames(video["start"], video["stop"], video["step"]):
                i = position.get(index)
                if i is None or done[i]:
                    continue
                buffer[i] = image if image.shape[:2] == canvas else cv2.resize(
                    image, (canvas[1], canvas[0]), interpolation=cv2.INTER_AREA)
                start = i - i % coll.shard
                if all(k in buffer for k in range(start, ends[start])):
                    _write_frames(coll, start, ends[start], {k: buffer.pop(k) for k in range(start, ends[start])},
                                  canvas)
    except InputError as exc:  # damaged part-way: what was decoded before the damage is kept
        log.warning("%s; the frames decoded before it are kept", exc)
    state = coll.state("ingest")
    for start, stop in coll.shard_ranges():  # the shards the container did not deliver whole (truncated)
        if (state[start:stop] == PENDING).any():
            _write_frames(coll, start, stop, {k: buffer.pop(k) for k in range(start, stop) if k in buffer}, canvas)
    return {"ingest": _summary(coll.state("ingest")[~done], time.perf_counter() - t0)}  # this pass's frames


def _write_frames(coll: Collection, start: int, stop: int, frames: dict[int, np.ndarray], canvas) -> None:
    """The shard [start, stop) of a video collection: the decoded ``frames`` by index; a frame the
    container promised but did not deliver (a truncated or damaged file) is rejected, its neighbours kept."""
    n = stop - start
    rgb = np.zeros((n, *canvas, 3), np.uint8)
    decoded = np.zeros(n, bool)
    for k, image in frames.items():
        rgb[k - start], decoded[k - start] = image, True
    coll.array("photos/rgb")[start:stop] = rgb
    coll.array("photos/size")[start:stop] = np.tile(np.array(canvas, np.int32), (n, 1))
    coll.array("photos/hint")[start:stop] = np.full((n, 68, 2), np.nan, np.float32)
    coll.array("photos/sha256")[start:stop] = np.full(n, "", dtype=object).astype(str)
    coll.write_status("ingest", start, np.where(decoded, OK, REJECTED).astype(np.int8),
                      ["" if d else "frame could not be decoded" for d in decoded])
