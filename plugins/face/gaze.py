"""Gaze: where the iris sits in the eye's opening, measured in a frame and given to B's texture.

Not in the paper. The drive's texture keeps B's neutral geometry and takes its eyes from B's photos
whose lids are as far apart as the target's (``eye_sigma``); nothing in the 49 fiducials says where
the eyes look, so B's irises stayed where B's photos mostly had them, looking ahead, while the driver
looked left, right, up or down.

Measured (:func:`iris_offsets`): in each eye's opening (the polygon of its six iBUG points) the iris is
the disc about ``IRIS`` eye widths across that holds the most iris and the least white: each texel of the
opening it covers counts its darkness (the opening's brightest tenth less the grey) less ``IRIS_SHARE`` of
the opening's dark end, so white counts against a disc and the lids and skin beyond the opening count
nothing. A disc half under a lid is found where the iris is, not pushed back into the opening; it must
have ``IRIS_SEEN`` as much of itself in the opening as the disc with the most. The best disc's place is
refined to a fraction of a pixel by a parabola through its neighbours. Its offset is taken from the middle
of the eye's two corners, along the line from corner to corner (u, positive towards the image's right) and
across it (v, positive down), in eye widths: a measure that does not depend on the size of the face or its
roll.

Given (:func:`look`): in B's texture (at B's neutral fiducials) each eye turns under its lids by the
driver's offset from the driver's own usual gaze (the clip's median), times B's eye width: the iris, found
there as above, moves as one disc, the white it leaves is filled in from the white beside it, and it is
drawn only inside the eye's opening, so that the lids cut an iris gone to a corner as they cut a real one.
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

#: an eye whose lids are closer than this share of its width shows too little iris to measure: dlib's lids of a
#: shut eye stay 0.12-0.16 of its width apart (the expressions woman's blinks), an open eye's are 0.25-0.45
MIN_OPENING = 0.16

#: a texel of the opening counts for a disc as the iris by its darkness less this share of the opening's dark
#: end (its 95th percentile), against it below: a disc is pulled onto the iris and kept off the white. Irises
#: drawn up to 0.15 eye widths up and down in eyes 14-60 px wide are found 0.88-0.94 times as far, where a disc
#: that sums darkness alone, its centre kept in the opening, finds 0.39-0.58 (tests/plugins/test_gaze.py)
IRIS_SHARE = 0.4

#: the least share of a disc that must lie in the eye's opening for its centre to be taken, over the share the
#: disc with the most of itself there has: an iris half under a lid is found, but the lashes of a narrowed eye,
#: beyond its opening, are not taken for it
IRIS_SEEN = 0.5

#: the largest offset given to a texture (eye widths, along and across): beyond it the white in front of
#: the iris is squeezed to nothing
MAX_SHIFT = (0.3, 0.1)

#: each eye turns its own way where the spread of a clip's turn of one eye against the other is at least this
#: many times the measure's noise (:func:`turns_apart`): the HD clips stand at 5.1-6.5, the clips of small or
#: light eyes at 2.3 or less. Below it the noise turned B's eyes apart at random, and the gaze along the eye lost
#: 0.15-0.35 of its gain on the frontal man, the Obama address and the MEAD actor
APART_SNR = 3.0

#: the furthest two eyes turn apart along the eye (eye widths, the image's right one's shift less the left one's)
#: from where they usually are in a clip. Eyes converge on what is near and can cross, but do not part beyond
#: looking far: from looking at a camera half a metre away, each turns out about 4°, 0.03 eye widths. A larger
#: parting is the measure's error: a glare on glasses over one iris (the man with glasses looking up: 0.16-0.32),
#: a wink or an eye half shut (the expressions woman: 0.10-0.33)
MAX_PART = 0.1


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
    crop = cv2.warpAffine(_grey_near(image, origin, side / scale + 2), affine, (side, side), flags=cv2.INTER_AREA,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=-1)
    inside = np.zeros((side, side), np.uint8)
    cv2.fillPoly(inside, [np.round((points @ rotation.T + affine[:, 2]) * 4).astype(np.int32)], 1, shift=2)
    inside = inside.astype(bool) & (crop >= 0)
    if inside.sum() < 10:
        return np.full(2, np.nan)
    darkest, brightest = np.percentile(crop[inside], [5, 90])
    dark = np.where(inside, np.maximum(brightest - crop, 0), 0).astype(np.float32)
    radius = IRIS * MEASURE_WIDTH / 2
    disc = np.zeros((2 * int(radius) + 3,) * 2, np.float32)
    cv2.circle(disc, (disc.shape[1] // 2,) * 2, int(round(radius)), 1.0, -1)
    disc /= disc.sum()
    # each disc's mean darkness and share in the opening, both in one pass
    both = cv2.filter2D(np.dstack([dark, inside.astype(np.float32)]), -1, disc, borderType=cv2.BORDER_CONSTANT)
    summed, seen = both[..., 0], both[..., 1]
    threshold = IRIS_SHARE * max(brightest - darkest, 0)  # the opening's dark end: its darkness' 95th percentile
    score = summed - threshold * seen
    score[seen < IRIS_SEEN * seen.max()] = -np.inf  # the iris' centre may lie under a lid, not beyond it
    y, x = np.unravel_index(int(np.argmax(score)), score.shape)
    if not np.isfinite(score[y, x]) or score[y, x] <= 0:
        return np.full(2, np.nan)
    padded = np.pad(score, 1, constant_values=-np.inf)  # a neighbour off the crop never wins
    refined = []
    for here, before, after in ((x, padded[y + 1, x], padded[y + 1, x + 2]), (y, padded[y, x + 1], padded[y + 2, x + 1])):
        curve = before - 2 * score[y, x] + after  # a parabola through the best and its two neighbours
        refined.append(here + (0.5 * (before - after) / curve if np.isfinite(curve) and curve < 0 else 0.0))
    return (np.array(refined) - side / 2) / MEASURE_WIDTH


def _grey_near(image: np.ndarray, centre: np.ndarray, reach: float) -> np.ndarray:
    """(h, w) float32: ``image`` (h, w, 3) or (h, w) as grey within ``reach`` px of ``centre`` (x, y), 0 beyond,
    where the eye's crop never reads (converting all of an HD frame for each eye was most of the measure)."""
    h, w = image.shape[:2]
    x0, y0 = np.clip(np.floor(centre - reach).astype(int), 0, [w, h])
    x1, y1 = np.clip(np.ceil(centre + reach).astype(int) + 1, 0, [w, h])
    grey = np.zeros((h, w), np.float32)
    part = image[y0:y1, x0:x1]
    if part.size:
        grey[y0:y1, x0:x1] = part if part.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(part), cv2.COLOR_RGB2GRAY)
    return grey


