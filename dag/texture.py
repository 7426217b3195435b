"""Expression-dependent texture in the run (paper §5-§6).

Video mode, the paper's way for puppetry: the collection is warped once to the puppet's mean
fiducials (with the texture backend's own alignment, or as the ``align`` stage's collection flow
warped it: its ``video_alignment``), the target-independent terms of Eq. 3 (Laplacian pyramids
times detail weights) are cached in the store under ``texture/``, and each driver frame only
changes the expression weights. The textures keep the neutral geometry with the target's detail;
the renderer moves the geometry. Every step is Dask tasks over shards of photos or frames, and
no process holds the whole cache (:func:`run_texture`, :func:`stored_textures`).

Stored: ``<puppet>/texture/weighted_<k>``, ``texture/detail_<k>`` (per photo and level), their
sums over all photos ``texture/total_<weighted|detail|energy>_<k>`` (the cache, whose provenance
leaves out the texture backend's ``frame_params``), ``texture/neutral`` (the texture at the mean
fiducials, written last; its provenance has every param) and ``drive/texture/rgb`` (per frame).
For 3D renderers also the inside of B's mouth (the ``mouth`` backend's, :func:`run_mouth`):
``texture/mouth`` (when a photo shows it) and ``texture/lips`` (B's mean inner-lip curves,
written last).
"""

from __future__ import annotations

import logging
import operator

import numpy as np

from persona.plugins.face.blend import (BlendCache, BlendTotals, gaussian_pyramid, level_bias, seen_mean,
                                        seen_sums)
from persona.plugins.face.fiducials import rest_shape
from persona.plugins.face.gaze import LOOK_VERSION, photo_gazes
from persona.plugins.face.template import CANONICAL_HEIGHT as H, CANONICAL_WIDTH as W
from persona.plugins.face.texture import Aligned, to_grey, warped_basis
from persona.plugins.kinds import MouthPhotos, Pose, TextureBackend, TexturePhotos
from persona.stores import media, storage
from persona.stores.layout import OK, Collection, open_store
from persona.stores.provenance import Provenance

from . import stages as st
from .context import RunContext
from .graph import Target

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


def texture_backend(runner: RunContext):
    name, params = runner.wf.stage("texture")
    return name, params, st.default_registry().get("texture", name)(params)


def video_aligned(coll: Collection, ok: np.ndarray, backend, alignment: str | None) -> Aligned:
    """The accepted photos ``ok`` of a collection, all in memory, aligned to its mean fiducials as
    the video-mode cache aligns them (for benchmarks; the run does it a shard at a time,
    :func:`warp_shard` and :func:`cache_shard`): with the texture backend's own flow and misfit
    measures (``alignment`` "own"), or as the align stage's collection flow warped them."""
    if alignment == "own":
        target = coll.array("aligned/mean_fiducials")[...].astype(np.float64)
        return backend.params.aligned(texture_photos(coll, ok), target)
    return collection_aligned(coll, ok)


def collection_aligned(coll: Collection, rows: np.ndarray) -> Aligned:
    """The photos ``rows`` as the align stage's collection flow warped them to the mean fiducials."""
    return Aligned(coll.rows("collection/rgb", rows).astype(np.float32), coll.rows("collection/mask", rows))


