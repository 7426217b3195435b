"""Evaluation figures of a puppet video (paper §6), with dlib only.

Two parts:

- the ``identity`` backend kind (:class:`IdentityBackend`) and its dlib implementation
  :class:`DlibIdentity`: dlib's 128-D ResNet face descriptor (shipped in
  ``face_recognition_models``, nothing downloaded; run in NumPy, :mod:`.face_descriptor`), for
  "does the puppet look like B and not like A";
- pure metric functions on landmark tracks, frames and descriptors: expression
  transfer (correlation of mouth / eye / brow signals between driver and output),
  stability (landmark jitter, colour flicker), identity distances and masked
  PSNR / SSIM.

Conventions: landmark tracks are (n, 68, 2) float arrays of iBUG points (x, y); a frame
without a face has NaN landmarks (or a NaN descriptor row), and every per-frame signal
is NaN there. Scalar figures are plain Python ``float`` / ``int`` (JSON-serialisable;
NaN when undefined, e.g. too few frames), per-frame series are float64 ndarrays.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np
from pydantic import Field
from scipy.spatial.transform import Rotation

from ..base import Backend, Params, Rejected
from ..face.composite import mask_box
from ..face.template import IDX49, generic_template
from ..face.warp import compose
from ..hookspecs import hookimpl
from ..kinds import Pose
from .face_descriptor import describe_chip
from .render3d import project

# iBUG 68 indices
RIGHT_EYE = slice(36, 42)  # subject's right eye (image left)
LEFT_EYE = slice(42, 48)
BROWS = slice(17, 27)
INNER_LIP_PAIRS = ((62, 66), (61, 67), (63, 65))
EYE_LID_PAIRS = (((37, 41), (38, 40)), ((43, 47), (44, 46)))
MOUTH_CORNERS = (48, 54)
#: the middle of the upper lip, outer and inner edge: the lips' middle that moves least when the jaw opens,
#: so the corners' height over it tells a smile (up) from a frown (down) and not an open mouth
UPPER_LIP_MIDDLE = (51, 62)


# --------------------------------------------------------------------------- identity


class IdentityBackend(Backend):
    """Kind ``identity``: a face descriptor whose Euclidean distances compare identities."""

    kind = "identity"

    def describe(self, image: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
        """image: (h, w, 3) uint8 RGB; landmarks: (68, 2) (x, y) -> descriptor (d,) float64."""
        raise NotImplementedError


@lru_cache(maxsize=1)
def dlib_face_recognition_model():
    """dlib's ResNet face recognition model (``face_recognition_models``), loaded once per process."""
    import dlib
    import face_recognition_models

    return dlib.face_recognition_model_v1(face_recognition_models.face_recognition_model_location())


def full_object_detection(landmarks: np.ndarray):
    """A ``dlib.full_object_detection`` of the 68 landmarks in their bounding box."""
    import dlib

    points = np.asarray(landmarks, dtype=np.float64)
    left, top = np.floor(points.min(axis=0)).astype(int)
    right, bottom = np.ceil(points.max(axis=0)).astype(int)
    rect = dlib.rectangle(int(left), int(top), int(right), int(bottom))
    return dlib.full_object_detection(rect, [dlib.point(int(round(x)), int(round(y))) for x, y in points])


class DlibIdentity(IdentityBackend):
    name = "dlib_resnet"
    description = ("dlib ResNet 128-D face descriptor (face_recognition_models); same person "
                   "below ~0.6 Euclidean distance")
    default = True

    class Params(Params):
        jitters: int = Field(0, ge=0, le=100, description="dlib num_jitters: average the descriptor "
                             "over this many randomly jittered copies of the aligned face (0: the "
                             "face once; 10-100 is slightly more accurate and that many times slower, "
                             "and is run by dlib itself)")
        padding: float = Field(0.25, ge=0, le=1, description="padding of dlib's aligned 150x150 "
                               "face chip around the landmarks (dlib's default 0.25, as trained)")

    def describe(self, image, landmarks):
        image = np.asarray(image)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"identity: want an (h, w, 3) uint8 RGB image, got {image.shape} {image.dtype}")
        landmarks = np.asarray(landmarks, dtype=np.float64)
        if landmarks.shape != (68, 2):
            raise ValueError(f"identity: want (68, 2) landmarks, got {landmarks.shape}")
        if not np.all(np.isfinite(landmarks)):
            raise Rejected("identity: no landmarks (no face) in this frame")
        import dlib

        shape = full_object_detection(landmarks)
        image = np.ascontiguousarray(image)
        if self.params.jitters:  # dlib's own random jitter: only dlib can run it
            descriptor = dlib_face_recognition_model().compute_face_descriptor(
                image, shape, self.params.jitters, self.params.padding)
        else:  # the same network in NumPy (face_descriptor.py): the same figures, about 5x faster
            descriptor = describe_chip(dlib.get_face_chip(image, shape, 150, self.params.padding))
        return np.array(descriptor, dtype=np.float64)


@hookimpl
def persona_register_backends(register):
    register(DlibIdentity)


# --------------------------------------------------------------------------- helpers


def _track(landmarks) -> np.ndarray:
    """(n, 68, 2) float64 (a single (68, 2) face becomes n = 1)."""
    x = np.asarray(landmarks, dtype=np.float64)
    if x.ndim == 2:
        x = x[None]
    if x.ndim != 3 or x.shape[1:] != (68, 2):
        raise ValueError(f"want landmarks of shape (n, 68, 2), got {x.shape}")
    return x


def _ratio(num, den) -> float:
    """num / den as a float, NaN when den is 0 or either is not finite."""
    num, den = float(num), float(den)
    if not (np.isfinite(num) and np.isfinite(den)) or den == 0:
        return float("nan")
    return num / den


