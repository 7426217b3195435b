"""The mouth's interior: B's own teeth and dark cavity, drawn where B's lips part.

A depth-map surface cannot open: when the driver's lips part, B's mesh stretches the skin of
the lip line across the gap. Instead, the gap between B's inner lips is filled with the inside
of B's mouth as B's own open-mouth photos show it (issue 12, "lips that part").

**The interior image.** Each photo's inner lips (iBUG 60-67) are two curves from one inner
corner to the other: the upper lip through 60, 61, 62, 63, 64 and the lower through 60, 67, 66,
65, 64. A point of the gap has a position ``s`` along the mouth (the five nodes at s = 0, 1/4,
1/2, 3/4, 1, linear between them) and a height ``t`` from the upper curve (0) to the lower (1).
B's photos whose inner lips are over ``min_gap`` inter-ocular distances apart are resampled on
that (s, t) rectangle (:func:`sample`), and the per-pixel median of ``count`` of them is the
interior image: the widest (:func:`widest`; in a celebrity's collection mostly laughs, teeth and
tongue), or those darkest in the gap's middle (:func:`darkest`: the cavity of an open mouth).

**Teeth or cavity, as the driver shows them.** A round "O" shows the dark of the mouth, a smile
its teeth. B keeps both interiors, and each frame weighs them by how much the driver's own mouth
shows teeth there (:func:`teeth_share`: the grey of its gap's middle over that of its nose, so
that the light does not count; :func:`for_frame`).

**Or the driver's own (``mouth_choice: frame``, not B's).** Celebrity photos at ~100 px between
the ears rarely show teeth sharply, and some collections not at all (Bush's widest photos are
shouts, dark inside). The driver's video shows A's mouth interior in every frame, at the frame's
resolution, in the frame's light, moving as the lips do: :func:`from_frame` takes it between A's
inner lips as :func:`sample` does B's, a little inside the lip points (``inset``) so that A's lips,
which dlib's inner-lip points sit on, do not line the gap.

**Drawing it.** In each output frame the renderer projects B's inner-lip curves as the frame's
mesh moved them, rounds them into one smooth outline of the opening (:func:`rounded`: an "O" is
drawn round, not as a hexagon with pointed corners), and maps the interior image into the gap
between them, quad by quad between the outline's points (two affine triangles each), over the face
it rendered: the stretched skin is hidden, the lips themselves stay (they lie outside the gap).
Closed lips leave a gap of no area, so nothing is drawn. (The interior image itself is taken
between the photos' straight curves: taken between rounded ones, it lowered dlib's mouth-opening
gain on Bush <- Obama 0.82 -> 0.76; docs/expression.md.)

**A jaw that drops further than B's photos.** The interior shows teeth and cavity at the size of
the photos' gap. Where the frame's lips are further apart than that, the teeth keep their size
along the lips and the middle of the opening turns to B's darkest interior colour
(:func:`depth`, :func:`cavity`), rather than the teeth stretching with the jaw. The driver's own
interior, whose teeth are sharp, keeps its rows at their size both ways (:func:`_rows_fitted`): where it
has a dark gap (:func:`dark_row`), it is parted there and more of that dark fills what the jaw dropped
further, so upper teeth that fill A's gap stay on B's upper lip, not split between both lips with B's
dark between.

**The lower lip's shadow.** :func:`from_frame` takes the driver's interior a little inside A's lips, so
the dark band where A's lower lip meets the teeth or tongue is left out with the lip, and a tongue
drawn from it meets B's lower lip pink on pink: the lip is lost in it. :func:`draw` puts that band
back along B's lower lip (``shadow``; :func:`lower_lip_shadow`).
"""

from __future__ import annotations

import cv2
import numpy as np

from .template import IDX49
from .texture import to_grey

#: the iBUG-68 indices of the inner lips: upper curve and lower curve, corner to corner
UPPER = (60, 61, 62, 63, 64)
LOWER = (60, 67, 66, 65, 64)
#: (rows, cols) of the interior image
SIZE = (32, 64)
#: points of the opening's outline from one inner-lip node to the next (:func:`rounded`)
STEPS = 4


def lip_curves(landmarks68: np.ndarray) -> np.ndarray:
    """(2, 5, 2): the upper and lower inner-lip curves (x, y) of 68 landmarks."""
    lm = np.asarray(landmarks68, np.float64)
    return np.stack([lm[list(UPPER)], lm[list(LOWER)]])