def run_texture(runner: RunContext, stage: st.Stage, target: Target) -> None:
    """The video-mode cache of the aligned collection (:func:`build_cache`) and its neutral texture
    (``texture/neutral``, written last: it marks the step done); the picture it writes goes into
    ``target.pictures`` (``texture_neutral``).

    The cache is keyed by the texture backend's params but its ``frame_params``, the neutral texture
    by all of them and the cache's key: when only frame params changed, the cache stays and only the
    neutral texture is made again from it (one task)."""
    coll, aligned = Collection(runner.root, target.path), target.made["align"]
    name, params, backend = texture_backend(runner)
    cache = st.provenance(stage.name, backend=name, backend_version=backend.version,
                          params={k: v for k, v in params.items() if k not in backend.frame_params},
                          inputs={"align": aligned.key}, persona_version=runner.version)
    prov = st.provenance(stage.name, backend=name, backend_version=backend.version, params=params,
                         inputs={"align": aligned.key, "cache": cache.key}, persona_version=runner.version)
    looks = st.provenance(stage.name, backend="photo gazes", backend_version=LOOK_VERSION, params={},
                          inputs={"align": aligned.key}, persona_version=runner.version)
    out = storage.join(runner.wf.output, f"{coll.path.replace('/', '_')}_texture_neutral.png")
    if (st.is_done(coll, prov, *stage.done) and st.is_done(coll, cache, CACHE_DONE) and st.is_done(coll, looks, GAZES)
            and storage.isfile(out)):
        target.pictures["texture_neutral"] = str(out)
        return
    if type(backend).cache is TextureBackend.cache:
        log.warning("texture backend %s has no video mode: the drive shows the static average", name)
        coll.remove("texture/neutral")  # another backend's, from an earlier run
        return
    if not st.is_done(coll, cache, CACHE_DONE):
        build_cache(runner, coll, cache, (name, params, backend))
    if not st.is_done(coll, looks, GAZES):  # read by every blend's weights: made once here, not by each drive
        looked = runner.tasks.map_shards(coll, "gazes", photo_looks)
        coll.create_single(GAZES, np.concatenate([looked[s] for s, _ in coll.shard_ranges()]), ("photo", "along_across"),
                           looks)
    fiducials = coll.array("aligned/mean_fiducials")[...].astype(np.float64)
    (neutral,) = runner.executor.run(stored_textures, [(runner.wf.store, coll.path, name, params, fiducials[None])])
    neutral = neutral[0].round().astype(np.uint8)
    # the neutral texture last: its provenance marks the step done
    coll.create_single("texture/neutral", neutral, ("y", "x", "channel"), prov)
    media.write_png(out, np.kron(neutral, np.ones((2, 2, 1), np.uint8)))
    target.pictures["texture_neutral"] = str(out)


def build_cache(runner: RunContext, coll: Collection, cache: Provenance, chosen: tuple) -> None:
    """The video-mode cache of the aligned collection, made with the run's texture backend
    ``chosen`` = (name, params, backend) (:func:`texture_backend`), its arrays given the provenance ``cache``.

    Every step is Dask tasks over shards of photos, so neither the client nor a worker holds the
    collection: (1) each accepted photo warped to the mean fiducials (with the backend's own
    alignment: TPS, kept for (2)), their mean where they see; (2) with the own alignment, the
    rank-k basis of the warped photos (a randomised SVD, a pass over the shards per product);
    (3) each photo flowed to its projection on it and its pyramids stored (``texture/weighted_k``,
    ``detail_k``), with the sums over the shard that every blend needs of all photos; (4) the
    totals of those; then the cache is marked done (:data:`CACHE_DONE` last)."""
    import dask.array as da

    name, params, backend = chosen
    # an earlier cache's (of any number of levels) and what was made from it: nothing may take the
    # new one as done before it is
    coll.remove("texture/neutral", *_cache_arrays(coll))
    own = params.get("video_alignment") == "own"
    if own:  # the TPS-warped photos, for the basis: removed again below
        coll.create("texture/warped_grey", (H, W), np.float32, ("photo", "y", "x"), cache)
        coll.create("texture/warped_valid", (H, W), bool, ("photo", "y", "x"), cache)
    fill = seen_mean(*runner.tasks.fold_shards(coll, "tex. warp", warp_shard, lambda a, b: (a[0] + b[0], a[1] + b[1]),
                                         name, params))
    basis = None
    if own:
        grey, valid = (da.from_zarr(coll.array(f"texture/warped_{kind}"), chunks=(coll.shard, H, W))
                       for kind in ("grey", "valid"))
        basis = warped_basis(grey, valid, fill, backend.params.rank, runner.executor.compute,
                             keep=coll.state("align") == OK)
    levels = backend.params.levels
    for k, level in enumerate(gaussian_pyramid(np.zeros((H, W), np.float32), levels)):
        coll.create(f"texture/weighted_{k}", (*level.shape, 3), np.float32, ("photo", *_level_dims(k), "channel"),
                    cache, pending=True, by_shard=True)
        coll.create(f"texture/detail_{k}", (*level.shape, 1), np.float32, ("photo", *_level_dims(k), "weight"),
                    cache, pending=True, by_shard=True)
    totals = runner.tasks.fold_shards(coll, "tex. cache", cache_shard, operator.add, name, params, fill, basis)
    coll.remove("texture/warped_grey", "texture/warped_valid")
    for k in range(levels):  # what every target's blend takes of all photos (small)
        coll.create_single(f"texture/total_weighted_{k}", totals.weighted[k], (*_level_dims(k), "channel"), cache)
        coll.create_single(f"texture/total_detail_{k}", totals.detail[k], (*_level_dims(k), "weight"), cache)
        coll.create_single(f"texture/total_energy_{k}", totals.energy[k], _level_dims(k), cache)
    for k in reversed(range(levels)):  # after the data, CACHE_DONE (texture/weighted_0) last
        coll.mark_done(f"texture/detail_{k}", cache)
        coll.mark_done(f"texture/weighted_{k}", cache)


