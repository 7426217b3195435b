"""Expression-dependent texture in the run (paper §5-§6).

Video mode, the paper's way for puppetry: the collection is warped once to the puppet's mean
fiducials (the ``align`` stage's collection flow already does exactly this, with the workflow's
``flow`` stage; the texture backend's own ``flow`` param is for synthesis to one target), the target-
independent terms of Eq. 3 (Laplacian pyramids times detail weights) are cached in the store
under ``texture/``, and each driver frame only changes the expression weights. The textures
keep the neutral geometry with the target's detail; the renderer moves the geometry.

Stored: ``<puppet>/texture/weighted_<k>``, ``texture/detail_<k>`` (per photo and level),
``texture/neutral`` (the texture at the mean fiducials) and ``drive/texture/rgb`` (per frame).
For 3D renderers also the inside of B's mouth (:mod:`persona.plugins.face.mouth`):
``texture/mouth`` (when a photo shows it) and ``texture/lips`` (B's mean inner-lip curves,
written last).
"""

from __future__ import annotations

import logging

import numpy as np

from persona.plugins.face import mouth
from persona.plugins.face.blend import BlendCache, level_bias
from persona.plugins.face.texture import Aligned
from persona.plugins.kinds import Pose, TexturePhotos
from persona.stores import media, storage
from persona.stores.layout import OK, Collection, open_store
from persona.stores.provenance import Provenance

from . import stages as st

log = logging.getLogger(__name__)


def texture_photos(coll: Collection, rows: np.ndarray) -> TexturePhotos:
    """The photos ``rows`` of a collection as texture backends see them: raw photos, frontalizing
    maps (the frontalize backend's, from each photo's pose), visibility, pose-corrected fiducials."""
    rows = np.asarray(rows)
    sizes, poses = coll.array("photos/size")[:], coll.array("pose")[:]
    fiducials, frontalize = coll.array("aligned/fiducials")[:], st.frontalizer(coll)
    photos, maps, visible = [], [], []
    for i in rows:
        h, w = sizes[i]
        photos.append(coll.array("photos/rgb")[i][:h, :w])
        maps.append(frontalize.canonical_map(Pose.from_vector(poses[i])))
        visible.append(coll.array("aligned/mask")[i])
    return TexturePhotos(tuple(photos), np.stack(maps), np.stack(visible), fiducials[rows].astype(np.float64))


def texture_backend(runner):
    name, params = runner.wf.stage("texture")
    return name, params, st.default_registry().get("texture", name)(params)


def video_aligned(coll: Collection, ok: np.ndarray, backend, alignment: str | None) -> Aligned:
    """The accepted photos ``ok`` of a collection aligned to its mean fiducials for the video-mode
    cache: with the texture backend's own flow and misfit measures (``alignment`` "own"), or as the
    align stage's collection flow warped them (anything else)."""
    if alignment == "own":
        target = coll.array("aligned/mean_fiducials")[...].astype(np.float64)
        return backend.params.aligned(texture_photos(coll, ok), target)
    return Aligned(coll.rows("collection/rgb", ok).astype(np.float32), coll.rows("collection/mask", ok))


def run_texture(runner, coll: Collection, aligned: Provenance) -> dict[str, str]:
    """The video-mode cache of the aligned collection and its neutral texture; returns the
    picture written (``texture_neutral``)."""
    name, params, backend = texture_backend(runner)
    prov = Provenance.make(stage="texture", backend=name, backend_version=backend.version, params=params,
                           inputs={"align": aligned.key}, persona_version=runner.version)
    out = storage.join(runner.wf.output, f"{coll.path.replace('/', '_')}_texture_neutral.png")
    if coll.made_by("texture/neutral", prov) and storage.isfile(out):
        return {"texture_neutral": str(out)}
    ok = np.flatnonzero(coll.state("align") == OK)
    mean_fiducials = coll.array("aligned/mean_fiducials")[...].astype(np.float64)
    try:
        cache = backend.cache(video_aligned(coll, ok, backend, params.get("video_alignment")))
    except NotImplementedError:
        log.warning("texture backend %s has no video mode: the drive shows the static average", name)
        coll.remove("texture/neutral")  # another backend's, from an earlier run
        return {}
    row = np.full(coll.n, -1)
    row[ok] = np.arange(len(ok))
    for k in range(cache.levels):
        y, x = ("y", "x") if k == 0 else (f"y_level{k}", f"x_level{k}")  # one size per name, as xarray needs
        for kind, level, last in (("weighted", cache.weighted[k], "channel"), ("detail", cache.detail[k], "weight")):
            array = coll.create(f"texture/{kind}_{k}", level.shape[1:], np.float32, ("photo", y, x, last), prov)
            for start, stop in coll.shard_ranges():  # a shard at a time; rejected photos stay NaN
                rows = row[start:stop]
                block = np.full((stop - start, *level.shape[1:]), np.nan, np.float32)
                block[rows >= 0] = level[rows[rows >= 0]]
                array[start:stop] = block
    neutral = backend.blend(cache, coll.array("aligned/fiducials")[:][ok], mean_fiducials)
    coll.create_single("texture/neutral", neutral.round().astype(np.uint8), ("y", "x", "channel"), prov)
    media.write_png(out, np.kron(neutral.round().astype(np.uint8), np.ones((2, 2, 1), np.uint8)))
    return {"texture_neutral": str(out)}