def iris_offsets(image: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
    """(2, 2) :func:`iris_offset` of both eyes (the image's left one first) of a face whose 68 iBUG
    landmarks are ``landmarks``."""
    landmarks = np.asarray(landmarks, np.float64)
    return np.stack([iris_offset(image, landmarks[list(eye)]) for eye in EYES68])


def photo_gazes(images: np.ndarray, neutral: np.ndarray) -> np.ndarray:
    """(n, 2) where each of B's photos ``images`` (n, H, W, 3), aligned to the fiducials ``neutral`` (49, 2),
    looks: the mean of its two irises' offsets (:func:`iris_offset`, along and across, eye widths), the one
    found where only one is; NaN where neither is (eyes shut or too narrow)."""
    points = [np.asarray(neutral, np.float64)[list(eye)] for eye in EYES49]
    offsets = np.array([[iris_offset(image, eye) for eye in points] for image in images]).reshape(-1, 2, 2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a photo with neither eye found: NaN
        return np.nanmean(offsets, axis=1)


def ahead(gazes: np.ndarray, sigma: float) -> np.ndarray:
    """(n,) in (0, 1]: how nearly each photo looks where the photos usually do, from their gazes (n, 2;
    :func:`photo_gazes`): exp(-d² / 2σ²), d (eye widths) the distance from their median gaze; 1 where a
    photo's irises were not found (a shut or narrowed eye, which its lids weigh)."""
    gazes = np.asarray(gazes, np.float64)
    d2 = np.sum((gazes - np.nanmedian(gazes, axis=0)) ** 2, axis=1)
    return np.where(np.isfinite(d2), np.exp(-np.nan_to_num(d2) / (2 * sigma ** 2)), 1.0)


def gaze_shift(offsets: np.ndarray) -> np.ndarray:
    """(T, 2, 2) a clip's iris offsets (:func:`iris_offsets` of every frame) from its own usual gaze, each eye's
    from its own (its median over the clip), clipped to MAX_SHIFT. The eyes turn apart, as they do when they look
    at something near or cross, where the clip's turn of one eye against the other stands out from the
    measure's noise (:func:`turns_apart`), and never part further than MAX_PART; elsewhere both turn by their
    mean. An eye not measured in a frame takes the other's shift; 0 in a frame where neither was. Frame by
    frame, not smoothed in time: the eyes glance for two or three frames, and a mean over time halved those
    glances on the fringe clip (σ 0.75 frames: gain 0.72; a running median of three, 0.76; none, 0.995).
    :func:`together` moves both eyes by their mean."""
    offsets = np.asarray(offsets, np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an eye never measured: NaN, then 0
        moved = offsets - np.nanmedian(offsets, axis=0)  # (T, 2 eyes, 2)
    own = turns_apart(moved[:, 1] - moved[:, 0])
    moved = np.where(np.isnan(moved), moved[:, ::-1], moved)  # an eye not seen: the other's
    moved = np.where(own, moved, together(moved))
    beyond = np.maximum(moved[:, 1, 0] - moved[:, 0, 0] - MAX_PART, 0) / 2  # parted further than eyes do
    moved[:, 0, 0] += beyond
    moved[:, 1, 0] -= beyond
    return np.clip(np.nan_to_num(moved), -np.asarray(MAX_SHIFT), MAX_SHIFT)


def spread_over_noise(values: np.ndarray) -> np.ndarray:
    """(k,) per column of a clip's measures ``values`` (T, k; a frame with a NaN left out): their spread (standard
    deviation) over the measure's noise frame by frame, read from the changes between consecutive frames (their
    median absolute deviation, over √2); inf where those changes do not spread at all, 0 with fewer than three
    frames."""
    values = np.asarray(values, np.float64)
    values = values[np.isfinite(values).all(axis=1)]
    if len(values) < 3:
        return np.zeros(values.shape[1])
    steps = np.diff(values, axis=0)
    noise = 1.4826 * np.median(np.abs(steps - np.median(steps, axis=0)), axis=0) / np.sqrt(2)
    spread = values.std(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(noise > 0, spread / noise, np.inf)


def turns_apart(apart: np.ndarray) -> np.ndarray:
    """(2,) along and across: whether a clip's turn of one eye against the other, ``apart`` (T, 2; NaN where an
    eye was not measured), stands out from the measure's noise, its spread at least APART_SNR times the noise
    frame by frame (:func:`spread_over_noise`); where it does not, the eyes turn together. Eyes turn apart slowly
    or hold a cross, where the measure of a small eye jumps from frame to frame. Along the eye the ratio is 5.1-6.5
    on the HD clips (the fringe woman, whose eyes converge; the expressions woman; the man with glasses) and at
    most 2.3 on the others (the MEAD actor's 256² clips, whose eyes are 25 px wide, the phone clip, the Obama
    address, the frontal man's light irises, the smiling man)."""
    return spread_over_noise(apart) >= APART_SNR


def together(shift: np.ndarray) -> np.ndarray:
    """(..., 2, 2) the gaze shifts of both eyes (:func:`gaze_shift`) replaced by their mean: the eyes move as
    one, never apart (the measure's noise in each eye is halved, a real turn of one eye against the other is
    lost)."""
    shift = np.asarray(shift, np.float64)
    return np.repeat(shift.mean(axis=-2, keepdims=True), 2, axis=-2)


#: what :func:`look` draws, as a version: a drive's frame textures record it and are made again when it changes
LOOK_VERSION = "8"

#: the disc moved as the iris (:func:`look`), over the iris the measure looks for, at least: it takes the iris' dark
#: rim and the blur around it along, so that none of it is left behind in the white; a texel beyond the iris'
#: own reach (:func:`_iris_radius`) where that is further
DISC = 1.2


def _axes(axis: np.ndarray) -> np.ndarray:
    """(2, 2): an eye's unit axis from corner to corner and the unit across it (down the face), as rows."""
    return np.stack([axis, [-axis[1], axis[0]]])


def _almond(points: np.ndarray, steps: int = 12, lower: float = 1.0) -> np.ndarray:
    """(2 steps, 2) the outline of an eye's opening through its six points (6, 2): each lid the cubic, along
    the eye's axis, through its two points and the corners, rather than the hexagon's straight sides, which
    cut off the lids' curve at the corners; the lower lid ``lower`` px further out, where dlib's points lie a
    little inside the white (the upper lid's are on its lashes)."""
    origin, axis, width = _frame(points)
    local = (np.asarray(points, np.float64) - origin) @ _axes(axis).T  # along, across
    u = np.linspace(local[0, 0], local[3, 0], steps)
    lids = [np.polyval(np.polyfit(local[idx, 0], local[idx, 1], 3), u) for idx in ([0, 1, 2, 3], [0, 5, 4, 3])]
    lids[1] = lids[1] + lower * np.sin(np.pi * (u - u[0]) / max(u[-1] - u[0], 1e-9))  # none at the corners
    outline = np.vstack([np.c_[u, lids[0]], np.c_[u[::-1], lids[1][::-1]]])
    return origin + outline @ _axes(axis)


def _coverage(shape: tuple[int, int], points: np.ndarray) -> np.ndarray:
    """(h, w) float32 in [0, 1]: the share of each texel inside the polygon ``points`` (x, y), antialiased
    (drawn 4 times finer and averaged down)."""
    fine = np.zeros((shape[0] * 4, shape[1] * 4), np.uint8)
    cv2.fillPoly(fine, [np.round((np.asarray(points) + 0.5) * 4 - 0.5).astype(np.int32)], 255)
    return cv2.resize(fine, shape[::-1], interpolation=cv2.INTER_AREA).astype(np.float32) / 255


def _disc(shape: tuple[int, int], centre: np.ndarray, radius: float) -> np.ndarray:
    """(h, w) float32 in [0, 1]: a disc of ``radius`` texels about ``centre`` (x, y), its edge a texel wide."""
    ys, xs = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float32)
    return np.clip(radius + 0.5 - np.hypot(xs - centre[0], ys - centre[1]), 0, 1)


#: how many times :func:`look` turns an eye, each time by what the measure of the last one still missed
PASSES = 3

#: the smallest shift (eye widths, along or across) :func:`look` measures and turns again: below it the
#: measure's own noise would move the iris from frame to frame
MEASURED_FROM = 0.05


#: where the iris ends (:func:`_iris_radius`): the first ring about its centre whose darkness is under this share
#: of its core's
IRIS_EDGE = 0.25

#: an iris whose edge :func:`_iris_radius` reads: its middle darker than the white by at least this share of the
#: white's grey (dark and brown irises 0.7-0.85 on the example puppets, the frontal man's light ones 0.3)
IRIS_DARK = 0.5


def _iris_radius(crop: np.ndarray, opening: np.ndarray, centre: np.ndarray, width: float) -> float:
    """How far (texels) the iris about ``centre`` (x, y) reaches in ``crop`` (h, w, 3), an eye ``width`` texels
    wide whose opening covers ``opening`` (h, w): the inner radius of the first one-texel ring, within the
    opening, whose darkness (the opening's brightest tenth less the grey, as :func:`iris_offset` measures it)
    falls under ``IRIS_EDGE`` of the iris' core's (its middle, half the iris the measure looks for). Irises
    differ, and a blend of photos whose irises sit in slightly different places widens one. Half of ``IRIS``
    eye widths (the measure's own) for a light iris (its middle darker than the white by less than
    ``IRIS_DARK`` of the white's grey) or where no such ring lies within 0.4 eye widths: there the edge does
    not show against the white, and a disc grown as wide as the eye would move its lids and lashes with it."""
    nominal = IRIS * width / 2
    grey, inside = crop.mean(axis=2), opening > 0.5
    ys, xs = np.mgrid[0:grey.shape[0], 0:grey.shape[1]]
    r = np.hypot(xs - centre[0], ys - centre[1])
    core = inside & (r < nominal / 2)
    if not core.any():
        return nominal
    white = np.percentile(grey[inside], 90)
    dark = white - grey
    if np.mean(dark[core]) < IRIS_DARK * white:  # a light iris: its edge does not show
        return nominal
    level = IRIS_EDGE * np.mean(dark[core])
    for k in range(int(nominal / 2), int(np.ceil(0.4 * width))):
        ring = inside & (r >= k) & (r < k + 1)
        if ring.any() and np.mean(dark[ring]) < level:
            return float(k)
    return nominal


def _turned(texture: np.ndarray, opening: np.ndarray, bare: np.ndarray, iris: np.ndarray,
            move: np.ndarray) -> np.ndarray:
    """``texture`` with the ``iris`` disc's texels (its weights, (h, w)) moved by ``move`` (x, y) over the eye
    without it (``bare``), inside the ``opening`` (its coverage of each texel, (h, w)) alone."""
    h, w = opening.shape
    to = np.float32([[1, 0, move[0]], [0, 1, move[1]]])
    moved = cv2.warpAffine(texture, to, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    alpha = cv2.warpAffine(iris * opening, to, (w, h), flags=cv2.INTER_LINEAR)[..., None]
    inside = opening[..., None]  # the eye changes only inside its opening, its edge in proportion
    return texture + inside * (bare * (1 - alpha) + moved * alpha - texture)


#: the share of an eye's opening around the iris, its brightest, that :func:`_white_behind` takes as the white:
#: the rest is lid, lashes, the pink inner corner and the lower lid's shadow
WHITE_SHARE = 0.5


def _white_behind(texture: np.ndarray, hole: np.ndarray, opening: np.ndarray) -> np.ndarray:
    """``texture`` with the texels of ``hole`` (h, w) bool filled, row by row, from the eye's white either side
    of it in the same row: the ``opening``'s texels outside the hole that are among its brightest
    (``WHITE_SHARE``), linear between the nearest on each side, the nearest one beyond the last. The white
    the iris leaves behind, without the lids', lashes' or inner corner's colour that filling from all around
    would bring into it (on an eye whose white shows only a few texels either side of the iris, a grey band
    the measure took for the iris). A row with no such texel (along a lid) is filled from the rest of the
    opening in it, so the lid's line stays; a row with none at all takes the nearest row's that had."""
    out = np.array(texture, np.float32)
    around = opening & ~hole
    grey = out.mean(axis=2)
    white = around & (grey >= np.percentile(grey[around], 100 * (1 - WHITE_SHARE))) if around.any() else around
    rows = np.flatnonzero(hole.any(axis=1))
    filled = []
    for y in rows:
        source = np.flatnonzero(white[y]) if white[y].any() else np.flatnonzero(around[y])
        if len(source):
            gap = np.flatnonzero(hole[y])
            for c in range(out.shape[2]):
                out[y, gap, c] = np.interp(gap, source, out[y, source, c])
            filled.append(y)
    for y in np.setdiff1d(rows, filled) if filled else ():
        gap = np.flatnonzero(hole[y])
        out[y, gap] = out[filled[int(np.argmin(np.abs(np.asarray(filled) - y)))], gap]
    return out


#: how far beyond an eye's points (in its widths) :func:`look` reads and changes the texture: past the measure's
#: crop (1.5 widths square about the eye's middle, turned with it) and the furthest an iris moves
EYE_MARGIN = 1.2


def look(texture: np.ndarray, neutral: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """``texture`` (H, W, 3) at the geometry of the fiducials ``neutral`` (49, 2) with each eye looking
    ``shift`` (2, 2) away from where it does: per eye, along and across it, in its widths (:func:`gaze_shift`).

    The eye turns under its lids: the iris, found in the texture (:func:`iris_offset`; the eye's middle where
    it cannot be) as a disc ``DISC`` times the measured iris across or a texel beyond where its darkness ends
    (:func:`_iris_radius`), whichever is wider, moves as one; the white it leaves is
    filled from the white either side of it (:func:`_white_behind`); and it is drawn again only inside the
    eye's opening (through its six fiducials, :func:`_almond`, antialiased), so that the lids cut an iris
    gone towards a corner or a lid as they cut a real one. What the measure then finds may have moved less
    than the iris (the lids hide part of it, as they hid part of the driver's), so an eye asked to look
    ``MEASURED_FROM`` or more away is measured and turned again by what is missing, up to ``PASSES`` times,
    the best kept, never further than 1.5 times what was asked; where the measure does not follow the iris
    (a light one, whose darkest disc is the lashes) it is turned once, as asked. The lids, the corners and
    the skin stay."""
    shift = np.asarray(shift, np.float64)
    if not np.any(shift):
        return texture
    out = np.array(texture, np.float32)
    for eye, wanted in zip(EYES49, shift):
        points = np.asarray(neutral, np.float64)[list(eye)]
        if not np.any(wanted) or not np.isfinite(points).all():
            continue
        out = _look_eye(out, points, np.asarray(wanted, np.float64))
    return out


def _look_eye(out: np.ndarray, points: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """:func:`look` of one eye, its six points ``points``: a copy of ``out`` (H, W, 3) with the eye turned, its
    texels changed in a crop about the eye (``EYE_MARGIN``) and read only there but by the measure."""
    origin, axis, width = _frame(points)
    frame = _axes(axis) * width  # rows: one eye width along it, and across (down)
    x0, y0 = np.maximum(np.floor(points.min(axis=0) - EYE_MARGIN * width), 0).astype(int)
    x1, y1 = np.ceil(points.max(axis=0) + EYE_MARGIN * width).astype(int) + 1
    corner, crop = np.array([x0, y0]), out[y0:y1, x0:x1]
    image = np.clip(out, 0, 255).round().astype(np.uint8)

    def measured(texels):
        """:func:`iris_offset` of the texture with the crop's texels ``texels``."""
        image[y0:y1, x0:x1] = np.clip(texels, 0, 255).round().astype(np.uint8)
        return iris_offset(image, points)

    found = measured(crop)
    start = np.nan_to_num(found)
    opening = _coverage(crop.shape[:2], _almond(points) - corner)
    centre = origin + start @ frame - corner
    reach = max(DISC * IRIS * width / 2, _iris_radius(crop, opening, centre, width) + 1)  # the iris and its rim
    iris = _disc(crop.shape[:2], centre, reach)
    bare = _white_behind(crop, cv2.dilate((iris * opening > 0).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0,
                         opening > 0.5)
    move, best, least = wanted, None, np.inf
    for _ in range(PASSES if np.abs(wanted).max() >= MEASURED_FROM and np.isfinite(found).all() else 1):
        turned = _turned(crop, opening, bare, iris, move @ frame)
        best = turned if best is None else best  # the first pass, as asked, unless a later one does better
        seen = measured(turned) - start
        if np.isnan(seen).any() or seen @ wanted < 0.5 * (wanted @ wanted):
            break  # a measure that does not follow the iris (a light iris, dark lashes): keep what was asked
        miss = wanted - seen
        if np.abs(miss).max() >= least:
            break
        best, least = turned, np.abs(miss).max()
        move = np.clip(move + miss, -1.5 * np.abs(wanted) - 0.02, 1.5 * np.abs(wanted) + 0.02)
    out = out.astype(best.dtype)  # a copy, in the turned texels' precision
    out[y0:y1, x0:x1] = best
    return out