#: the array of the video-mode cache whose provenance, written after all the cache's data, marks it done
CACHE_DONE = "texture/weighted_0"

#: where each photo looks in its aligned photo (photo, 2): the texture's eyes are blended from the photos
#: that look ahead (``eye_gaze``); made from the aligned photos, so kept apart from the cache's key
GAZES = "texture/gazes"


def _cache_arrays(coll: Collection) -> list[str]:
    """The names of the stored video-mode cache's arrays, whatever its number of levels."""
    if "texture" not in coll.group:
        return []
    return [f"texture/{key}" for key in coll.group["texture"].array_keys()
            if key.startswith(("weighted_", "detail_", "total_"))]


def _cache_id(coll: Collection) -> str:
    """Which build of the stored cache this is, for the copies of it a process keeps between tasks
    (:func:`stages.per_process`, :func:`_read_block`): its key, shared by every neutral texture made
    from it whatever their frame params, and when it was built, so a cache built again is read again."""
    made = coll.provenance(CACHE_DONE)
    return f"{made.key}@{made.created}"


def _level_dims(k: int) -> tuple[str, str]:
    """The dimension names of pyramid level k: one size per name, as xarray needs."""
    return ("y", "x") if k == 0 else (f"y_level{k}", f"x_level{k}")


def _shard_photos(coll: Collection, start: int, stop: int) -> np.ndarray:
    """The accepted photos of shard [start, stop), as indices into the collection."""
    return start + np.flatnonzero(coll.state("align")[start:stop] == OK)


def warp_shard(url: str, path: str, start: int, stop: int, name: str, params: dict):
    """Step (1) of :func:`run_texture` for one shard: its accepted photos warped to the mean
    fiducials (the own alignment: TPS, the grey and where each sees stored for the basis; else the
    collection flow's photos); returns their sums for the collection's mean where they see."""
    coll = Collection(open_store(url), path)
    rows = _shard_photos(coll, start, stop)
    if len(rows) == 0:
        return None
    backend = st.default_registry().get("texture", name)(params)
    if params.get("video_alignment") == "own":
        target = coll.array("aligned/mean_fiducials")[...].astype(np.float64)
        warped, _ = backend.params.warped(texture_photos(coll, rows), target)
        grey = np.zeros((stop - start, H, W), np.float32)
        valid = np.zeros((stop - start, H, W), bool)
        grey[rows - start], valid[rows - start] = to_grey(warped.rgb), warped.valid
        coll.array("texture/warped_grey")[start:stop] = grey
        coll.array("texture/warped_valid")[start:stop] = valid
    else:
        warped = collection_aligned(coll, rows)
    return seen_sums(warped.rgb, warped.valid)


def photo_looks(url: str, path: str, start: int, stop: int) -> np.ndarray:
    """(stop - start, 2) where each accepted photo of shard [start, stop) looks in its aligned photo
    (gaze.photo_gazes at the collection's mean fiducials); NaN for the others."""
    coll = Collection(open_store(url, mode="r"), path)
    rows = _shard_photos(coll, start, stop)
    out = np.full((stop - start, 2), np.nan)
    if len(rows):
        out[rows - start] = photo_gazes(coll.rows("aligned/rgb", rows), coll.array("aligned/mean_fiducials")[...])
    return out