def lip_gap(landmarks68: np.ndarray, per_iod: bool = True) -> np.ndarray:
    """(n,) the mean distance between the inner lips (61-67, 62-66, 63-65) over the inter-ocular
    distance (in the landmarks' own units with ``per_iod`` False), for landmarks (n, 68, 2); NaN where
    a point is missing."""
    lm = np.asarray(landmarks68, np.float64)
    gap = np.linalg.norm(lm[:, [61, 62, 63]] - lm[:, [67, 66, 65]], axis=2).mean(axis=1)
    if not per_iod:
        return gap
    return gap / np.linalg.norm(lm[:, 36:42].mean(axis=1) - lm[:, 42:48].mean(axis=1), axis=1)


#: texels at least between B's upper and lower inner-lip curves where the mesh is read for them
#: (:func:`apart`)
LIP_SIDES = 2.0


def apart(curves: np.ndarray, least: float = LIP_SIDES) -> np.ndarray:
    """(2, 5, 2) B's inner-lip ``curves`` (canonical texels) with their three middle pairs moved apart, each
    lip by half the shortfall, to at least ``least`` texels: where the renderer reads the mesh for the
    opening's outline. The driver's meshes part the lips as a step at the line where they meet
    (:func:`persona.plugins.face.mesh.lip_split`), which B's meshes carry, smoothed, across the line; a
    puppet whose photos never part their lips has curves a texel or less apart, both on that line, and the
    lower curve read there moved with the upper lip: the opening was drawn a sliver (a V of teeth under a
    stretched pink lower lip where the driver laughed). Curves further apart are as they are."""
    out = np.array(curves, np.float64)
    short = np.maximum(least - (out[1, 1:-1, 1] - out[0, 1:-1, 1]), 0.0) / 2
    out[0, 1:-1, 1] -= short
    out[1, 1:-1, 1] += short
    return out


def outer_corners(fiducials49: np.ndarray) -> np.ndarray:
    """(2, 2): the mouth's outer corners (iBUG 48, 54), left first, among the paper's 49 fiducials (49, 2)."""
    return np.asarray(fiducials49)[[IDX49.index(48), IDX49.index(54)]]


