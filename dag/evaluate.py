"""``persona evaluate``: how much the output looks like B, moves like A, and holds still.

Figures (paper §6, with dlib's descriptor and landmarks only; nothing downloaded):

- identity: descriptor distance of every output frame to the centroid of B's photos and
  to that of A's; the fraction of frames that are "B and not A", of the render and of
  composite.mp4's frames (B's face in A's frame, matched to A's light); the distance between
  the two centroids (under the threshold, dlib cannot tell B's photos from A's: nothing to judge);
- expression: Pearson correlation of mouth opening, eye openness, brow height and mouth
  width between A's video and the output (landmarks found anew in the output frames);
- amplitude: for the same signals, the gain (slope of the output's signal on the driver's:
  1 = the same amplitude, which a correlation cannot see) with its 95 % interval (a block bootstrap
  of the frames: how far the gain could move with the same drive's noise), the correlation and both
  ranges, of the face alone (puppet.mp4) and of composite.mp4's frames (the same face, found by dlib
  with A's head around it);
- gaze: where the irises sit in the eyes (persona.plugins.face.gaze.iris_offsets, along and across the
  eye, in eye widths), the gain and correlation of the face alone's and composite.mp4's on the driver's;
- creases: the fine detail between the brows (ev.crease_energy: it rises as a frown creases the skin
  there), the gain and correlation of the face alone's and composite.mp4's on the driver's: creases
  that come and go with the driver's, not B's in every frame;
- held: per signal, the expression each face holds through the clip (its mean less its resting face's:
  A's mean photo, B's neutral texture), of the driver, the face alone and composite.mp4's frames; a
  smile held throughout has no amplitude for a gain to see;
- stability: landmark jitter and face-colour flicker, output over driver (the colour inside the rendered
  face less both mouths, A's and B's outer lips and the interior drawn between B's: a mouth that opens
  changes the mean colour by what it shows, which is expression, not flicker); the jitter of the face
  alone over the 51 points inside the jaw line (its mask ends above the chin, and dlib's jaw on it is
  a guess that wanders), and on composite.mp4's frames over all 68 (the output as a viewer sees it:
  B's face in A's frame, with A's jaw line); the texture's own
  change from frame to frame (B's synthesized texture against A's frontalized frames, both in
  the canonical frame, median mean absolute change inside the face: details that come and go);
- composite: the seam of composite.mp4 along the rendered face's edge (colour step across it beyond
  the driver frame's own, gradient energy on it over the frame's), medians over every 4th frame,
  beside the same for a plain paste through the mask;
- self-reenactment (when asked): PSNR and SSIM of the output against A's real frames
  inside the rendered face, of the render and of composite.mp4's frame, and the landmark registration:
  how far dlib's 68 points on each lie from those on the real frame, per region (jaw, brows, nose, eyes,
  mouth), median % of the eye distance; and, of a drive rendered in 3D, how far B's 49 fiducials lie from
  them where the mesh and the pose put them, before the face is drawn (the motion's share of the error);
- motion (3D runs): the same expression signals computed from the fiducials moved by A's
  per-frame meshes M_D^t and by B's meshes M_P^t after the transfer, against A's landmarks
  (gain, correlation, ranges): how much of A's expression each step of the 3D method carries,
  before texture and rendering add their own errors (the chain: A's meshes, B's meshes, output).

Descriptors are computed by Dask tasks over shards; only small per-frame figures come back. A person's
centroid is kept in its collection (:data:`CENTROID`), so that its photos are described once, not once
a drive.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from persona.plugins.builtin import evaluate as ev
from persona.plugins.builtin.landmarks import DlibLandmarks, dlib_models
from persona.plugins.face import composite, gaze
from persona.plugins.face.template import generic_template
from persona.plugins.base import Rejected
from persona.plugins.manager import default_registry
from persona.stores.errors import InputError
from persona.stores.layout import OK, Cast, Collection, open_store
from persona.stores.provenance import Provenance

from .stages import RENDER_3D, accepted, backend_key, provenance, render_alpha

#: the figures' version: a run keeps its last evaluation only when this is the same (raise it whenever a
#: figure is added or computed differently)
VERSION = 14

#: a person's descriptor centroid (128,), kept in its collection: the mean descriptor of the sample of its
#: accepted photos that every drive of the person is judged against (:func:`centroid_plan`)
CENTROID = "identity/centroid"


def _identity(spec: tuple[str, dict]):
    return default_registry().get("identity", spec[0])(spec[1])


def warm_up() -> None:
    """What every shard of an evaluation loads first, loaded once per process: dlib's detector and predictor
    (0.6 s). A drive sends it to the workers as it starts (:meth:`persona.dag.executor.Executor.warm`), while
    they wait on the client's retargeting, so that the evaluation's first shards do not load it."""
    dlib_models()


def describe_photos(url: str, path: str, indices: list[int], identity: tuple[str, dict]) -> np.ndarray:
    """Descriptors (k, 128) of accepted photos ``indices`` of a collection, from their stored landmarks."""
    coll = Collection(open_store(url, mode="r"), path)
    backend = _identity(identity)
    sizes, points = coll.array("photos/size")[:], coll.array("landmarks/points")[:]  # small: read once
    out = []
    for i in indices:
        h, w = sizes[i]
        image = coll.array("photos/rgb")[i][:h, :w]  # one chunk per photo
        out.append(backend.describe(image, points[i].astype(np.float64)))
    return np.array(out).reshape(len(out), -1)


def analyse_frames(url: str, start: int, stop: int, identity: tuple[str, dict], compare: bool, cast: Cast,
                   every: int = 1) -> dict:
    """For output frames [start, stop) of the drive of ``cast``: landmarks found anew, descriptors
    (of every ``every``-th frame of the drive, NaN for the others: :func:`identity_every`; none when
    ``every`` is 0), the mean
    face colour of output and driver inside the rendered face less both mouths (ev.without_mouths), and
    (``compare``) PSNR and SSIM against the driver, of the render and of the composite (the composite
    stage's frames, composite.mp4's); of the driver's frame, the face alone and the composite, where the
    irises sit and the fine detail between the brows (ev.crease_energy)."""
    root = open_store(url, mode="r")
    drive, frames = Collection(root, cast.drive), Collection(root, cast.frames)
    rendered = drive.array("render/rgb")[start:stop]
    alphas = drive.array("render/mask")[start:stop]
    composites = drive.array("composite/rgb")[start:stop]
    masks = alphas > 127
    drawn = drive.array("render/own")[start:stop] > 0  # the driver's mouth interior drawn into B's
    theirs = driver_frame_landmarks(root, cast.frames, slice(start, stop))
    skin = np.zeros_like(masks)  # the face less both mouths, where the colour's flicker is judged
    original = frames.array("photos/rgb")[start:stop]
    detector, backend = DlibLandmarks(), _identity(identity)
    n = stop - start
    landmarks = np.full((n, 68, 2), np.nan)
    composite_landmarks = np.full((n, 68, 2), np.nan)  # on composite.mp4's frames
    descriptors = np.full((n, 2, 128), np.nan)  # of the render, of the composite
    psnr, ssim = np.full((n, 2), np.nan), np.full((n, 2), np.nan)  # the render's, the composite's
    irises = np.full((n, 3, 2, 2), np.nan)  # where the eyes look: the driver's, the face alone's, the composite's
    creases = np.full((n, 3), np.nan)  # the detail between the brows: the driver's, the face alone's, the composite's
    seams = {"blend": [], "paste": []}
    sharp = []  # every 4th frame: the face alone's and the composite's fine detail over the driver's face
    errors = ev.ErrorSums.zeros(original.shape[1:]) if compare else None  # a self-reenactment's error map
    for j in range(n):
        alpha = render_alpha(alphas[j])
        face = composite.alone(rendered[j], alpha)  # as puppet.mp4 shows it
        blended = composites[j]
        box = composite.mask_box(masks[j])
        height = None if box is None else box[0].stop - box[0].start  # the drawn face's, for dlib's search
        for k, (image, found) in enumerate(((face, landmarks), (blended, composite_landmarks))):
            try:
                found[j] = detector.detect(image, face_height=height).points
                if every and (start + j) % every == 0:
                    descriptors[j, k] = backend.describe(image, found[j])
            except Rejected:
                pass
        for k, (image, points) in enumerate(((original[j], theirs[j]), (face, landmarks[j]),
                                             (blended, composite_landmarks[j]))):
            irises[j, k] = gaze.iris_offsets(image, points)
            creases[j, k] = ev.crease_energy(image, points, masks[j] if k == 1 else None)
        skin[j] = ev.without_mouths(masks[j] & ~drawn[j], theirs[j], landmarks[j])
        if compare and masks[j].any():
            psnr[j] = [ev.masked_psnr(image, original[j], masks[j]) for image in (face, blended)]
            ssim[j] = ev.masked_ssims((face, blended), original[j], masks[j])
        if compare:
            errors.add(blended, original[j], masks[j], theirs[j])
        if (start + j) % 4 == 0:
            for name, found in composite.seams(rendered[j], original[j], alpha, blended).items():
                if found is not None:
                    seams[name].append([found["colour_step"], found["gradient_ratio"]])
            if masks[j].any():
                sharp.append([ev.sharpness(image, original[j], masks[j]) for image in (face, blended)])
    face = generic_template().mask  # B's synthesized textures and A's frontalized frames, canonical
    texture_change = ev.frame_changes(drive.array("texture/rgb")[start:stop], face)
    driver_change = ev.frame_changes(frames.array("aligned/rgb")[start:stop], face)
    return {"start": start, "landmarks": landmarks, "composite_landmarks": composite_landmarks,
            "descriptors": descriptors, "psnr": psnr, "ssim": ssim, "irises": irises, "creases": creases,
            "errors": errors, "texture_change": texture_change, "driver_change": driver_change,
            **{f"seam_{k}": np.array(v).reshape(-1, 2) for k, v in seams.items()},
            "sharpness": np.array(sharp).reshape(-1, 2),
            "colour_output": ev.masked_mean_colours(rendered, skin),
            "colour_composite": ev.masked_mean_colours(composites, skin),
            "colour_driver": ev.masked_mean_colours(original, skin)}


def identity_every(n: int, frames: int) -> int:
    """Every how many of a drive's ``n`` frames a descriptor is taken so that about ``frames`` of them
    are (0: every frame)."""
    return 1 if frames == 0 or n <= frames else -(-n // frames)


def _sample(ok: np.ndarray, k: int) -> list[int]:
    idx = np.flatnonzero(ok)
    return [int(i) for i in idx[np.linspace(0, len(idx) - 1, min(k, len(idx))).round().astype(int)]] if len(idx) else []


def centroid_plan(store: str, root, actor: str, path: str, identity: tuple[str, dict], sample: int,
                  version: str) -> tuple[Provenance | None, list[int]]:
    """Which ``sample`` of the accepted photos of the collection at ``path`` (the ``actor``'s) its descriptor
    centroid is taken over, and the provenance of that centroid (:data:`CENTROID`: the same accepted rows
    of the same landmarks, described by the same identity backend; None for landmarks without one)."""
    coll = Collection(root, path)
    if not coll.has("status/screen/state"):
        raise InputError(f"{store}: the {actor}'s photos were processed by an older Persona, before the "
                         "collection's screen existed; run `persona run` on the workflow again to bring "
                         "the store up to date, then evaluate")
    chosen = _sample(accepted(coll), sample)
    landmarks = coll.provenance("landmarks/points")
    if landmarks is None:
        return None, chosen
    backend, backend_version = backend_key("identity", identity[0])
    return provenance("evaluate", backend=backend, backend_version=backend_version,
                      params={**identity[1], "photos": chosen}, inputs={"landmarks": landmarks.key},
                      persona_version=version), chosen


def motion_figures(store: str, cast: Cast, self_reenactment: bool = False) -> dict | None:
    """The expression signals of A's meshes, B's meshes and B's meshes as posed (:func:`mesh_landmarks`)
    against A's landmarks; in a self-reenactment also the registration of B's fiducials as posed on the real
    frame's landmarks (where the motion puts the face's features before it is drawn, beside where dlib finds
    them on the drawn face); None for a drive not rendered from the motion step's meshes."""
    root = open_store(store, mode="r")
    drive = Collection(root, cast.drive)
    if drive.provenance("render/rgb").stage != RENDER_3D.name:
        return None
    driver_landmarks = driver_frame_landmarks(root, cast.frames)
    moved, posed = mesh_landmarks(root, f"{cast.drive}/mesh", cast.puppet, poses=drive.array("pose")[:])
    figures = {"driver_meshes": expression_gains(driver_landmarks, mesh_landmarks(
                   root, f"{cast.drive}/motion/driver_mesh", cast.driver)[0]),
               "puppet_meshes": expression_gains(driver_landmarks, moved),
               "puppet_meshes_posed": expression_gains(driver_landmarks, posed)}
    if self_reenactment:
        figures["registration_posed"] = ev.registration(driver_landmarks, posed)
    return figures


