"""Gaze: where the iris sits in the eye's opening, measured in a frame and given to B's texture.

Not in the paper. The drive's texture keeps B's neutral geometry and takes its eyes from B's photos
whose lids are as far apart as the target's (``eye_sigma``); nothing in the 49 fiducials says where
the eyes look, so B's irises stayed where B's photos mostly had them, looking ahead, while the driver
looked left, right, up or down.

Measured (:func:`iris_offsets`): in each eye's opening (the polygon of its six iBUG points) the iris is
the darkest disc about ``IRIS`` eye widths across (its darkness, the opening's brightest tenth less
the grey, summed over the disc; the best disc's place refined to a fraction of a pixel by a parabola
through its neighbours). Its offset is taken from the middle of the eye's two corners, along the line
from corner to corner (u, positive towards the image's right) and across it (v, positive down), in
eye widths: a measure that does not depend on the size of the face or its roll.

Given (:func:`look`): B's texture's eye openings (at B's neutral fiducials, grown by a pixel) have
their insides slid by the driver's offset from the driver's own usual gaze (the clip's median), times
B's eye width: the iris slides in the opening, the white in front of it squeezed and behind it
stretched, the corners and lids where they were.
"""

from __future__ import annotations

import warnings

import cv2
import numpy as np

from .template import IDX49

#: the iris' diameter over the eye's width (corner to corner) that the measure looks for; adult irises
#: are 11-12 mm across in an eye opening of 28-30 mm
IRIS = 0.4

#: the eye width (px) every eye is resampled to before the iris is looked for
MEASURE_WIDTH = 40

#: per eye, the image's left one first: its six iBUG points (corner, upper lid 2, corner, lower lid 2)
EYES68 = (tuple(range(36, 42)), tuple(range(42, 48)))

#: the same eyes' six points among the paper's 49 fiducials
EYES49 = tuple(tuple(IDX49.index(i) for i in eye) for eye in EYES68)

#: an eye whose lids are closer than this share of its width shows too little iris to measure
MIN_OPENING = 0.12

#: the largest offset given to a texture (eye widths, along and across): beyond it the white in front of
#: the iris is squeezed to nothing
MAX_SHIFT = (0.3, 0.1)