def _divide(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """Elementwise num / den, NaN where den is not a positive finite number (no warnings)."""
    num, den = np.broadcast_arrays(np.asarray(num, float), np.asarray(den, float))
    out = np.full(num.shape, np.nan)
    ok = np.isfinite(den) & (den > 0)
    np.divide(num, den, out=out, where=ok)
    return out


def _finite_mean(values) -> float:
    """Mean of the finite values, NaN when there are none (no empty-slice warning)."""
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else float("nan")


def _dist(landmarks: np.ndarray, i: int, j: int) -> np.ndarray:
    return np.linalg.norm(landmarks[:, i] - landmarks[:, j], axis=-1)


def eye_centres(landmarks) -> tuple[np.ndarray, np.ndarray]:
    """Centres of the two eyes, each (n, 2): the means of points 36-41 and 42-47."""
    x = _track(landmarks)
    return x[:, RIGHT_EYE].mean(axis=1), x[:, LEFT_EYE].mean(axis=1)


# --------------------------------------------------------------------------- expression


def interocular(landmarks) -> np.ndarray:
    """Inter-ocular distance (IOD) of each frame.

    Parameters
    ----------
    landmarks : ndarray, shape (n, 68, 2)
        iBUG landmarks (x, y) per frame; NaN for a frame without a face.

    Returns
    -------
    ndarray, shape (n,), float64
        Distance between the eye centres (means of points 36-41 and 42-47), NaN
        where the landmarks are NaN.
    """
    right, left = eye_centres(landmarks)
    return np.linalg.norm(left - right, axis=-1)


def expression_signals(landmarks) -> dict[str, np.ndarray]:
    """Per-frame expression signals, normalised by the inter-ocular distance (IOD).

    Parameters
    ----------
    landmarks : ndarray, shape (n, 68, 2)
        iBUG landmarks (x, y) per frame; NaN for a frame without a face.

    Returns
    -------
    dict of str to ndarray, each shape (n,), float64
        ``mouth_open``: inner-lip gap, the mean of ``|62-66|``, ``|61-67|``, ``|63-65|``,
        over IOD;
        ``eye_open``: mean over both eyes of ``(|37-41| + |38-40|) / 2`` (and
        ``43-47``, ``44-46``), over IOD;
        ``brow_height``: mean distance of the brow points 17-26 to the line through the
        two eye centres, over IOD;
        ``mouth_width``: distance of the mouth corners 48-54, over IOD;
        ``mouth_corners``: height of the corners' mean (48, 54) over the middle of the upper lip
        (mean of 51, 62), along the face's upward axis (perpendicular to the line through the eye
        centres), over IOD: up in a smile, down in a frown or a pout.
        NaN where the landmarks are NaN (or the IOD is 0).
    """
    x = _track(landmarks)
    right, left = eye_centres(x)
    axis = left - right  # (n, 2)
    iod = np.linalg.norm(axis, axis=-1)
    mouth = np.mean([_dist(x, i, j) for i, j in INNER_LIP_PAIRS], axis=0)
    eye = np.mean([(_dist(x, *a) + _dist(x, *b)) / 2 for a, b in EYE_LID_PAIRS], axis=0)
    rel = x[:, BROWS] - right[:, None]  # (n, 10, 2)
    cross = np.abs(axis[:, None, 0] * rel[..., 1] - axis[:, None, 1] * rel[..., 0])  # = dist * IOD
    brow = _divide(cross.mean(axis=1), iod)
    up = np.stack([axis[:, 1], -axis[:, 0]], axis=-1)  # the eye axis turned a quarter towards the brows
    corners = x[:, list(MOUTH_CORNERS)].mean(axis=1) - x[:, list(UPPER_LIP_MIDDLE)].mean(axis=1)
    lift = np.sum(corners * up, axis=-1)  # = height * IOD
    return {
        "mouth_open": _divide(mouth, iod),
        "eye_open": _divide(eye, iod),
        "brow_height": _divide(brow, iod),
        "mouth_width": _divide(_dist(x, *MOUTH_CORNERS), iod),
        "mouth_corners": _divide(_divide(lift, iod), iod),
    }


#: the moments a viewer looks at to judge an expression: (what it shows, signal of :func:`expression_signals` or,
#: prefixed ``gaze_``, of :func:`gaze_signals`, +1 its highest / -1 its lowest)
PEAKS = (("widest mouth", "mouth_open", 1), ("widest lips", "mouth_width", 1),
         ("corners highest", "mouth_corners", 1), ("corners lowest", "mouth_corners", -1),
         ("eyes widest", "eye_open", 1), ("eyes most closed", "eye_open", -1),
         ("brows highest", "brow_height", 1), ("brows lowest", "brow_height", -1),
         ("looks furthest to the image's left", "gaze_along", -1),
         ("looks furthest to the image's right", "gaze_along", 1),
         ("eyes most crossed", "gaze_apart", -1), ("deepest creases between the brows", "creases", 1),
         ("head turned furthest to the image's left", "head_turn", -1),
         ("head turned furthest to the image's right", "head_turn", 1))


def head_turns(poses) -> np.ndarray:
    """(T,) how far each frame's head is turned: the sideways part of the direction its face looks in (the
    canonical face looks along -z, towards the camera), the sine of the turn; + when the nose points to the
    image's right, NaN for a frame without a pose. ``poses``: (T, k) rows that begin with the rotation vector
    (kinds.Pose.as_vector), as a drive's ``pose`` holds them."""
    rvecs = np.asarray(poses, np.float64).reshape(len(poses), -1)[:, :3]
    posed = np.isfinite(rvecs).all(axis=1)
    out = np.full(len(rvecs), np.nan)
    if posed.any():
        out[posed] = -Rotation.from_rotvec(rvecs[posed]).as_matrix()[:, 0, 2]  # x of R @ (0, 0, -1)
    return out


def expression_peaks(signals: dict) -> list[tuple[str, int]]:
    """The frame of each of :data:`PEAKS` in a face's :func:`expression_signals`, ``gaze_``-prefixed
    :func:`gaze_signals`, ``creases`` (:func:`crease_energy`) and ``head_turn`` (:func:`head_turns`): (what it
    shows, frame), leaving out a signal that is missing or NaN in every frame."""
    peaks = []
    for label, name, sign in PEAKS:
        x = sign * np.asarray(signals.get(name, np.nan), np.float64)
        if np.isfinite(x).any():
            peaks.append((label, int(np.nanargmax(x))))
    return peaks


def pearson(a, b) -> float:
    """Pearson correlation of two per-frame signals.

    Parameters
    ----------
    a, b : array_like, shape (n,)
        Signals; NaN (or inf) marks a frame to leave out.

    Returns
    -------
    float
        The correlation over the frames where both are finite; NaN when there are fewer
        than 3 such frames or either signal has zero variance there.
    """
    a = np.asarray(a, dtype=np.float64).ravel()
    b = np.asarray(b, dtype=np.float64).ravel()
    if a.shape != b.shape:
        raise ValueError(f"pearson: signals of different lengths {a.shape} and {b.shape}")
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3:
        return float("nan")
    da = a[ok] - a[ok].mean()
    db = b[ok] - b[ok].mean()
    saa, sbb = float(da @ da), float(db @ db)
    if saa == 0 or sbb == 0:
        return float("nan")
    # sqrt(s * s) == s exactly in IEEE arithmetic, so a signal against itself gives exactly 1
    r = float(da @ db) / np.sqrt(saa * sbb)
    return float(np.clip(r, -1.0, 1.0))


def moved_landmarks(meshes, fiducials) -> np.ndarray:
    """(T, 68, 2) landmarks of a face moved by per-frame meshes, for :func:`expression_signals`: the
    (x, y) of meshes (T, H, W, 3) at the canonical pixels of its 49 ``fiducials`` (49, 2); the jaw
    line (not among the fiducials) is NaN. Fiducials off the grid take its nearest edge pixel."""
    meshes = np.asarray(meshes)
    h, w = meshes.shape[1:3]
    cols, rows = np.round(np.asarray(fiducials, np.float64)).astype(int).T
    out = np.full((len(meshes), 68, 2), np.nan)
    out[:, list(IDX49)] = meshes[:, rows.clip(0, h - 1), cols.clip(0, w - 1), :2]
    return out


def posed_landmarks(meshes, fiducials, poses) -> np.ndarray:
    """(T, 68, 2) landmarks of a face moved by per-frame meshes and seen as the renderer draws it: the
    :func:`moved_landmarks` points' 3D positions (the meshes' (x, y, z) at the canonical pixels of the 49
    ``fiducials``, bilinear) projected at each frame's pose (``poses`` (T, 10), the store's rows), in frame
    pixels, where dlib's landmarks on the rendered frames should find them. A frame without a pose (NaN)
    and the jaw line are NaN."""
    fiducials = np.asarray(fiducials, np.float32)
    out = np.full((len(meshes), 68, 2), np.nan)
    for t, (mesh, pose) in enumerate(zip(meshes, poses)):
        if not np.isfinite(pose).all():
            continue
        points = compose(np.asarray(mesh, np.float32), fiducials[None], border=cv2.BORDER_REPLICATE)[0]
        out[t, list(IDX49)] = project(points, Pose.from_vector(pose))[0]
    return out


#: consecutive frames resampled together for a gain's interval (:func:`gain_interval`): a second at 25
#: frames/s, about how long a reading's error and an expression last
GAIN_BLOCK = 25


def amplitude(driver, output) -> dict:
    """How far an output signal moves with its driver's, which a correlation cannot see (a puppet
    that moves a tenth as far correlates perfectly).

    Parameters
    ----------
    driver, output : array_like, shape (n,)
        The same expression signal of the driver and the output; NaN marks a frame to leave out.

    Returns
    -------
    dict
        ``gain``: the least-squares slope of the output on the driver (1 = the same amplitude;
        NaN when fewer than 3 frames have both or the driver does not move); ``gain_interval``:
        [low, high], its 95 % interval (:func:`gain_interval`); ``r``: their Pearson correlation;
        ``driver_range``, ``output_range``: the 5th-95th percentile spread of each over those frames.
    """
    d = np.asarray(driver, np.float64).ravel()
    o = np.asarray(output, np.float64).ravel()
    ok = np.isfinite(d) & np.isfinite(o)
    if ok.sum() < 3:
        return {"gain": float("nan"), "gain_interval": [float("nan")] * 2, "r": float("nan"),
                "driver_range": float("nan"), "output_range": float("nan")}
    spread = [float(np.subtract(*np.percentile(v, [95, 5]))) for v in (d[ok], o[ok])]
    return {"gain": _slope(d[ok], o[ok]), "gain_interval": gain_interval(d[ok], o[ok]), "r": pearson(d, o),
            "driver_range": spread[0], "output_range": spread[1]}


def _slope(driver: np.ndarray, output: np.ndarray) -> float:
    """The least-squares slope of ``output`` on ``driver`` (n,) each, none missing; NaN where the driver
    does not move."""
    dd, do = driver - driver.mean(), output - output.mean()
    return _ratio(dd @ do, dd @ dd) if np.ptp(driver) > 0 else float("nan")


def gain_interval(driver: np.ndarray, output: np.ndarray, block: int = GAIN_BLOCK, resamples: int = 2000,
                  seed: int = 0) -> list[float]:
    """[low, high]: the 2.5th and 97.5th percentiles of the :func:`amplitude` gain over a moving-block
    bootstrap of the frames (the frames of ``driver`` and ``output``, (n,) each, none missing, drawn
    again ``resamples`` times as runs of ``block`` consecutive frames, so that the error dlib makes on
    neighbouring frames, which is alike, is not counted as independent). How far the gain could move on
    another clip of the same drive: a gain whose driver barely moves (a brow still to a pixel) has a wide
    one. Seeded: the same frames give the same interval. NaN where the driver does not move."""
    gains = _drawn_gains(driver, [output], block, resamples, seed)
    return _percentiles(gains[0]) if gains is not None else [float("nan")] * 2


def gain_difference(driver, first, second, block: int = GAIN_BLOCK, resamples: int = 2000,
                    seed: int = 0) -> dict:
    """How two runs of one drive differ in gain, judged on the same frames: ``difference``, the second's
    :func:`amplitude` gain less the first's, and ``interval``, its 95 % interval over the same draws of
    frames for both (a paired :func:`gain_interval`: the drive's own noise, in both, largely cancels, so
    it is much narrower than either run's interval). ``driver``, ``first``, ``second``: (n,) signals of
    the same frames, NaN to leave a frame out (of all three)."""
    d, a, b = (np.asarray(v, np.float64).ravel() for v in (driver, first, second))
    ok = np.isfinite(d) & np.isfinite(a) & np.isfinite(b)
    gains = _drawn_gains(d[ok], [a[ok], b[ok]], block, resamples, seed)
    if gains is None:
        return {"difference": float("nan"), "interval": [float("nan")] * 2}
    return {"difference": _slope(d[ok], b[ok]) - _slope(d[ok], a[ok]), "interval": _percentiles(gains[1] - gains[0])}


def _drawn_gains(driver: np.ndarray, outputs: list[np.ndarray], block: int, resamples: int,
                 seed: int) -> np.ndarray | None:
    """(len(outputs), draws): the gain of each output on ``driver`` over the same moving-block draws of
    the frames (none missing), draws where the driver moves in the drawn frames; None for a driver that
    does not move at all."""
    driver = np.asarray(driver, np.float64)
    n = len(driver)
    if n < 3 or np.ptp(driver) == 0:
        return None
    block = min(block, n)
    starts = np.random.default_rng(seed).integers(0, n - block + 1, (resamples, -(-n // block)))
    rows = (starts[..., None] + np.arange(block)).reshape(resamples, -1)[:, :n]  # (resamples, n) frames
    dd = driver[rows] - driver[rows].mean(axis=1, keepdims=True)
    var = np.einsum("ij,ij->i", dd, dd)
    moves = var > 0
    drawn = [np.asarray(o, np.float64)[rows] for o in outputs]
    return np.stack([np.einsum("ij,ij->i", dd, o - o.mean(axis=1, keepdims=True))[moves] / var[moves] for o in drawn])


def _percentiles(values: np.ndarray) -> list[float]:
    return [float(v) for v in np.percentile(values, [2.5, 97.5])] if len(values) else [float("nan")] * 2


def resting_landmarks(image: np.ndarray, detect, scales=(2, 3, 4, 5, 6)) -> np.ndarray | None:
    """Landmarks (68, 2) of a small, soft picture of a mean face ``image`` (h, w, 3) uint8, in its own
    pixels: the median of ``detect``'s (an image -> (68, 2) points, raising Rejected where it finds no
    face) on it enlarged by each of ``scales`` (cubic). One reading of a mean's mouth moves by up to 0.05
    IOD with the scale. None when no reading finds a face."""
    found = []
    for scale in scales:
        try:
            found.append(detect(cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)) / scale)
        except Rejected:
            pass
    return np.median(found, axis=0) if found else None


def held_expression(landmarks, rest) -> dict[str, float]:
    """The expression a face holds through a clip, which a gain cannot see (a face that smiles
    throughout smiles in no frame more than in the others): per expression signal, its mean over the
    frames of ``landmarks`` (n, 68, 2; NaN for a frame without a face) less its value on the resting
    face ``rest`` (68, 2): the actor's mean photo, or the puppet's neutral texture. NaN where no frame
    has a face, or the resting face has none (``rest`` None or NaN)."""
    moving = expression_signals(landmarks)
    resting = expression_signals(np.full((1, 68, 2), np.nan) if rest is None else np.asarray(rest)[None])
    out = {}
    for k, v in moving.items():
        v = v[np.isfinite(v)]
        out[k] = float(v.mean() - resting[k][0]) if len(v) and np.isfinite(resting[k][0]) else float("nan")
    return out


# --------------------------------------------------------------------------- stability


#: the iBUG points inside the jaw line (brows, nose, eyes, mouth): what a face without its jaw line shows
INNER = slice(17, 68)


def jitter(landmarks, points=slice(None)) -> float:
    """Landmark jitter: the mean acceleration of the points, relative to the face size.

    Parameters
    ----------
    landmarks : ndarray, shape (n, 68, 2)
        iBUG landmarks (x, y) per frame; NaN for a frame without a face.
    points : slice or index array
        The points counted (default all 68; :data:`INNER` leaves the jaw line out).

    Returns
    -------
    float
        Mean over frames t = 1 .. n-2 and the points of
        ``|x[t+1] - 2 x[t] + x[t-1]|`` (Euclidean) divided by the IOD of frame t.
        Triples with a NaN frame are skipped; NaN when no triple is left. Constant and
        uniformly moving tracks have jitter 0.
    """
    x = _track(landmarks)
    if len(x) < 3:
        return float("nan")
    accel = np.linalg.norm(x[2:] - 2 * x[1:-1] + x[:-2], axis=-1)[:, points]  # (n-2, points)
    return _finite_mean(_divide(accel, interocular(x)[1:-1, None]))


def masked_mean_colours(frames, masks) -> np.ndarray:
    """Mean RGB of the masked pixels of each frame.

    Parameters
    ----------
    frames : ndarray, shape (n, h, w, 3)
    masks : ndarray, shape (n, h, w), bool

    Returns
    -------
    ndarray, shape (n, 3), float64
        In the frames' units (0-255 for uint8); NaN for a frame with an empty mask.
    """
    frames = np.asarray(frames)
    masks = np.asarray(masks, dtype=bool)
    if frames.ndim != 4 or masks.shape != frames.shape[:3]:
        raise ValueError(f"want frames (n, h, w, c) and masks (n, h, w), "
                         f"got {frames.shape} and {masks.shape}")
    out = np.full((len(frames), frames.shape[3]), np.nan)
    for t, (frame, mask) in enumerate(zip(frames, masks)):
        box = mask_box(mask)
        if box is not None:
            out[t] = cv2.mean(np.ascontiguousarray(frame[box]), mask[box].astype(np.uint8))[:frames.shape[3]]
    return out


#: the iBUG points of the outer lips, round the mouth
OUTER_LIPS = slice(48, 60)


def without_mouths(mask: np.ndarray, *landmarks) -> np.ndarray:
    """The face region ``mask`` (h, w) bool less each face's mouth: the polygon of its outer lips
    (:data:`OUTER_LIPS`) in each of ``landmarks`` (68, 2; the driver's and the output's, in the mask's
    pixels). A mouth that opens changes the face's mean colour by what it shows (teeth, tongue, the
    dark inside), which is expression, not flicker: the colour flicker is judged without it. All False
    where any of them lacks a point, so that the frame is not judged."""
    mask = np.asarray(mask, bool)
    lips = [np.asarray(points, np.float64)[OUTER_LIPS] for points in landmarks]
    if not all(np.isfinite(p).all() for p in lips):
        return np.zeros_like(mask)
    mouths = np.zeros(mask.shape, np.uint8)
    for p in lips:  # one at a time: overlapping mouths in one call would leave their overlap out
        cv2.fillPoly(mouths, [np.round(p * 16).astype(np.int32)], 1, cv2.LINE_8, shift=4)
    return mask & (mouths == 0)


def colour_change(frames, masks) -> float:
    """Colour flicker of the face region between consecutive frames.

    Parameters
    ----------
    frames : ndarray, shape (n, h, w, 3)
        RGB frames (uint8, 0-255).
    masks : ndarray, shape (n, h, w), bool
        The face region of each frame (empty: no face).

    Returns
    -------
    float
        Mean over t of the Euclidean RGB distance between the mean colours of the masked
        region at t+1 and at t, in 0-255 units; pairs with an empty mask are skipped,
        NaN when no pair is left.
    """
    return flicker(masked_mean_colours(frames, masks))


def flicker(colours) -> float:
    """Mean Euclidean change between consecutive rows of (n, 3) mean colours (NaN rows skipped)."""
    colours = np.asarray(colours, dtype=np.float64)
    if len(colours) < 2:
        return float("nan")
    return _finite_mean(np.linalg.norm(np.diff(colours, axis=0), axis=-1))


def frame_changes(frames, mask) -> np.ndarray:
    """(n - 1,) the mean absolute change (grey levels, over RGB) inside ``mask`` (h, w) between
    consecutive frames (n, h, w, 3): how much an image sequence flickers, detail and all (the
    mean colour of :func:`flicker` cannot see details that come and go)."""
    if len(frames) < 2:
        return np.zeros(0)
    inside = np.asarray(frames)[:, np.asarray(mask, bool)].astype(np.float32)  # (n, pixels, 3)
    return np.abs(np.diff(inside, axis=0)).mean(axis=(1, 2)).astype(np.float64)


# --------------------------------------------------------------------------- tears

#: σ (canonical px) of the Hessian that finds thin lines: a crack is one or two px wide
TEAR_SIGMA = 1.0
#: a pixel is torn where its line strength exceeds this percentile of the collection's own photos' there
TEAR_PERCENTILE = 90


def masked_blur(grey, mask, sigma: float) -> np.ndarray:
    """(h, w) float32: a Gaussian blur (σ px) of ``grey`` (h, w) over the pixels of ``mask`` (h, w) alone,
    each pixel the weighted mean of the masked ones around it (normalised convolution); the whole image
    with ``mask`` None. A photo frontalized into the canonical frame is 0 beyond its view: a plain blur
    would mix that 0 into the face, and a filter would see the cut-out's edge as detail or as a line."""
    grey = np.asarray(grey, np.float32)
    if mask is None:
        return cv2.GaussianBlur(grey, (0, 0), sigma)
    weight = np.asarray(mask, np.float32)
    return cv2.GaussianBlur(grey * weight, (0, 0), sigma) / np.maximum(cv2.GaussianBlur(weight, (0, 0), sigma), 1e-6)


def line_strength(image, mask=None) -> np.ndarray:
    """(h, w) how much each pixel of an RGB image (0-255) lies on a thin line or a step: ||λ1| - |λ2||
    of the grey image's Hessian at σ = ``TEAR_SIGMA`` (σ²-normalised), λ the two eigenvalues, from the
    pixels of ``mask`` alone (:func:`masked_blur`; None: all). High across a crack or a jump, low on
    smooth skin and on round blobs."""
    grey = np.asarray(image, np.float32) @ np.float32([0.299, 0.587, 0.114]) / 255
    g = masked_blur(grey, mask, TEAR_SIGMA)
    xx, yy = cv2.Sobel(g, cv2.CV_32F, 2, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 2, ksize=3)
    xy = cv2.Sobel(g, cv2.CV_32F, 1, 1, ksize=3)
    mean, half = (xx + yy) / 2, np.sqrt(((xx - yy) / 2) ** 2 + xy ** 2)
    return np.abs(np.abs(mean + half) - np.abs(mean - half)) * np.float32(TEAR_SIGMA ** 2)


def inner(valid, margin: int = 2) -> np.ndarray:
    """``valid`` (h, w) bool eroded by ``margin`` px: where a photo's view ends its image jumps to 0."""
    size = 2 * margin + 1
    return cv2.erode(np.asarray(valid, np.uint8), np.ones((size, size), np.uint8)) > 0


def tear_reference(photos, masks) -> np.ndarray:
    """(h, w) the ``TEAR_PERCENTILE``-th percentile of :func:`line_strength` over the photos (n, h, w, 3)
    whose mask (n, h, w; their view, :func:`inner`) holds each pixel: the lines a collection's own
    photos have there (eyelids, lips, creases). NaN where no photo counts."""
    strengths = np.stack([np.where(m, line_strength(p, m), np.nan) for p, m in zip(photos, masks)])
    return nan_percentile(strengths, TEAR_PERCENTILE)


def nan_percentile(values: np.ndarray, q: float) -> np.ndarray:
    """``np.nanpercentile(values, q, axis=0)`` (linear interpolation between the two nearest ranks of the
    finite values), NaN where none is finite, without its loop over every other axis' positions: the
    values sorted along axis 0 (NaN last) and read at each position's own rank."""
    ordered = np.sort(values, axis=0)
    count = np.isfinite(values).sum(axis=0)
    rank = np.maximum(count - 1, 0) * (q / 100)
    below = np.floor(rank).astype(int)
    above = np.minimum(below + 1, np.maximum(count - 1, 0))
    low = np.take_along_axis(ordered, below[None], axis=0)[0]
    high = np.take_along_axis(ordered, above[None], axis=0)[0]
    return np.where(count > 0, low + (rank - below) * (high - low), np.nan)


def tear_energy(image, mask, reference) -> float:
    """The tears of one image (h, w, 3) in the canonical frame: the mean square (×1000) inside ``mask``
    of its line strength beyond the collection's ``reference`` (:func:`tear_reference`). A collection's
    own photos score about the same as one another (each exceeds the others' percentile here and
    there); a clean blend of them scores less, cracks that no photo has score more."""
    excess = np.maximum(line_strength(image, mask) - reference, 0)
    inside = np.asarray(mask, bool) & np.isfinite(reference)
    return float(1000 * np.mean(excess[inside] ** 2)) if inside.any() else float("nan")


#: the fine detail the believable-face issue measures: a difference of Gaussians of σ 1 and 2 px on a face
#: whose eyes are ``DETAIL_IOD`` px apart
DETAIL_SIGMAS = (1.0, 2.0)
DETAIL_IOD = 100.0


@lru_cache(maxsize=1)
def canonical_iod() -> float:
    """How far apart (px) the eye centres of the canonical frame's generic template are (65.6)."""
    return float(interocular(generic_template().landmarks3d[None, :, :2])[0])


def detail_energy(image, mask, iod: float | None = None) -> float:
    """Fine detail of an image (h, w, 3, 0-255) inside ``mask``: the mean square ×1000 of its grey band-pass
    (grey in [0, 1]; difference of Gaussians of ``DETAIL_SIGMAS`` at ``DETAIL_IOD`` px between the eyes,
    scaled to the image's ``iod``, by default the canonical frame's; from the pixels of ``mask`` alone,
    :func:`masked_blur`). A blur lowers it, tears raise it, and the edge of a photo cut out on black does
    not count."""
    scale = (canonical_iod() if iod is None else iod) / DETAIL_IOD
    grey = np.asarray(image, np.float32) @ np.float32([0.299, 0.587, 0.114]) / 255
    band = masked_blur(grey, mask, DETAIL_SIGMAS[0] * scale) - masked_blur(grey, mask, DETAIL_SIGMAS[1] * scale)
    inside = np.asarray(mask, bool)
    return float(1000 * np.mean(band[inside] ** 2)) if inside.any() else float("nan")


def _reach(sigma: float) -> int:
    """How far (px) OpenCV's Gaussian blur of σ ``sigma`` reads from a pixel on float images: half its kernel,
    which OpenCV makes 8σ + 1 wide, rounded to odd."""
    return int(round(sigma * 8 + 1)) // 2


#: how far inside the rendered face's edge (px) :func:`sharpness` looks: the mask's feather and the
#: composite's seam are not the face's detail
SHARPNESS_INSET = 4


def sharpness(image, reference, mask) -> float:
    """How sharp ``image`` is beside ``reference`` (both (h, w, 3), 0-255) inside ``mask`` (h, w) less its
    outer SHARPNESS_INSET px: the ratio of their :func:`detail_energy` at the images' own scale (σ 1 and
    2 px, whatever the face's size), the fine detail a viewer sees at the video's resolution, each over its
    mean grey squared there, so that a face lit darker (B's skin under A's light) is as sharp as before.
    1 = as sharp as the reference (the driver's own face in its frame); a blur or a texture finer than the
    frame shows lowers it, ringing and noise raise it. NaN where nothing is left of the mask or the
    reference is flat. The mask is eroded on its box grown by the inset, and the detail taken on a box
    (:func:`relative_detail`): the whole frame's figure (to float32's rounding) at a fraction of its cost
    on an HD frame."""
    box = mask_box(np.asarray(mask, bool), SHARPNESS_INSET)
    if box is None:
        return float("nan")
    image, reference = np.asarray(image)[box], np.asarray(reference)[box]
    inset = 2 * SHARPNESS_INSET + 1
    inside = cv2.erode(np.asarray(mask, np.uint8)[box], np.ones((inset, inset), np.uint8)) > 0
    if not inside.any():
        return float("nan")

    theirs = relative_detail(reference, inside, DETAIL_IOD)
    return relative_detail(image, inside, DETAIL_IOD) / theirs if theirs > 0 else float("nan")


def relative_detail(image, inside, iod: float) -> float:
    """:func:`detail_energy` of ``image`` inside ``inside`` (h, w) over the mean grey (0-1) there squared: the
    same for a face lit darker or brighter. Computed on the box of ``inside`` grown by what the blurs reach, and
    so the whole image's figure (to float32's rounding)."""
    box = mask_box(np.asarray(inside, bool), _reach(DETAIL_SIGMAS[1] * iod / DETAIL_IOD))
    if box is None:
        return float("nan")
    image, inside = np.asarray(image)[box], np.asarray(inside, bool)[box]
    grey = float((np.asarray(image, np.float32)[inside] @ np.float32([0.299, 0.587, 0.114])).mean()) / 255
    return detail_energy(image, inside, iod=iod) / max(grey, 1e-3) ** 2


#: the skin between the brows reaches this many eye distances above the higher brow, and this many below the
#: lower of the brows' inner ends (:func:`crease_region`): not down to the nose, where glasses have their bridge
CREASE_ABOVE, CREASE_BELOW = 0.35, 0.1
#: fewer pixels than this between the brows: no crease figure for that face
CREASE_MIN_PIXELS = 20


def crease_region(points, shape) -> np.ndarray:
    """(h, w) bool: the skin between the brows of a face with iBUG landmarks ``points`` (68, 2) in an image of
    ``shape`` (h, w), where a frown draws its upright creases and raised brows their level ones. Along the eyes'
    axis, from the inner end of one brow (point 21) to that of the other (22); across it, from
    ``CREASE_ABOVE`` eye distances above the higher brow down to ``CREASE_BELOW`` below the lower inner end.
    None of it where the points are NaN."""
    p = np.asarray(points, np.float64)
    out = np.zeros(shape[:2], np.uint8)
    if not np.isfinite(p).all():
        return out > 0
    right, left = (centre[0] for centre in eye_centres(p[None]))
    iod = float(np.linalg.norm(left - right))
    along = (left - right) / max(iod, 1e-9)
    down = np.array([-along[1], along[0]])  # the eyes' axis turned a quarter: down the face
    a0, a1 = sorted((p[21] @ along, p[22] @ along))
    d0, d1 = min(p[17:27] @ down) - CREASE_ABOVE * iod, max(p[21] @ down, p[22] @ down) + CREASE_BELOW * iod
    corners = [a * along + d * down for a, d in ((a0, d0), (a1, d0), (a1, d1), (a0, d1))]
    cv2.fillConvexPoly(out, np.round(corners).astype(np.int32), 1)
    return out > 0


def crease_energy(image, points, mask=None) -> float:
    """The fine detail between the brows of a face in an RGB ``image`` (h, w, 3) with iBUG landmarks ``points``
    (68, 2): :func:`relative_detail` of its :func:`crease_region` (within ``mask`` (h, w) where given: a face
    drawn alone on grey) at the face's own scale, σ 1 and 2 px at 100 px between the eyes. It rises as a frown
    draws creases there and falls as the skin smooths. NaN without the points or with fewer than
    ``CREASE_MIN_PIXELS`` pixels there."""
    region = crease_region(points, np.shape(image))
    if mask is not None:
        region &= np.asarray(mask, bool)
    if region.sum() < CREASE_MIN_PIXELS:
        return float("nan")
    return relative_detail(image, region, float(interocular(np.asarray(points, np.float64)[None])[0]))


# --------------------------------------------------------------------------- identity figures


def centroid(descriptors) -> np.ndarray:
    """Mean of the finite rows of descriptors (n, d) -> (d,); all NaN when there are none."""
    d = np.asarray(descriptors, dtype=np.float64)
    ok = np.all(np.isfinite(d), axis=1)
    return d[ok].mean(axis=0) if ok.any() else np.full(d.shape[1], np.nan)


def identity_figures(descriptors, centroid_b, centroid_a, threshold: float = 0.6) -> dict:
    """Does each output frame look like B (the puppet) and not like A (the driver)?

    Parameters
    ----------
    descriptors : ndarray, shape (n, d)
        Face descriptor of each output frame; a NaN row for a frame without a face.
    centroid_b, centroid_a : ndarray, shape (d,)
        Reference descriptors of B and A (e.g. the :func:`centroid` of their photos).
    threshold : float
        Same-person distance threshold (0.6 for dlib's descriptor).

    Returns
    -------
    dict
        ``distance_to_b``, ``distance_to_a``: ndarray (n,) float64, NaN without a face;
        ``mean_distance_to_b``, ``mean_distance_to_a``: float over the frames with a face;
        ``fraction_b_not_a``: float, the fraction of all n frames with
        ``d_b < threshold`` and ``d_a > threshold`` (a frame without a face counts as a
        failure; NaN when n = 0);
        ``frames_without_face``: int.
    """
    d = np.asarray(descriptors, dtype=np.float64)
    if d.ndim != 2:
        raise ValueError(f"want descriptors of shape (n, d), got {d.shape}")
    b = np.asarray(centroid_b, dtype=np.float64)
    a = np.asarray(centroid_a, dtype=np.float64)
    face = np.all(np.isfinite(d), axis=1)
    d_b = np.linalg.norm(d - b, axis=1)  # NaN rows stay NaN
    d_a = np.linalg.norm(d - a, axis=1)
    d_b[~face] = np.nan
    d_a[~face] = np.nan
    n = len(d)
    with np.errstate(invalid="ignore"):  # NaN comparisons are False: failures
        success = (d_b < threshold) & (d_a > threshold)
    return {
        "distance_to_b": d_b,
        "distance_to_a": d_a,
        "mean_distance_to_b": _finite_mean(d_b),
        "mean_distance_to_a": _finite_mean(d_a),
        "fraction_b_not_a": float(success.sum() / n) if n else float("nan"),
        "frames_without_face": int(n - face.sum()),
    }


# --------------------------------------------------------------------------- image fidelity


def _mask_like(a: np.ndarray, b: np.ndarray, mask) -> np.ndarray:
    if a.shape != b.shape:
        raise ValueError(f"images of different shapes {a.shape} and {b.shape}")
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != a.shape[:2]:
        raise ValueError(f"mask {mask.shape} does not match the images {a.shape}")
    return mask


def masked_psnr(a, b, mask) -> float:
    """PSNR of two images over a mask.

    Parameters
    ----------
    a, b : ndarray, shape (h, w, 3) or (h, w), uint8
    mask : ndarray, shape (h, w), bool

    Returns
    -------
    float
        ``10 log10(255^2 / MSE)`` in dB, the MSE over the masked pixels and all channels;
        inf for identical images, NaN for an empty mask.
    """
    a, b = np.asarray(a), np.asarray(b)
    mask = _mask_like(a, b, mask)
    box = mask_box(mask)
    if box is None:
        return float("nan")
    inside = mask[box].astype(np.uint8)
    squares = cv2.norm(np.ascontiguousarray(a[box]), np.ascontiguousarray(b[box]), cv2.NORM_L2SQR, mask=inside)
    mse = squares / (int(inside.sum()) * (a.shape[2] if a.ndim == 3 else 1))
    if mse == 0:
        return float("inf")
    return float(10 * np.log10(255.0**2 / mse))


#: the root-mean-square difference (grey levels) :meth:`ErrorSums.picture` draws red; 0 is blue
ERROR_SCALE = 40.0

#: the mean difference, real less output (grey levels), :meth:`ErrorSums.picture` draws red (the output darker);
#: minus it is blue (lighter), 0 green
BIAS_SCALE = 20.0

#: the parts of the face whose shares of a self-reenactment's squared error are given (:meth:`ErrorSums.shares`):
#: each the convex hulls of these groups of the real frame's iBUG points, grown by :data:`REGION_GROWTH`; a pixel
#: in two goes to the first; the face's pixels in none are ``rest`` (cheeks, forehead, chin)
ERROR_REGIONS = {"eyes": (range(36, 42), range(42, 48)), "brows": (range(17, 22), range(22, 27)),
                 "nose": (range(27, 36),), "mouth": (range(48, 60),)}
#: how far each region reaches beyond its points' hull, in the frame's eye distances
REGION_GROWTH = 0.1


def region_labels(landmarks: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(h, w) uint8: each pixel's index in :data:`ERROR_REGIONS` by a frame's 68 ``landmarks``, or its length
    (``rest``) where it is in none."""
    labels = np.full(shape, len(ERROR_REGIONS), np.uint8)
    grow = REGION_GROWTH * float(interocular(np.asarray(landmarks)[None])[0])
    for index, groups in reversed(list(enumerate(ERROR_REGIONS.values()))):  # the first region drawn last
        for group in groups:
            hull = cv2.convexHull(np.asarray(landmarks, np.float32)[list(group)])[:, 0].astype(np.float64)
            out = hull - hull.mean(axis=0)
            hull += grow * out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-9)
            cv2.fillPoly(labels, [np.round(hull).astype(np.int32)], index)
    return labels


@dataclass
class ErrorSums:
    """What a self-reenactment's error map is made of, summed over frames: each pixel's squared difference of
    the output from the real frame (``square``, (h, w, 3) float32, per channel), the real frames (``real``,
    (h, w, 3) float32), the outputs (``output``, the same), the pixels the face covered in some frame
    (``seen``, (h, w) bool), how many ``frames``, and the squared error inside the face in each of
    :data:`ERROR_REGIONS` and the rest (``regions``). Sums of disjoint frames add (``+``)."""

    square: np.ndarray
    real: np.ndarray
    output: np.ndarray
    seen: np.ndarray
    frames: int = 0
    regions: np.ndarray = field(default_factory=lambda: np.zeros(len(ERROR_REGIONS) + 1))

    @classmethod
    def zeros(cls, shape: tuple[int, int, int]) -> "ErrorSums":
        return cls(np.zeros(shape, np.float32), np.zeros(shape, np.float32), np.zeros(shape, np.float32),
                   np.zeros(shape[:2], bool))

    def add(self, output: np.ndarray, real: np.ndarray, face: np.ndarray, landmarks: np.ndarray | None = None) -> None:
        """One frame: ``output`` and ``real`` (h, w, 3) uint8, ``face`` (h, w) bool, and the real frame's 68
        ``landmarks`` (none, or NaN: its error counts in no region). OpenCV's accumulators: a tenth of NumPy's
        time on a 720p frame, the same sums."""
        difference = cv2.absdiff(output, real)
        cv2.accumulateSquare(difference, self.square)
        cv2.accumulate(real, self.real)
        cv2.accumulate(output, self.output)
        self.seen |= face
        self.frames += 1
        box = mask_box(face)
        if box is not None and landmarks is not None and np.isfinite(landmarks).all():
            off = len(self.regions)  # the label of the pixels off the face, dropped
            labels = np.where(face[box], region_labels(np.asarray(landmarks) - [box[1].start, box[0].start],
                                                       face[box].shape), off)
            part = difference[box].astype(np.float32)
            squares = np.einsum("ijk,ijk->ij", part, part)
            self.regions += np.bincount(labels.ravel(), weights=squares.ravel(), minlength=off + 1)[:off]

    def __add__(self, other: "ErrorSums") -> "ErrorSums":
        return ErrorSums(self.square + other.square, self.real + other.real, self.output + other.output,
                         self.seen | other.seen, self.frames + other.frames, self.regions + other.regions)

    def shares(self) -> dict[str, float]:
        """Each region's share of the squared error inside the face (:data:`ERROR_REGIONS`, then ``rest``), over
        the frames whose real face dlib found; NaN where there is none."""
        total = self.regions.sum()
        names = [*ERROR_REGIONS, "rest"]
        return {name: float(v / total) if total > 0 else float("nan") for name, v in zip(names, self.regions)}

    def picture(self, scale: float = ERROR_SCALE, bias: float = BIAS_SCALE, margin: float = 0.1) -> np.ndarray | None:
        """Where the output differs from the real frames, (h, 3w, 3) uint8 RGB, in OpenCV's JET colours: the mean
        real frame; the root-mean-square difference at each pixel (the mean over the channels), blue at 0 to red
        at ``scale`` grey levels and over; and the mean difference, real less output, green at 0, red at ``bias``
        and over (the output darker there on average: its light or tone, not its detail), blue at -``bias``. All
        cut to the face's box (``seen``) and ``margin`` of its size around. None where the face covered no pixel."""
        face = mask_box(self.seen)  # none: no frame drew a face
        if face is None:
            return None
        box = mask_box(self.seen, int(margin * max(s.stop - s.start for s in face)))
        rms = np.sqrt(self.square[box].astype(np.float64).mean(axis=-1) / self.frames)
        darker = (self.real[box].astype(np.float64) - self.output[box]).mean(axis=-1) / self.frames
        heats = [cv2.cvtColor(cv2.applyColorMap(np.clip(np.round(255 * level), 0, 255).astype(np.uint8),
                                                cv2.COLORMAP_JET), cv2.COLOR_BGR2RGB)
                 for level in (rms / scale, 0.5 + darker / (2 * bias))]
        mean = np.clip(np.round(self.real[box].astype(np.float64) / self.frames), 0, 255).astype(np.uint8)
        return np.hstack([mean, *heats])


#: SSIM's window (px, a box of this side, as skimage's default) and constants (Wang et al. 2004)
SSIM_WINDOW, SSIM_K1, SSIM_K2 = 7, 0.01, 0.03


def ssim_map(a, b, data_range: float = 255.0) -> np.ndarray:
    """The structural similarity of two images (h, w[, c]) at every pixel and channel, float32: the mean,
    variance (sample variance, as skimage's default) and covariance over a :data:`SSIM_WINDOW` box about
    each pixel, the image's edge reflected. :func:`skimage.metrics.structural_similarity`'s ``full`` map
    to 1e-4 (its mean over a face to 1e-6), in a quarter of its time: OpenCV's box filter in float32, on
    values centred on mid-grey so that the variances keep their precision."""
    return ssim_maps([a], b, data_range)[0]


def ssim_maps(images, reference, data_range: float = 255.0) -> list[np.ndarray]:
    """:func:`ssim_map` of each of ``images`` against the same ``reference``, whose local mean and variance
    are computed once (the same figures to the bit)."""
    centre = np.float32(data_range / 2)

    def mean(x):
        return cv2.boxFilter(x, -1, (SSIM_WINDOW, SSIM_WINDOW), normalize=True, borderType=cv2.BORDER_REFLECT)

    n = SSIM_WINDOW * SSIM_WINDOW
    sample = np.float32(n / (n - 1))

    def covariance(x, y, ux, uy):
        return sample * (mean(x * y) - ux * uy)

    c1, c2 = np.float32((SSIM_K1 * data_range) ** 2), np.float32((SSIM_K2 * data_range) ** 2)
    b = np.asarray(reference, np.float32) - centre
    ub = mean(b)
    vb, mb = covariance(b, b, ub, ub), ub + centre  # the reference's variance and (not centred) mean
    maps = []
    for a in images:
        a = np.asarray(a, np.float32) - centre
        ua = mean(a)
        va, vab = covariance(a, a, ua, ua), covariance(a, b, ua, ub)
        ma = ua + centre
        maps.append((2 * ma * mb + c1) * (2 * vab + c2) / ((ma * ma + mb * mb + c1) * (va + vb + c2)))
    return maps


def masked_ssim(a, b, mask) -> float:
    """Mean structural similarity of two images over a mask.

    Parameters
    ----------
    a, b : ndarray, shape (h, w, 3) or (h, w), uint8
    mask : ndarray, shape (h, w), bool

    Returns
    -------
    float
        The SSIM map (:func:`ssim_map`, ``data_range`` 255, per channel) averaged over the masked pixels
        (and channels); 1 for identical images, NaN for an empty mask. The map is computed on the mask's
        bounding box widened by half the window (every window of a masked pixel lies inside it, or
        meets the image's own edge there): the same figure as on the whole image, in the time of the
        face's pixels.
    """
    return masked_ssims([a], b, mask)[0]


def masked_ssims(images, reference, mask) -> list[float]:
    """:func:`masked_ssim` of each of ``images`` against the same ``reference`` (:func:`ssim_maps`)."""
    reference = np.asarray(reference)
    images = [np.asarray(a) for a in images]
    for a in images:
        mask = _mask_like(a, reference, mask)
    box = mask_box(mask, SSIM_WINDOW // 2)
    if box is None:
        return [float("nan")] * len(images)
    inside = mask[box]
    maps = ssim_maps([a[box] for a in images], reference[box])
    return [float(np.mean(full[inside], dtype=np.float64)) for full in maps]


#: a parting of the eyes measured further than this (eye widths) beyond the clip's usual one is the measure's error,
#: not a turn: eyes part at most gaze.MAX_PART (0.1) beyond where they usually are, and the measure's noise at HD is
#: 0.03-0.05 a frame. The errors looked at: an eye half open after a blink (the fringe woman's 0.70), a glare on
#: glasses over one iris (the man with glasses: up to 0.32 beyond his usual)
PART_MEASURED = 0.2


def gaze_signals(offsets) -> dict[str, np.ndarray]:
    """Per frame, where the eyes look: the iris offsets (n, 2 eyes, 2) of
    :func:`persona.plugins.face.gaze.iris_offsets`, the two eyes' mean along the eye (``along``, positive
    towards the image's right) and across it (``across``, positive down), in eye widths, NaN where neither
    eye was measured; and how far they turn apart (``apart``: the image's right eye's offset along less the
    left one's, positive as they diverge, negative as they converge or cross), NaN where either was not, or
    where they part further than :data:`PART_MEASURED` beyond the median over the frames."""
    offsets = np.asarray(offsets, np.float64).reshape(-1, 2, 2)
    seen = np.isfinite(offsets[..., 0]).sum(axis=1)
    total = np.nansum(offsets, axis=1)
    mean = np.where(seen[:, None] > 0, total / np.maximum(seen, 1)[:, None], np.nan)
    apart = offsets[:, 1, 0] - offsets[:, 0, 0]
    if np.isfinite(apart).any():
        apart[apart > np.nanmedian(apart) + PART_MEASURED] = np.nan
    return {"along": mean[:, 0], "across": mean[:, 1], "apart": apart}


#: the regions of dlib's 68 points the landmark registration is given for (iBUG indices)
REGIONS = {"jaw": slice(0, 17), "brows": BROWS, "nose": slice(27, 36), "eyes": slice(36, 48),
           "mouth": slice(48, 68)}


def registration(reference, found) -> dict[str, float]:
    """How far the landmarks ``found`` (n, 68, 2) on output frames lie from those of the real frames
    ``reference`` (n, 68, 2) at the same moments (a self-reenactment: the frames the output replaces),
    per region of :data:`REGIONS` and over all 68: the median over frames of each frame's mean point
    distance, in % of the real frame's inter-ocular distance. Frames where either has no face are left
    out; NaN when none is left. Points that ``found`` has in no frame at all are left out of their region
    (B's 49 fiducials posed by the mesh have no jaw line: their "all" is over the 49, their jaw NaN)."""
    reference, found = _track(reference), _track(found)
    if reference.shape != found.shape:
        raise ValueError(f"registration: {reference.shape} and {found.shape} landmark tracks")
    error = np.linalg.norm(found - reference, axis=-1) / interocular(reference)[:, None] * 100  # (n, 68)
    drawn = np.flatnonzero(np.isfinite(found).all(axis=-1).any(axis=0))  # the points found has at all
    out = {}
    for name, points in {"all": slice(None), **REGIONS}.items():
        region = error[:, np.intersect1d(np.arange(68)[points], drawn)]
        per_frame = region[np.isfinite(region).all(axis=1)].mean(axis=1) if region.shape[1] else []
        out[name] = float(np.median(per_frame)) if len(per_frame) else float("nan")
    return out


# --------------------------------------------------------------------------- driver vs output


def compare_videos(driver_landmarks, output_landmarks, *, driver_frames=None, driver_masks=None,
                   output_frames=None, output_masks=None, jaw: bool = True) -> dict:
    """Expression transfer and stability of a puppet video against its driving video.

    Parameters
    ----------
    driver_landmarks, output_landmarks : ndarray, shape (n, 68, 2)
        Landmarks of the driving video (A) and of the puppet video (B), frame-aligned;
        NaN for a frame without a face.
    driver_frames, output_frames : ndarray, shape (n, h, w, 3), uint8, optional
        RGB frames, for the colour flicker; each needs its masks.
    driver_masks, output_masks : ndarray, shape (n, h, w), bool, optional
        Face region of each frame.
    jaw : bool
        Whether the output shows a jaw line. The face alone on grey does not (its mask ends above
        the chin): dlib's 17 jaw points on it are its shape model's guess, which wanders from frame
        to frame with nothing in the image to hold it, so without a jaw the jitter counts the 51
        points inside it (:data:`INNER`), the driver's too.

    Returns
    -------
    dict
        ``expression``: ``{"mouth_open", "eye_open", "brow_height", "mouth_width", "mouth_corners"}``, the
        Pearson correlation between the driver's and the output's signal (see
        :func:`expression_signals`); ``amplitude``: the same signals' :func:`amplitude`;
        ``stability``: ``jitter_driver``, ``jitter_output``, ``jitter_ratio``
        (output / driver), and, when the frames are given, ``colour_change_driver``,
        ``colour_change_output`` and ``colour_change_ratio``. All plain floats.
    """
    driver = _track(driver_landmarks)
    output = _track(output_landmarks)
    if len(driver) != len(output):
        raise ValueError(f"driver has {len(driver)} frames, output {len(output)}: align them first")
    sd, so = expression_signals(driver), expression_signals(output)
    expression = {k: pearson(sd[k], so[k]) for k in sd}
    amplitudes = {k: amplitude(sd[k], so[k]) for k in sd}
    points = slice(None) if jaw else INNER
    jd, jo = jitter(driver, points), jitter(output, points)
    stability = {"jitter_driver": jd, "jitter_output": jo, "jitter_ratio": _ratio(jo, jd)}
    for who, frames, masks in (("driver", driver_frames, driver_masks),
                               ("output", output_frames, output_masks)):
        if frames is None:
            continue
        if masks is None:
            raise ValueError(f"{who}_frames need {who}_masks (the face region)")
        stability[f"colour_change_{who}"] = colour_change(frames, masks)
    if "colour_change_driver" in stability and "colour_change_output" in stability:
        stability["colour_change_ratio"] = _ratio(stability["colour_change_output"],
                                                  stability["colour_change_driver"])
    return {"expression": expression, "amplitude": amplitudes, "stability": stability}