def _piece(tag: str, kind: str, *args):
    """One independent piece of an evaluation as one task, returned as (tag, result): ``frames``
    (:func:`analyse_frames` of a shard), ``photos`` (:func:`describe_photos`), ``texture``
    (:func:`texture_figures` of the store at args[0]) or ``motion`` (:func:`motion_figures`). All of a
    drive's pieces go to the workers at once, so none waits for another's last task."""
    if kind == "frames":
        return tag, analyse_frames(*args)
    if kind == "photos":
        return tag, describe_photos(*args)
    if kind == "texture":
        return tag, texture_figures(open_store(args[0], mode="r"), *args[1:])
    return tag, motion_figures(*args)


def evaluate(store: str, executor, *, identity: tuple[str, dict], threshold: float = 0.6,
             collection_sample: int = 100, identity_frames: int = 0, self_reenactment: bool = False,
             cast: Cast = Cast(),
             progress: Callable[[int], object] = lambda frames: None, keep_in=None, version: str = "") -> dict:
    """Every figure of a finished drive (``cast``; a format-1 store's by default), as a JSON-ready
    dict (plus per-frame series under "series", with each frame's PSNR in a self-reenactment);
    ``progress(n)`` is called as each shard of n frames is analysed. Identity is judged on
    ``identity_frames`` frames evenly spaced (0: all), and not at all where the puppet is the driver (a
    self-reenactment from one collection: B is A, and dlib's descriptors, two a frame, were most of the
    evaluation's time).
    A collection's centroid is taken from the collection when it holds one made from the same photos
    (:data:`CENTROID`), and kept in ``keep_in`` (the store, open for writing by a caller that holds its
    lock; ``version``: Persona's, which the centroid's provenance records) when it was computed: a person
    who drives two puppets, or whose drive is evaluated again, is described once."""
    root = open_store(store, mode="r")
    drive = Collection(root, cast.drive)
    judged = cast.puppet != cast.driver
    every = identity_every(drive.n, identity_frames) if judged else 0
    tasks = [("frames", "frames", store, start, stop, identity, self_reenactment, cast, every)
             for start, stop in drive.shard_ranges()]
    centroids, wanted = {}, {}  # the actors' centroids kept, and (path, provenance) of those to compute
    for actor, path in ((("puppet", cast.puppet), ("driver", cast.driver)) if judged else ()):
        made, chosen = centroid_plan(store, root, actor, path, identity, collection_sample, version)
        person = Collection(root, path)
        if made is not None and person.made_by(CENTROID, made):
            centroids[actor] = person.array(CENTROID)[:]
        else:
            wanted[actor] = (path, made)
            tasks += [(actor, "photos", store, path, chosen[i::2], identity) for i in range(2)]
    # the drive's two single pieces first: each is several shards' work, and started last they ran alone
    tasks = [("motion", "motion", store, cast, self_reenactment),
             ("texture", "texture", store, cast, collection_sample), *tasks]
    parts, described, pieces, errors = [], {actor: [] for actor in wanted}, {}, None
    for tag, result in executor.run(_piece, tasks):
        if tag == "frames":
            part = result.pop("errors")  # summed as they come: a long HD drive's would not all fit in memory
            errors = part if errors is None else errors + part  # None alike unless a self-reenactment
            parts.append(result)
            progress(len(result["landmarks"]))
        elif tag in described:
            described[tag].append(result)
        else:
            pieces[tag] = result
    for actor, (path, made) in wanted.items():
        centroids[actor] = ev.centroid(np.concatenate(described[actor]))
        if keep_in is not None and made is not None:
            Collection(keep_in, path).create_single(CENTROID, centroids[actor], ("descriptor",), made)
    parts.sort(key=lambda p: p["start"])
    joined = {k: np.concatenate([p[k] for p in parts]) for k in parts[0] if k != "start"}

    driver_landmarks = driver_frame_landmarks(root, cast.frames)
    without_face = int(np.isnan(joined["landmarks"][:, 0, 0]).sum())
    distances = {name: np.full(drive.n, np.nan) for name in ("distance_to_b", "distance_to_a")}  # NaN: not judged
    if judged:
        described = joined["descriptors"][::every]
        figures = ev.identity_figures(described[:, 0], centroids["puppet"], centroids["driver"], threshold)
        on_composite = ev.identity_figures(described[:, 1], centroids["puppet"], centroids["driver"], threshold)
        for name in distances:
            distances[name][::every] = figures[name]
        identity = {**{k: v for k, v in figures.items() if not isinstance(v, np.ndarray)},
                    "distance_b_to_a": float(np.linalg.norm(centroids["puppet"] - centroids["driver"])),
                    "fraction_b_not_a_composite": on_composite["fraction_b_not_a"],
                    "frames_judged": len(described), "frames_without_face": without_face}
    else:  # the puppet is the driver: nothing to tell apart
        identity = {"judged": False, "frames_judged": 0, "frames_without_face": without_face}
    video = ev.compare_videos(driver_landmarks, joined["landmarks"], jaw=False)  # the face alone has none
    on_composite_video = ev.compare_videos(driver_landmarks, joined["composite_landmarks"])
    stability = video["stability"]
    stability["jitter_driver_composite"] = on_composite_video["stability"]["jitter_driver"]  # all 68 points
    stability["jitter_composite"] = on_composite_video["stability"]["jitter_output"]
    stability["jitter_ratio_composite"] = on_composite_video["stability"]["jitter_ratio"]
    stability["colour_change_driver"] = ev.flicker(joined["colour_driver"])
    stability["colour_change_output"] = ev.flicker(joined["colour_output"])
    stability["colour_change_ratio"] = _ratio(stability["colour_change_output"], stability["colour_change_driver"])
    stability["colour_change_composite"] = ev.flicker(joined["colour_composite"])
    stability["colour_change_ratio_composite"] = _ratio(stability["colour_change_composite"],
                                                        stability["colour_change_driver"])
    stability["texture_change_output"] = _median(joined["texture_change"])
    stability["texture_change_driver"] = _median(joined["driver_change"])
    stability["texture_change_ratio"] = _ratio(stability["texture_change_output"], stability["texture_change_driver"])
    gazes = {who: ev.gaze_signals(joined["irises"][:, i]) for i, who in enumerate(("driver", "output", "composite"))}
    result = {
        "identity": identity,
        "texture": pieces["texture"],
        "expression": video["expression"],
        "amplitude": video["amplitude"],
        "amplitude_composite": on_composite_video["amplitude"],
        "gaze": gaze_figures(gazes),
        "creases": {where: ev.amplitude(joined["creases"][:, 0], joined["creases"][:, k])
                    for k, where in ((1, "face_alone"), (2, "composite"))},
        "held": held_figures(root, cast, driver_landmarks, joined["landmarks"], joined["composite_landmarks"]),
        "stability": stability,
        "sharpness": {"face_alone": _median(joined["sharpness"][:, 0]),
                      "composite": _median(joined["sharpness"][:, 1])},
        "composite": {k: {"colour_step": _median(joined[f"seam_{k}"][:, 0]),
                          "gradient_ratio": _median(joined[f"seam_{k}"][:, 1])} for k in ("blend", "paste")},
        "frames": drive.n,
        "bridged_frames": int(drive.array("bridged")[:].sum()),
        "series": {
            **distances,
            **{f"{who}_{k}": v for who, points in (("driver", driver_landmarks), ("output", joined["landmarks"]),
                                                     ("composite", joined["composite_landmarks"]))
               for k, v in ev.expression_signals(points).items()},
            **{f"{who}_gaze_{k}": v for who, signals in gazes.items() for k, v in signals.items()},
            **{f"{who}_creases": joined["creases"][:, k] for k, who in enumerate(("driver", "output", "composite"))},
            "driver_head_turn": ev.head_turns(drive.array("pose")[:]),  # for the report's frames at the widest turns
        },
    }
    if pieces["motion"] is not None:  # rendered from the motion step's meshes
        result["motion"] = pieces["motion"]
    if self_reenactment:
        result["series"].update({"psnr_face_alone": joined["psnr"][:, 0], "psnr_composite": joined["psnr"][:, 1]})
        result["self_reenactment"] = {"psnr_db": _nanmean(joined["psnr"][:, 0]), "ssim": _nanmean(joined["ssim"][:, 0]),
                                      "psnr_db_composite": _nanmean(joined["psnr"][:, 1]),
                                      "ssim_composite": _nanmean(joined["ssim"][:, 1]),
                                      "registration": ev.registration(driver_landmarks, joined["landmarks"]),
                                      "registration_composite": ev.registration(driver_landmarks,
                                                                                joined["composite_landmarks"])}
        if pieces["motion"] is not None:  # where the motion puts B's fiducials, before the face is drawn
            result["self_reenactment"]["registration_posed"] = pieces["motion"].pop("registration_posed")
        result["self_reenactment"]["error_share"] = errors.shares()
        picture = errors.picture()
        result["pictures"] = {} if picture is None else {"error_map": picture}
    return result