def _frame(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(origin, unit axis from the first corner to the second, width) of an eye's six points (6, 2)."""
    first, second = points[0], points[3]
    width = float(np.linalg.norm(second - first))
    return (first + second) / 2, (second - first) / max(width, 1e-9), width


def _opening(points: np.ndarray) -> float:
    """How far apart an eye's lids are (the mean of its two facing pairs), over its width."""
    return float(np.mean([np.linalg.norm(points[1] - points[5]), np.linalg.norm(points[2] - points[4])])
                 / max(_frame(points)[2], 1e-9))


def iris_offset(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(2,) the iris' centre (u along the eye, v across it) from the middle of its corners, in eye widths,
    of the eye whose six iBUG points (6, 2) are ``points`` in ``image`` (h, w, 3) or (h, w); NaN when the
    eye is too closed (MIN_OPENING), outside the image or not found."""
    points = np.asarray(points, np.float64)
    if not np.isfinite(points).all() or _opening(points) < MIN_OPENING:
        return np.full(2, np.nan)
    origin, axis, width = _frame(points)
    if width < 3:
        return np.full(2, np.nan)
    scale = MEASURE_WIDTH / width
    # a crop about the eye, rotated so its corners lie on a row and resampled to MEASURE_WIDTH px wide
    side = int(MEASURE_WIDTH * 1.5)
    rotation = np.array([[axis[0], axis[1]], [-axis[1], axis[0]]]) * scale
    affine = np.hstack([rotation, (side / 2 - rotation @ origin)[:, None]])
    grey = image if image.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    crop = cv2.warpAffine(grey.astype(np.float32), affine, (side, side), flags=cv2.INTER_AREA,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=-1)
    inside = np.zeros((side, side), np.uint8)
    cv2.fillPoly(inside, [np.round((points @ rotation.T + affine[:, 2]) * 4).astype(np.int32)], 1, shift=2)
    inside = inside.astype(bool) & (crop >= 0)
    if inside.sum() < 10:
        return np.full(2, np.nan)
    values = crop[inside]
    dark = np.where(inside, np.maximum(np.percentile(values, 90) - crop, 0), 0).astype(np.float32)
    radius = IRIS * MEASURE_WIDTH / 2
    disc = np.zeros((2 * int(radius) + 3,) * 2, np.float32)
    cv2.circle(disc, (disc.shape[1] // 2,) * 2, int(round(radius)), 1.0, -1)
    score = cv2.filter2D(dark, -1, disc / disc.sum(), borderType=cv2.BORDER_CONSTANT)
    score[~inside] = -np.inf  # the iris' centre lies in the opening
    y, x = np.unravel_index(int(np.argmax(score)), score.shape)
    if not np.isfinite(score[y, x]) or score[y, x] <= 0:
        return np.full(2, np.nan)
    padded = np.pad(score, 1, constant_values=-np.inf)  # a neighbour off the crop never wins
    refined = []
    for here, before, after in ((x, padded[y + 1, x], padded[y + 1, x + 2]), (y, padded[y, x + 1], padded[y + 2, x + 1])):
        curve = before - 2 * score[y, x] + after  # a parabola through the best and its two neighbours
        refined.append(here + (0.5 * (before - after) / curve if np.isfinite(curve) and curve < 0 else 0.0))
    return (np.array(refined) - side / 2) / MEASURE_WIDTH


def iris_offsets(image: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
    """(2, 2) :func:`iris_offset` of both eyes (the image's left one first) of a face whose 68 iBUG
    landmarks are ``landmarks``."""
    landmarks = np.asarray(landmarks, np.float64)
    return np.stack([iris_offset(image, landmarks[list(eye)]) for eye in EYES68])


def gaze_shift(offsets: np.ndarray) -> np.ndarray:
    """(T, 2, 2) a clip's iris offsets (:func:`iris_offsets` of every frame) from its own usual gaze (their
    median over the clip), both eyes moved together by the mean of the two (an eye that was not measured
    takes the other's), clipped to MAX_SHIFT; 0 in a frame where neither eye was measured. Frame by frame,
    not smoothed in time: the eyes glance for two or three frames, and a mean over time halved those
    glances on the fringe clip (σ 0.75 frames: gain 0.72; a running median of three, 0.76; none, 0.995)."""
    offsets = np.asarray(offsets, np.float64)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an eye or a frame never measured: NaN, then 0
        moved = np.nanmean(offsets - np.nanmedian(offsets, axis=0), axis=1)  # (T, 2): the two eyes together
    moved = np.clip(np.nan_to_num(moved), -np.asarray(MAX_SHIFT), MAX_SHIFT)
    return np.repeat(moved[:, None], 2, axis=1)


def _slid(length: int, middle: float, move: float, rigid: float) -> np.ndarray:
    """(length,) where each texel of a run of ``length`` texels takes its value from when the ``rigid``
    texels either side of the run's ``middle`` (a position in it) move by ``move`` as one, the iris, and
    the run's two ends stay: linear in between, never outside the run (the move and the rigid part are
    made smaller where the run is too short for them)."""
    x = np.arange(length, dtype=np.float64)
    a, b = -0.5, length - 0.5
    c = float(np.clip(middle, a + 1, b - 1))
    m = float(np.clip(move, a + 1 - c, b - 1 - c))  # the middle stays in the run
    r = max(min(rigid, c + m - a - 1, b - c - m - 1, c - a - 1, b - c - 1), 0.0)
    return np.interp(x, [a, c - r + m, c + r + m, b], [a, c - r, c + r, b])


def _runs(row: np.ndarray) -> list[tuple[int, int]]:
    """[(start, stop)] of the runs of True in a 1-D bool array."""
    edges = np.flatnonzero(np.diff(np.r_[0, row.astype(np.int8), 0]))
    return list(zip(edges[::2], edges[1::2]))


def look(texture: np.ndarray, neutral: np.ndarray, shift: np.ndarray, *, grow: int = 1) -> np.ndarray:
    """``texture`` (H, W, 3) at the geometry of the fiducials ``neutral`` (49, 2), the inside of each eye's
    opening (the polygon of its six fiducials grown by ``grow`` texels) slid by ``shift`` (2, 2): per eye,
    along and across it, in its widths (:func:`gaze_shift`). Each row of the opening is slid along itself
    (:func:`_slid`: the iris about the eye's middle moves by the shift along as one, the row's two ends, at
    the lids and corners, stay), then each column across, inside the opening less a texel at its edge (its
    lashes stay); a texel only ever takes another of the opening's."""
    shift = np.asarray(shift, np.float64)
    if not np.any(shift):
        return texture
    out = np.array(texture, np.float32)
    h, w = out.shape[:2]
    for eye, (du, dv) in zip(EYES49, shift):
        points = np.asarray(neutral, np.float64)[list(eye)]
        if (du == 0 and dv == 0) or not np.isfinite(points).all():
            continue
        origin, _, width = _frame(points)
        opening = np.zeros((h, w), np.uint8)
        cv2.fillPoly(opening, [np.round(points * 4).astype(np.int32)], 1, shift=2)
        if grow:
            opening = cv2.dilate(opening, np.ones((2 * grow + 1, 2 * grow + 1), np.uint8))
        inside = opening > 0
        for move, middle, along_rows in ((du * width, origin[0], True), (dv * width, origin[1], False)):
            if move == 0:
                continue
            mx, my = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
            # across, the opening less its edge: the lashes along the lids are not stretched down into it
            lines = inside if along_rows else (cv2.erode(opening, np.ones((3, 3), np.uint8)) > 0).T
            target = mx if along_rows else my.T
            for k in np.flatnonzero(lines.any(axis=1)):
                for a, b in _runs(lines[k]):
                    target[k, a:b] = a + _slid(b - a, middle - a, move, IRIS * width / 2)
            out = cv2.remap(out, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out