def cache_shard(url: str, path: str, start: int, stop: int, name: str, params: dict, fill: np.ndarray,
                basis: np.ndarray | None) -> BlendTotals | None:
    """Step (3) of :func:`run_texture` for one shard: its accepted photos aligned (the own
    alignment: TPS again, then flowed on ``basis``) and their pyramids stored, rejected photos NaN;
    returns the shard's :class:`BlendTotals` (None when it has no accepted photo)."""
    coll = Collection(open_store(url), path)
    rows = _shard_photos(coll, start, stop)
    backend = st.default_registry().get("texture", name)(params)
    cache = None
    if len(rows) and basis is not None:
        target = coll.array("aligned/mean_fiducials")[...].astype(np.float64)
        photos = texture_photos(coll, rows)
        cache = backend.cache(backend.params.flowed(photos, *backend.params.warped(photos, target), basis), fill)
    elif len(rows):
        cache = backend.cache(collection_aligned(coll, rows), fill)
    for k in range(_levels(coll)):
        for kind in ("weighted", "detail"):
            array = coll.array(f"texture/{kind}_{k}")
            block = np.full((stop - start, *array.shape[1:]), np.nan, np.float32)
            if cache is not None:
                block[rows - start] = getattr(cache, kind)[k]
            array[start:stop] = block
    return None if cache is None else cache.totals


def load_cache(coll: Collection) -> tuple[BlendCache, np.ndarray, np.ndarray]:
    """The whole stored video-mode cache, the fiducials of its photos and where they look (:data:`GAZES`;
    for tests and benchmarks: a drive reads it a shard at a time, :func:`frame_textures`)."""
    ok = np.flatnonzero(coll.state("align") == OK)
    levels = _levels(coll)
    weighted = [coll.rows(f"texture/weighted_{k}", ok) for k in range(levels)]
    detail = [coll.rows(f"texture/detail_{k}", ok) for k in range(levels)]
    params = coll.provenance(CACHE_DONE).params
    cache = BlendCache(weighted, detail, level_bias(levels, params["beta"], params["tau"]))
    return cache, *_fiducials_and_gazes(coll, ok)