def gaze_figures(signals: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, dict]]:
    """Where the eyes look, output against driver: per signal of ev.gaze_signals (along and across the eye,
    apart, eye widths), the ev.amplitude (gain, interval, r, ranges) of the face alone and of composite.mp4's
    frames, from the gaze signals of the driver's, the face alone's and the composite's frames (``signals``
    keyed "driver", "output", "composite"); with "apart", how far the driver's eyes' turn against each other
    stands out from the measure's noise (``driver_over_noise``, gaze.spread_over_noise: below gaze.APART_SNR
    B's eyes turn together, and the gain has no target)."""
    figures = {where: {k: ev.amplitude(signals["driver"][k], signals[who][k]) for k in signals["driver"]}
               for where, who in (("face_alone", "output"), ("composite", "composite"))}
    over = float(gaze.spread_over_noise(np.asarray(signals["driver"]["apart"], np.float64)[:, None])[0])
    for signal in figures.values():
        signal["apart"]["driver_over_noise"] = over
    return figures


def own_photos(puppet: Collection, sample: int = 100):
    """(rows, photos, masks, tear reference) of ``sample`` of a collection's accepted frontalized
    photos: what its textures are measured against; masks are the face inside each photo's view."""
    chosen = _sample(accepted(puppet), sample)
    face = generic_template().mask
    photos = puppet.rows("aligned/rgb", chosen)
    inside = [face & ev.inner(v) for v in puppet.rows("aligned/mask", chosen)]
    return chosen, photos, inside, ev.tear_reference(photos, inside)