def corner_inset(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """(2,): how far in from the mouth's outer corners (iBUG 48, 54) its inner corners (60, 64) are,
    along the line between the outer corners, as fractions of the mouth's width (left, right).

    ``outer`` and ``inner`` are (2, 2) or (n, 2, 2) points (x, y), the left corner first; the result
    has their leading shape. A round "O" brings the inner corners in further than a smile does."""
    outer, inner = np.asarray(outer, np.float64), np.asarray(inner, np.float64)
    axis = outer[..., 1, :] - outer[..., 0, :]
    length2 = np.sum(axis ** 2, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):  # corners that coincide: NaN
        left = np.sum((inner[..., 0, :] - outer[..., 0, :]) * axis, axis=-1) / length2
        right = np.sum((outer[..., 1, :] - inner[..., 1, :]) * axis, axis=-1) / length2
    return np.stack([left, right], axis=-1)


def landmark_inset(landmarks68: np.ndarray) -> np.ndarray:
    """:func:`corner_inset` of 68 landmarks (..., 68, 2) -> (..., 2)."""
    lm = np.asarray(landmarks68, np.float64)
    return corner_inset(lm[..., [48, 54], :], lm[..., [60, 64], :])


def frame_insets(puppet_neutral: np.ndarray, driver_neutral: np.ndarray, frame68: np.ndarray) -> np.ndarray | None:
    """(2,) where B's inner-lip corners go in one frame (``mouth_corners: driver``): B's neutral
    :func:`corner_inset` plus how far the driver's own inner corners have moved from theirs in this
    frame (its 68 landmarks ``frame68``), as the paper moves B's fiducials by A's offsets. The mesh
    moves only the 49 fiducials, which leave out the inner corners: left to the mesh they stay near
    the outer corners, and a round "O" is drawn as wide as the lips. None where a point is missing."""
    insets = np.asarray(puppet_neutral) + landmark_inset(frame68) - np.asarray(driver_neutral)
    return insets if np.all(np.isfinite(insets)) else None


def place_corners(curves: np.ndarray, outer: np.ndarray, inset: np.ndarray) -> np.ndarray:
    """The inner-lip ``curves`` (2, nodes, 2) with their corner nodes moved along the mouth, so that
    they lie ``inset`` (2,) of the way in from the ``outer`` corners (2, 2) (:func:`corner_inset`);
    across the mouth each keeps its own offset from its outer corner. The insets are held between 0
    and 0.45 (an inner corner stays inside its outer one and short of the middle)."""
    curves, outer = np.array(curves, np.float64), np.asarray(outer, np.float64)
    inset = np.clip(np.asarray(inset, np.float64), 0.0, 0.45)
    axis = outer[1] - outer[0]
    unit = axis / np.linalg.norm(axis)
    for node, start, sign, share in ((0, outer[0], 1.0, inset[0]), (-1, outer[1], -1.0, inset[1])):
        offset = curves[0, node] - start
        across = offset - np.dot(offset, unit) * unit
        curves[:, node] = start + sign * share * axis + across
    return curves


def along(curves: np.ndarray) -> float:
    """How long a mouth is along its inner-lip ``curves`` (2, n, 2): per step between nodes the longer of
    the two lips', summed (in the curves' units)."""
    return float(np.linalg.norm(np.diff(curves, axis=1), axis=2).max(axis=0).sum())


def rounded(curves: np.ndarray, steps: int = STEPS) -> np.ndarray:
    """(2, (nodes - 1) · steps + 1, 2): the inner-lip curves (2, nodes, 2) as one closed, smooth outline
    of the opening, sampled ``steps`` times from each node to the next.

    The nodes, once round the opening (the upper lip from corner to corner, the lower lip back), are
    joined by a uniform Catmull-Rom spline, which passes through each of them. The lips' polygon
    would give an "O" six corners; the spline gives it a round outline, and at the mouth's two
    corners the upper and lower curves meet with one tangent. Lips that touch keep a gap of no area
    (the loop doubles back on itself)."""
    curves = np.asarray(curves, np.float64)
    loop = np.concatenate([curves[0], curves[1, -2:0:-1]])  # corner, upper lip, corner, lower lip back
    m = len(loop)
    t = np.arange(steps)[:, None] / steps
    basis = 0.5 * np.stack([-t ** 3 + 2 * t ** 2 - t, 3 * t ** 3 - 5 * t ** 2 + 2,
                            -3 * t ** 3 + 4 * t ** 2 + t, t ** 3 - t ** 2])  # (4, steps, 1)
    segment = lambda k: sum(basis[j] * loop[(k - 1 + j) % m] for j in range(4))  # from node k to k + 1
    nodes = curves.shape[1]
    upper = np.concatenate([segment(k) for k in range(nodes - 1)] + [curves[0, -1:]])
    lower = np.concatenate([segment(k) for k in range(nodes - 1, m)] + [curves[0, :1]])[::-1]
    return np.stack([upper, lower])


def _positions(curves: np.ndarray, size: tuple[int, int] = SIZE, inset: float = 0.0) -> np.ndarray:
    """(rows, cols, 2): the image point (x, y) of every (s, t) cell of the interior rectangle, t from
    ``inset`` to 1 - ``inset`` of the way from the upper curve to the lower."""
    rows, cols = size
    s = np.linspace(0, 1, cols) * (curves.shape[1] - 1)
    k = np.minimum(np.floor(s).astype(int), curves.shape[1] - 2)
    a = (s - k)[:, None]
    upper = curves[0, k] * (1 - a) + curves[0, k + 1] * a  # (cols, 2)
    lower = curves[1, k] * (1 - a) + curves[1, k + 1] * a
    t = np.linspace(inset, 1 - inset, rows)[:, None, None]
    return upper[None] * (1 - t) + lower[None] * t


def sample(rgb: np.ndarray, landmarks68: np.ndarray, inset: float = 0.0,
           size: tuple[int, int] = SIZE) -> np.ndarray:
    """(rows, cols, 3) float32: one photo ``rgb`` (h, w, 3) between its inner lips (its 68 landmarks
    in its own pixels), resampled on the (s, t) rectangle of ``size`` (its rows from ``inset`` of the gap
    below the upper lip to as far above the lower)."""
    at = _positions(lip_curves(landmarks68), size, inset=inset).astype(np.float32)
    return cv2.remap(np.asarray(rgb, np.float32), at[..., 0], at[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


def from_frame(rgb: np.ndarray, landmarks68: np.ndarray, *, inset: float = 0.15, max_inset: float | None = 0.03,
               min_gap: float = 0.04, min_px: float = 2.0) -> tuple[np.ndarray, float] | None:
    """The driver's own mouth interior in one frame (``mouth_choice: frame``) and how far apart A's lips
    are (frame px; :func:`draw` fits the interior's rows to B's gap from it); None where A's lips are under
    ``min_gap`` inter-ocular distances or ``min_px`` px apart, or a point is missing (the renderer then
    draws no interior: B's own lips close over the gap).

    The interior is A's frame between A's inner lips (:func:`sample`) at the frame's own resolution (a
    row a pixel of the height it spans, a column a pixel along the lips; :data:`SIZE` at least), from
    ``inset`` of the gap inside each lip, but at most ``max_inset`` inter-ocular distances (None: no cap).
    The inset leaves out A's lips, on whose edge dlib's points sit; it is capped because that edge is as
    sharp however far the mouth opens, and a share of a wide gap cut off the rows of teeth that hang from
    each lip. The gap given is the whole of A's, not the part the sample spans: where B's lips are as far
    apart as A's the sample fills B's gap from lip to lip, as A's teeth do, where the rows left out went in
    as dark at its darkest row (a dark bar between a smile's teeth). dlib's inner-lip points on closed lips
    lie a little apart, by about as much at any resolution: a gap of a few px at HD is still lips, and drawn
    as the interior it showed as a pale line or a patch of A's lip colour across B's mouth."""
    lm = np.asarray(landmarks68, np.float64)
    if not np.isfinite(lm).all():
        return None
    gap, per_iod = lip_gap(lm[None], per_iod=False)[0], lip_gap(lm[None])[0]
    if not (gap >= min_px and per_iod >= min_gap):
        return None
    if max_inset is not None:
        inset = min(inset, max_inset / per_iod)  # max_inset IODs as a share of a gap of per_iod IODs
    length = along(lip_curves(lm))
    size = (max(SIZE[0], int(np.ceil(gap * (1 - 2 * inset)))), max(SIZE[1], int(np.ceil(length))))
    return sample(rgb, lm, inset, size), float(gap)


def interior(samples) -> np.ndarray | None:
    """The interior image (rows, cols, 3) float32 0-255: the per-pixel median of photos' gaps, each
    resampled on the (s, t) rectangle (:func:`sample`); None for none. Choose them with :func:`widest`
    or :func:`darkest`."""
    samples = list(samples)
    return np.median(np.stack(samples), axis=0).astype(np.float32) if samples else None


def widest(landmarks68: np.ndarray, count: int, min_gap: float) -> np.ndarray:
    """Indices of the (at most) ``count`` photos whose inner lips are furthest apart, widest first,
    among those open by ``min_gap`` inter-ocular distances."""
    gap = lip_gap(landmarks68)
    gap = np.where(np.isfinite(gap), gap, -np.inf)
    order = np.argsort(-gap, kind="stable")
    return order[gap[order] >= min_gap][:count]


def _middle_half(sample: np.ndarray) -> np.ndarray:
    """The middle half of the mouth's length of a :func:`sample` (its columns), away from the corners,
    which are dark anyway."""
    cols = sample.shape[1]
    return sample[:, cols // 4: cols - cols // 4]


def _middle_grey(sample: np.ndarray) -> float:
    """The mean grey (0-1) of a gap's middle, away from the lips: the middle half of the mouth's
    length and the middle third of the gap's height of a :func:`sample`."""
    rows = sample.shape[0]
    return float(to_grey(_middle_half(sample)[rows // 3: rows - rows // 3]).mean())


def darkest(samples: np.ndarray, count: int) -> np.ndarray:
    """Indices of the (at most) ``count`` of the photos' gaps ``samples`` (n, rows, cols, 3), each
    from :func:`sample`, whose middle (:func:`_middle_grey`) is darkest, darkest first: photos that
    show the cavity of an open mouth, not a row of teeth or a tongue."""
    return np.argsort([_middle_grey(sample) for sample in samples], kind="stable")[:count]


def teeth_share(rgb: np.ndarray, landmarks68: np.ndarray, *, cavity: float = 0.2, teeth: float = 0.7,
                min_gap: float = 2.0) -> float:
    """How much a frame's open mouth shows teeth rather than the dark cavity, in [0, 1]: the grey of
    its gap's middle (:func:`_middle_grey`) over the median grey of its nose below the bridge (iBUG
    29-33, between the nostrils 31 and 35), 0 at ``cavity`` or less, 1 at ``teeth`` or more, smooth
    between. 0 where its inner lips are under ``min_gap`` px apart, or a point is missing: where closed
    lips meet, a line of B's cavity, the dark between them."""
    lm = np.asarray(landmarks68, np.float64)
    if not np.isfinite(lm).all() or lip_gap(lm[None], per_iod=False)[0] < min_gap:
        return 0.0
    h, w = rgb.shape[:2]
    x0, x1 = int(np.clip(lm[31, 0], 0, w - 1)), int(np.clip(lm[35, 0], 1, w))
    y0, y1 = int(np.clip(lm[29, 1], 0, h - 1)), int(np.clip(lm[33, 1], 1, h))
    nose = np.asarray(rgb, np.float32)[y0:max(y1, y0 + 1), x0:max(x1, x0 + 1)]
    ratio = _middle_grey(sample(rgb, lm)) / max(float(np.median(to_grey(nose))), 1e-3)
    t = float(np.clip((ratio - cavity) / (teeth - cavity), 0, 1))
    return t * t * (3 - 2 * t)


def for_frame(teeth: np.ndarray, cavity: np.ndarray, gaps: tuple[float, float], share: float):
    """The interior image and its photos' gap for a frame whose mouth shows ``share`` teeth
    (:func:`teeth_share`): the ``teeth`` interior (from the widest photos) and the ``cavity`` one
    (from the darkest), and their ``gaps``, weighed by it."""
    return teeth * share + cavity * (1 - share), gaps[0] * share + gaps[1] * (1 - share)


def cavity(image: np.ndarray) -> np.ndarray:
    """(3,) the colour of B's dark cavity: the mean of the interior ``image``'s darkest 5 %."""
    grey = to_grey(image)
    return image[grey <= np.percentile(grey, 5)].mean(axis=0)


def depth(opening: np.ndarray, gap: float) -> np.ndarray:
    """(h, w) float32 in [0, 1]: how far into the cavity each pixel of the ``opening`` (h, w, uint8,
    nonzero inside) lies, for photos whose lips were ``gap`` px apart: 0 within ``gap / 2`` of the lips
    (the teeth and tongue at the size B's photos show them), 1 from ``3 gap / 4`` in, smooth between.
    An opening no taller than the photos' has no depth anywhere (nor any opening, for a gap of 0)."""
    if not gap > 0:
        return np.zeros(opening.shape, np.float32)
    inside = cv2.distanceTransform(np.pad(opening, 1), cv2.DIST_L2, 5)[1:-1, 1:-1] - 0.5  # from the pixel's centre
    t = np.clip((inside - gap / 2) / (gap / 4), 0, 1)
    return (t * t * (3 - 2 * t)).astype(np.float32)


#: sub-pixels a side with which :func:`_area` measures a triangle's cover of each pixel
SUPERSAMPLE = 4


def _area(triangle: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(h, w) float32 in [0, 1]: the share of each pixel (centres at integer coordinates) that the
    ``triangle`` (3, 2) covers, counted on a grid of SUPERSAMPLE² sub-pixels (over the triangle's
    bounding box only: zero elsewhere)."""
    n, out = SUPERSAMPLE, np.zeros(shape, np.float32)
    triangle = np.asarray(triangle, np.float64)
    x0, y0 = np.maximum(np.floor(triangle.min(axis=0)).astype(int) - 1, 0)
    x1, y1 = np.minimum(np.ceil(triangle.max(axis=0)).astype(int) + 2, (shape[1], shape[0]))
    if x1 <= x0 or y1 <= y0:
        return out
    fine = np.zeros(((y1 - y0) * n, (x1 - x0) * n), np.uint8)
    corners = (triangle - [x0, y0] + 0.5) * n - 0.5  # pixel edges onto sub-pixel edges
    cv2.fillConvexPoly(fine, np.round(corners * 16).astype(np.int32), 255, cv2.LINE_8, shift=4)
    out[y0:y1, x0:x1] = cv2.resize(fine, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA) / np.float32(255)
    return out


#: a row of the driver's interior darker than this share of its median row's is a gap to part it at
#: (:func:`dark_row`)
DARK_GAP = 0.5


def dark_row(image: np.ndarray, share: float = DARK_GAP) -> int | None:
    """The row of the interior ``image`` at which to part it where the lips open further than its own:
    its darkest (the mean grey of its :func:`_middle_half`),
    when no brighter than ``share`` of its median row: the dark between two rows of teeth, or below
    upper teeth that fill the gap. None where no row is that dark: teeth closed edge to edge, a
    tongue, or a mouth dark throughout have no gap to part."""
    middle = to_grey(_middle_half(image)).mean(axis=1)
    row = int(np.argmin(middle))
    return row if middle[row] <= share * np.median(middle) else None


def _rows_fitted(image: np.ndarray, height: float, gap: float, split: int | None) -> np.ndarray:
    """The interior ``image`` for lips ``height`` px apart where its own were ``gap`` apart, its rows at
    their own size: the upper teeth hang from the upper lip and the lower ones sit on the lower.
    Closer, only its rows nearest each lip are kept, its middle left out: a mouth that opens less shows
    less between them. Further, and parted at the row ``split`` (:func:`dark_row`), rows of that row's
    colour (its middle half's mean, across the whole row: a teeth's edge that is not level would
    otherwise run down as streaks) go below it: a jaw that drops further shows more of the dark, and
    the teeth keep their size and their lip. Further with no row to part at, the image as it is
    (:func:`draw` stretches it and turns the middle to the cavity by :func:`depth`)."""
    rows, cols = image.shape[:2]
    if not 0 < gap < np.inf:
        return image
    want = int(round(rows * min(height / gap, 4.0)))
    if want == rows or (want > rows and split is None):
        return image
    if want < rows:
        keep = max(want, 2)
        return np.concatenate([image[:(keep + 1) // 2], image[rows - keep // 2:]])
    colour = _middle_half(image)[split].mean(axis=0)
    dark = np.broadcast_to(colour, (want - rows, cols, image.shape[2]))
    return np.concatenate([image[:split + 1], dark, image[split + 1:]]).astype(image.dtype)


#: how far up from the lower lip its shadow reaches (:func:`lower_lip_shadow`), as a share of the gap's height
SHADOW_REACH = 0.1


def lower_lip_shadow(rows: int, strength: float) -> np.ndarray:
    """(rows,) float32: what each of the ``rows`` of a quad of the opening (top to bottom) is multiplied by
    for the lower lip's shadow of ``strength`` (0: none): 1 - strength · exp(-u / SHADOW_REACH) at a row
    whose centre is a share u of the gap's height above the lower lip. The shadow scales with the gap: a
    gap one row tall, its row half of it above the lip, is barely touched (0.3 % at strength 0.5); a tall
    one gets a dark band about a tenth of its height."""
    up = (rows - np.arange(rows) - 0.5) / rows  # each row's centre above the lower lip, as a share of the gap
    return (1 - strength * np.exp(-up / SHADOW_REACH)).astype(np.float32)


def draw(out: np.ndarray, face: np.ndarray, image: np.ndarray, curves: np.ndarray,
         gap: float = np.inf, keep_rows: bool = False, shadow: float = 0.0) -> np.ndarray:
    """Draw the interior ``image`` into the frame ``out`` (h, w, 3) uint8, in place, between the
    frame's inner-lip ``curves`` (2, 5, 2), :func:`rounded`, where the rendered ``face`` mask (h, w)
    float is. ``gap``: how far apart (frame px) the lips of the photos the interior comes from were;
    where the frame's lips are further apart, the middle of the opening turns to B's :func:`cavity`
    colour by its :func:`depth`, as a jaw that drops shows the dark between the teeth (inf: never).
    ``keep_rows``: the image's rows keep their size, the rows nearest each lip hanging from it
    (:func:`_rows_fitted`; the driver's own interior, whose teeth are sharp): where the lips are
    closer the image's middle is left out; where further and it has a dark gap (:func:`dark_row`),
    it is parted there and more of that dark goes between, rather than the whole image squeezed or
    stretched into the gap (and no :func:`depth` is drawn). ``shadow``: with ``keep_rows``, the strength of
    the lower lip's shadow drawn along it (:func:`lower_lip_shadow`; 0: none). Returns how much of each
    pixel of ``out`` (h, w) float32 the interior covers.

    Quad by quad between the outline's points, the image is first averaged down (area resampling) to
    the quad's own height and the mouth's length in pixels, so that a gap a pixel or two tall shows
    the interior's mean colour along it rather than whichever of its rows (teeth, cavity) the
    sampling happens to hit; each quad covers a pixel by the share of its area inside (:func:`_area`),
    which also makes the gap's soft edge."""
    h, w = out.shape[:2]
    drawn = np.zeros((h, w), np.float32)
    curves = np.asarray(curves, np.float64)
    if not np.all(np.isfinite(curves)):
        return drawn
    curves = rounded(curves)
    lo = np.floor(curves.reshape(-1, 2).min(axis=0)).astype(int) - 2
    hi = np.ceil(curves.reshape(-1, 2).max(axis=0)).astype(int) + 3
    x0, y0 = max(lo[0], 0), max(lo[1], 0)
    x1, y1 = min(hi[0], w), min(hi[1], h)
    if x1 <= x0 or y1 <= y0:
        return drawn
    rows, cols = image.shape[:2]
    nodes = curves.shape[1]
    split = dark_row(image) if keep_rows else None
    length = along(curves)  # px
    cols_px = int(np.clip(np.ceil(length), 2, cols))
    paint = np.zeros((y1 - y0, x1 - x0, 3), np.float32)
    cover = np.zeros((y1 - y0, x1 - x0), np.float32)
    offset = np.array([x0, y0], np.float64)
    for k in range(nodes - 1):
        height = np.linalg.norm(curves[1, k:k + 2] - curves[0, k:k + 2], axis=1).mean()
        rows_px = int(np.clip(np.ceil(height), 1, rows))
        kept = _rows_fitted(image, height, gap, split) if keep_rows else image
        small = kept if (rows_px, cols_px) == kept.shape[:2] else cv2.resize(kept, (cols_px, rows_px),
                                                                             interpolation=cv2.INTER_AREA)
        if keep_rows and shadow > 0:
            small = small * lower_lip_shadow(rows_px, shadow)[:, None, None]
        left, right = k * (cols_px - 1) / (nodes - 1), (k + 1) * (cols_px - 1) / (nodes - 1)
        top, bottom = -0.5, rows_px - 0.5  # the image's pixel edges onto the lips
        quad_dst = np.array([curves[0, k], curves[0, k + 1], curves[1, k + 1], curves[1, k]]) - offset
        quad_src = np.array([[left, top], [right, top], [right, bottom], [left, bottom]])
        for tri in ((0, 1, 2), (0, 2, 3)):
            dst, src = quad_dst[list(tri)], quad_src[list(tri)]
            (ax, ay), (bx, by) = dst[1] - dst[0], dst[2] - dst[0]
            if abs(ax * by - ay * bx) < 1e-3:  # no area: closed lips
                continue
            matrix = cv2.getAffineTransform(src.astype(np.float32), dst.astype(np.float32))
            warped = cv2.warpAffine(small, matrix, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR,
                                    borderMode=cv2.BORDER_REPLICATE)
            new = np.minimum(_area(dst, cover.shape), 1 - cover)
            paint += warped * new[..., None]
            cover += new
    if not cover.any():
        return drawn
    colour = paint / np.maximum(cover, 1e-6)[..., None]
    if np.isfinite(gap) and split is None:  # the photos' gap known: the dark between the teeth where the jaw dropped further
        dark = depth((cover > 0.5).astype(np.uint8), gap)[..., None]
        colour = colour * (1 - dark) + cavity(image) * dark
    drawn[y0:y1, x0:x1] = alpha = cover * face[y0:y1, x0:x1]
    region, alpha = out[y0:y1, x0:x1].astype(np.float32), alpha[..., None]
    out[y0:y1, x0:x1] = np.clip(colour * alpha + region * (1 - alpha), 0, 255).round().astype(np.uint8)
    return drawn