def load_cache(coll: Collection) -> tuple[BlendCache, np.ndarray]:
    """The stored video-mode cache and the fiducials of its photos."""
    ok = np.flatnonzero(coll.state("align") == OK)
    levels = sum(1 for key in coll.group["texture"].array_keys() if key.startswith("weighted_"))
    params = coll.provenance("texture/neutral").params
    weighted = [coll.rows(f"texture/weighted_{k}", ok) for k in range(levels)]
    detail = [coll.rows(f"texture/detail_{k}", ok) for k in range(levels)]
    cache = BlendCache(weighted, detail, level_bias(levels, params["beta"], params["tau"]))
    return cache, coll.array("aligned/fiducials")[:][ok].astype(np.float64)


def run_frame_textures(runner, drive: Collection, puppet: Collection, retargeted: Provenance) -> Provenance:
    """B's texture for every driver frame: ``drive/texture/rgb`` (frame, H, W, 3) uint8, from the
    video-mode cache and the frame's target fiducials, or B's static mean face when the texture
    backend has no video mode."""
    texture = puppet.provenance("texture/neutral")
    source = texture if texture is not None else puppet.provenance("aligned/mean")
    prov = Provenance.make(stage="frame_texture", backend=source.backend, backend_version=source.backend_version,
                           params=source.params, inputs={"texture": source.key, "retarget": retargeted.key},
                           persona_version=runner.version)
    if drive.made_by("texture/rgb", prov):
        return prov
    array = drive.create("texture/rgb", puppet.array("aligned/mean").shape, np.uint8, ("frame", "y", "x", "channel"),
                         prov, pending=True)
    if texture is None:
        mean = np.clip(puppet.array("aligned/mean")[...], 0, 255).round().astype(np.uint8)
        for start, stop in drive.shard_ranges():
            array[start:stop] = np.broadcast_to(mean, (stop - start, *mean.shape))
        drive.mark_done("texture/rgb", prov)
        return prov
    runner.map_shards(drive, "texture", frame_textures, prov.key, puppet.path, *runner.wf.stage("texture"))
    drive.mark_done("texture/rgb", prov)  # after the last frame: a killed run leaves no key to trust
    return prov


def frame_textures(url: str, path: str, start: int, stop: int, key: str, puppet: str, name: str,
                   params: dict) -> None:
    """One shard's task of :func:`run_frame_textures`: B's texture for frames [start, stop) with the
    texture backend ``name``; the ``puppet`` collection's video-mode cache is read once per worker."""
    root = open_store(url)
    drive = Collection(root, path)
    backend = st.default_registry().get("texture", name)(params)
    cache, fiducials = st.per_process(key, lambda: load_cache(Collection(root, puppet)))
    drive.array("texture/rgb")[start:stop] = np.stack([backend.blend(cache, fiducials, t).round().astype(np.uint8)
                                                       for t in drive.array("target")[start:stop]])


def run_mouth(runner, coll: Collection) -> Provenance:
    """The inside of B's mouth for the renderer (``mouth``, ``mouth_photos`` and ``mouth_min_gap``
    of its params): the median of B's widest-open accepted photos between their inner lips, and B's
    mean inner-lip curves in the canonical frame."""
    name, params = runner.wf.stage("render")
    chosen = st.default_registry().get("render", name)(params).params
    settings = {"photos": chosen.mouth_photos, "min_gap": chosen.mouth_min_gap}
    prov = Provenance.make(stage="mouth", backend="-", backend_version="1", params=settings,
                           inputs={"screen": coll.provenance("status/screen/state").key},
                           persona_version=runner.version)
    if coll.made_by("texture/lips", prov):
        return prov
    ok = np.flatnonzero(st.accepted(coll))
    points = coll.array("landmarks/points").oindex[ok].astype(np.float64)
    sizes = coll.array("photos/size").oindex[ok]
    photos = []
    for i in mouth.widest(points, settings["photos"], settings["min_gap"]):
        h, w = sizes[i]
        photos.append((coll.array("photos/rgb")[int(ok[i])][:h, :w], points[i]))
    interior = mouth.interior(photos)
    coll.remove("texture/mouth")  # an earlier run's
    if interior is None:
        log.warning("%s: no photo with the lips %.2f inter-ocular distances apart; the puppet's mouth shows "
                    "no interior when it opens", coll.path, settings["min_gap"])
    else:
        coll.create_single("texture/mouth", interior.round().astype(np.uint8), ("mouth_t", "mouth_s", "channel"),
                           prov)
    landmarks = coll.array("aligned/landmarks").oindex[ok].astype(np.float64)
    lips = mouth.lip_curves(np.nanmean(landmarks, axis=0))
    coll.create_single("texture/lips", lips, ("lip", "lip_node", "xy"), prov)
    return prov