def texture_figures(root, cast: Cast, sample: int = 100, every: int = 8) -> dict[str, dict[str, float]]:
    """B's textures against ``sample`` of B's own frontalized photos, inside the face (docs/texture.md).

    tears (:func:`ev.tear_energy`: thin cracks and jumps beyond the photos' own lines there): the
    median of those photos themselves (the collection's own level), of the same photos as the align
    stage's collection flow warped them, of the neutral texture and of every ``every``-th frame's
    texture; ``ratio`` is the frames' over the photos' (≤ 1: no more tears than the photos have).
    detail (:func:`ev.detail_energy`, band-pass energy): the same medians, ``ratio`` again the frames'
    over the photos' (1: as sharp as a photo)."""
    puppet, drive = Collection(root, cast.puppet), Collection(root, cast.drive)
    chosen, photos, inside, reference = own_photos(puppet, sample)
    face = generic_template().mask
    aligned = puppet.has("collection/rgb")  # not when the collection was too small for a collection flow
    warped = puppet.rows("collection/rgb", chosen) if aligned else []
    warped_inside = [face & ev.inner(v) for v in puppet.rows("collection/mask", chosen)] if aligned else []
    frames = [drive.array("texture/rgb")[t] for t in range(0, drive.n, every)]
    neutral = [puppet.array("texture/neutral")[...]] if puppet.has("texture/neutral") else []
    out = {}
    for name, measure in (("tears", lambda image, mask: ev.tear_energy(image, mask, reference)),
                          ("detail", ev.detail_energy)):
        figures = {"photos": _median([measure(p, m) for p, m in zip(photos, inside)]),
                   "collection_flow": _median([measure(p, m) for p, m in zip(warped, warped_inside)]),
                   "neutral": _median([measure(t, face) for t in neutral]),
                   "frames": _median([measure(t, face) for t in frames])}
        figures["ratio"] = _ratio(figures["frames"], figures["photos"])
        out[name] = figures
    return out