def _fiducials_and_gazes(coll: Collection, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The fiducials (n, 49, 2) of the photos ``ok`` of the collection and where they look (:data:`GAZES`,
    (n, 2)): what every blend's weights read of them."""
    return coll.array("aligned/fiducials")[:][ok].astype(np.float64), coll.array(GAZES)[...][ok]


def _levels(coll: Collection) -> int:
    return sum(1 for key in coll.group["texture"].array_keys() if key.startswith("weighted_"))


def _totals(coll: Collection, params) -> BlendTotals:
    """The stored sums over all photos of the cache (:class:`BlendTotals`), made with the texture
    backend's ``params``."""
    levels = _levels(coll)
    return BlendTotals(*([coll.array(f"texture/total_{kind}_{k}")[...] for k in range(levels)]
                         for kind in ("weighted", "detail", "energy")),
                       level_bias(levels, params.beta, params.tau))


#: bytes of B's texture cache a worker keeps in memory between a drive's tasks; a larger cache is
#: read again, a block of photos at a time, by each task (so a worker's memory stays bounded
#: whatever the size of the collection)
CACHE_BYTES = 1 << 30

#: bytes of B's texture cache read and summed as one block of consecutive shards of photos (at least one
#: shard): the frames' sums take one matrix product per level and block, and each product reads and writes
#: all of the frames' sums again, so a few large blocks cost far less than one per shard of photos
#: (Bush's 530 photos in 34 shards: 240 ms a task, against 77 in three blocks)
BLOCK_BYTES = 256 << 20

_blocks: dict[tuple[str, int], tuple[list, list]] = {}


def _block_ranges(coll: Collection, totals: BlendTotals) -> list[tuple[int, int]]:
    """The blocks of the collection's cache (:data:`BLOCK_BYTES`): [begin, end) of whole shards. A photo's
    levels have the shapes and type of the cache's ``totals``, already in memory: no array is opened."""
    photo = sum(a.nbytes for a in (*totals.weighted, *totals.detail))
    size = coll.shard * max(1, BLOCK_BYTES // (photo * coll.shard))
    return [(begin, min(begin + size, coll.n)) for begin in range(0, coll.n, size)]


def _read_block(coll: Collection, key: str, begin: int, rows: np.ndarray, levels: int) -> tuple[list, list]:
    """The ``levels`` cache levels (weighted, detail) of the photos ``rows`` of the block from ``begin`` of the
    cache ``key`` (:func:`_cache_id`), kept between tasks while all kept blocks fit in :data:`CACHE_BYTES`
    (the oldest dropped first)."""
    if (key, begin) not in _blocks:
        _blocks[(key, begin)] = tuple([coll.rows(f"texture/{kind}_{k}", rows) for k in range(levels)]
                                      for kind in ("weighted", "detail"))
        for old in [k for k in _blocks if k[0] != key]:  # another puppet's or an earlier cache's
            del _blocks[old]
        size = lambda part: sum(a.nbytes for arrays in part for a in arrays)
        while len(_blocks) > 1 and sum(size(part) for part in _blocks.values()) > CACHE_BYTES:
            del _blocks[next(iter(_blocks))]
    return _blocks[(key, begin)]


def run_frame_textures(runner: RunContext, stage: st.Stage, target: Target) -> None:
    """B's texture for every driver frame: ``drive/texture/rgb`` (frame, H, W, 3) uint8, from the
    video-mode cache, the frame's target fiducials and the driver's gaze (``eyes/gaze``), or B's static
    mean face when the texture backend has no video mode."""
    drive, puppet = Collection(runner.root, target.path), Collection(runner.root, target.cast.puppet)
    retargeted, gaze = target.made["retarget"], target.made["gaze"]
    texture = puppet.provenance("texture/neutral")
    source = texture if texture is not None else puppet.provenance("aligned/mean")
    share = runner.motion_params()["neutral_share"]  # B at rest as the retargeting takes it
    prov = st.provenance(stage.name, backend=source.backend, backend_version=source.backend_version,
                         params={**source.params, "look": LOOK_VERSION,
                                 **({"neutral_share": share} if share != 1 else {})},
                         inputs={"texture": source.key, "retarget": retargeted.key, "gaze": gaze.key},
                         persona_version=runner.version)
    target.made[stage.name] = prov
    if st.is_done(drive, prov, *stage.done):
        return
    array = drive.create("texture/rgb", puppet.array("aligned/mean").shape, np.uint8, ("frame", "y", "x", "channel"),
                         prov, pending=True)
    if texture is None:
        mean = np.clip(puppet.array("aligned/mean")[...], 0, 255).round().astype(np.uint8)
        for start, stop in drive.shard_ranges():
            array[start:stop] = np.broadcast_to(mean, (stop - start, *mean.shape))
        drive.mark_done("texture/rgb", prov)
        return
    runner.tasks.map_shards(drive, "texture", frame_textures, puppet.path, share, *runner.wf.stage("texture"))
    drive.mark_done("texture/rgb", prov)  # after the last frame: a killed run leaves no key to trust


def frame_textures(url: str, path: str, start: int, stop: int, puppet: str, neutral_share: float, name: str,
                   params: dict) -> None:
    """One shard's task of :func:`run_frame_textures`: B's texture for frames [start, stop) with the
    texture backend ``name``, from the ``puppet``'s stored cache (:func:`stored_textures`)."""
    drive = Collection(open_store(url), path)
    textures = stored_textures(url, puppet, name, params, drive.array("target"), start, stop,
                               gaze=drive.array("eyes/gaze")[start:stop], neutral_share=neutral_share)
    drive.array("texture/rgb")[start:stop] = textures.round().astype(np.uint8)


def stored_textures(url: str, path: str, name: str, params: dict, targets, start: int = 0,
                    stop: int | None = None, gaze: np.ndarray | None = None, neutral_share: float = 1.0) -> np.ndarray:
    """B's textures (f, H, W, 3) float32 for the frames [start, stop) of consecutive frames' ``targets``
    (T, 49, 2; an array read only about those frames) from the stored video-mode cache of the collection
    ``path``: the sums of Eq. 3 taken over it a block of photos at a time (:data:`BLOCK_BYTES`; a block
    that no target weighs is not read, one kept from an earlier task of this process is not read again),
    then finished with the totals; ``gaze`` (f, 2, 2), the driver's in those frames (``eyes/gaze``),
    moves B's irises; B's neutral is the :func:`rest_shape` of ``neutral_share`` of the photos' fiducials,
    as retargeting's."""
    source = Collection(open_store(url, mode="r"), path)
    key = _cache_id(source)
    backend = st.default_registry().get("texture", name)(params)
    stop = targets.shape[0] if stop is None else stop
    first, last = max(start - backend.time_radius, 0), min(stop + backend.time_radius, targets.shape[0])
    around = np.asarray(targets[first:last], np.float64)  # the frames whose targets the weights take in
    ok = np.flatnonzero(source.state("align") == OK)
    totals, fiducials, gazes = st.per_process(key, lambda: (  # one entry: a second key would evict the first
        _totals(source, backend.params), *_fiducials_and_gazes(source, ok)))
    keep = slice(start - first, stop - first)
    rest = rest_shape(fiducials, neutral_share)
    weights = backend.weights(fiducials, around, keep, rest, gazes)  # (targets and the backend's own rows, photos)
    sums = backend.sums(fiducials, stop - start, totals)
    for begin, end in _block_ranges(source, totals):
        a, b = np.searchsorted(ok, [begin, end])
        if weights[:, a:b].any():
            sums.add(*_read_block(source, key, begin, ok[a:b], len(totals.weighted)), weights[:, a:b])
    return backend.finish(sums, totals, fiducials, around[keep], gaze=gaze)


def run_mouth(runner: RunContext, stage: st.Stage, target: Target) -> None:
    """The inside of B's mouth for the renderer, as the ``mouth`` backend makes it from B's accepted photos
    (``mouth``, ``mouth_photos``, ``mouth_min_gap`` and ``mouth_choice`` of the render's params say how):
    ``texture/mouth`` and, for ``driver``, ``texture/mouth_cavity`` (each when a photo shows it), how far apart
    their photos' lips are (``_gap``, canonical px), and B's mean inner-lip curves (``texture/lips``, last)."""
    coll = Collection(runner.root, target.path)
    chosen = runner.render_params()
    # mouth_choice frame draws the driver's own interior, B's only where the driver's lips are closed: the widest
    choice = "widest" if chosen.mouth_choice == "frame" else chosen.mouth_choice
    settings = {"photos": chosen.mouth_photos, "min_gap": chosen.mouth_min_gap, "choice": choice}
    name, params = runner.wf.stage("mouth")
    recorded, version = st.backend_key("mouth", name)
    prov = st.provenance(stage.name, backend=recorded, backend_version=version, params=settings,
                         inputs={"screen": coll.provenance("status/screen/state").key}, persona_version=runner.version)
    target.made[stage.name] = prov
    if st.is_done(coll, prov, *stage.done):
        return
    ok = np.flatnonzero(st.accepted(coll))
    made = st.default_registry().get("mouth", name)(params).interior(
        MouthPhotos(_Photos(coll, ok), coll.rows("landmarks/points", ok).astype(np.float64),
                    coll.rows("aligned/landmarks", ok).astype(np.float64)),
        count=settings["photos"], min_gap=settings["min_gap"], choice=choice)
    for array in ("texture/mouth", "texture/mouth_gap", "texture/mouth_cavity", "texture/mouth_cavity_gap"):
        coll.remove(array)  # an earlier run's
    if made.interior is None:
        log.warning("%s: no photo with the lips %.2f inter-ocular distances apart; the puppet's mouth shows "
                    "no interior when it opens", coll.path, settings["min_gap"])
    for array, interior in (("texture/mouth", made.interior), ("texture/mouth_cavity", made.cavity)):
        if interior is not None:
            coll.create_single(array, np.asarray(interior.image, np.uint8), ("mouth_t", "mouth_s", "channel"), prov)
            coll.create_single(f"{array}_gap", np.array([interior.gap]), ("one",), prov)
    coll.create_single("texture/lips", np.asarray(made.lips), ("lip", "lip_node", "xy"), prov)


class _Photos:
    """The photos ``rows`` of a collection, each read (and cut to its size) when indexed."""

    def __init__(self, coll: Collection, rows: np.ndarray):
        self.coll, self.rows, self.sizes = coll, rows, coll.rows("photos/size", rows)

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, i: int) -> np.ndarray:
        h, w = self.sizes[i]
        return self.coll.array("photos/rgb")[int(self.rows[i])][:h, :w]