def resting_face(coll: Collection, name: str, detector: DlibLandmarks) -> np.ndarray | None:
    """dlib's landmarks (68, 2) on the collection's canonical picture ``name`` (a mean face), read at
    several sizes (ev.resting_landmarks); None when the store has none or dlib finds no face on it."""
    if not coll.has(name):
        return None
    image = np.clip(coll.array(name)[...], 0, 255).round().astype(np.uint8)
    return ev.resting_landmarks(image, lambda big: detector.detect(big).points)


def held_figures(root, cast: Cast, driver: np.ndarray, alone: np.ndarray, composited: np.ndarray) -> dict:
    """Per signal, the expression held through the clip (ev.held_expression) by the driver (against A's mean
    photo, ``aligned/mean``), the face alone and composite.mp4's frames (against B's neutral texture,
    ``texture/neutral``), from their landmarks (T, 68, 2) each."""
    detector = DlibLandmarks()
    rest_a = resting_face(Collection(root, cast.driver), "aligned/mean", detector)
    rest_b = resting_face(Collection(root, cast.puppet), "texture/neutral", detector)
    figures = {who: ev.held_expression(points, rest) for who, points, rest in
               (("driver", driver, rest_a), ("output", alone, rest_b), ("composite", composited, rest_b))}
    return {k: {who: f[k] for who, f in figures.items()} for k in figures["driver"]}


def driver_frame_landmarks(root, path: str = Cast.frames, rows: slice = slice(None)) -> np.ndarray:
    """(T, 68, 2) dlib's landmarks on the driver's frames (the collection at ``path``; its frames ``rows``),
    the reference of every expression figure; NaN for a frame without a face."""
    frames = Collection(root, path)
    landmarks = frames.array("landmarks/points")[rows].astype(np.float64)
    landmarks[frames.state("landmarks")[rows] != OK] = np.nan
    return landmarks


def mesh_landmarks(root, meshes: str, actor: str, poses: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray | None]:
    """(T, 68, 2) the actor's mean fiducials moved by the per-frame meshes at ``meshes`` (T, H, W, 3; their
    (x, y) at each fiducial's canonical pixel, rigid pose already removed: ev.moved_landmarks); and with the
    frames' ``poses`` (T, 10), from the same read of the meshes, the fiducials seen at each frame's pose, as
    the renderer draws them (ev.posed_landmarks; the step between these and dlib's landmarks on the rendered
    frames is what dlib reads of the drawn face), else None."""
    fiducials = root[f"{actor}/aligned/mean_fiducials"][...]
    array = root[meshes]
    moved, posed = [], []
    for start in range(0, array.shape[0], 256):  # a few frames at a time
        chunk = array[start:start + 256]
        moved.append(ev.moved_landmarks(chunk, fiducials))
        if poses is not None:
            posed.append(ev.posed_landmarks(chunk, fiducials, poses[start:start + 256]))
    return np.concatenate(moved), np.concatenate(posed) if poses is not None else None


def expression_gains(driver_landmarks: np.ndarray, landmarks: np.ndarray) -> dict[str, dict]:
    """The :func:`amplitude` (gain, r, ranges) of each expression signal of ``landmarks`` (T, 68, 2) on the
    driver's landmarks (T, 68, 2)."""
    theirs, ours = ev.expression_signals(driver_landmarks), ev.expression_signals(landmarks)
    return {k: ev.amplitude(theirs[k], ours[k]) for k in theirs}


def _ratio(a: float, b: float) -> float:
    return a / b if np.isfinite(a) and np.isfinite(b) and b != 0 else float("nan")


def _median(values) -> float:
    values = np.asarray(values, np.float64)
    values = values[np.isfinite(values)]
    return float(np.median(values)) if len(values) else float("nan")


def _nanmean(values: np.ndarray) -> float:
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if len(finite) else float("nan")
