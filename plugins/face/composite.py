"""B's rendered face in A's frame: a multi-band composite, and a measure of its seam.

Pasting the render through its soft mask (``face α + frame (1 - α)``) leaves a visible edge
wherever B's skin tone or lighting differs from A's around it: the step is as sharp as the mask's
few-pixel feather. Multi-band blending (Burt & Adelson 1983) blends each band of a Laplacian
pyramid through the mask's Gaussian pyramid at the same level: fine detail switches from A to B
over a pixel or two, while the low frequencies (skin tone, lighting) cross over a width that
grows with the band, so the colour step is spread over a good part of the face instead of the
feather. Each level's weights come from the mask eroded by half that level's pixel, so the
coarse transitions lie inside B's face: without that, B's tone spilled as a light halo into A's
hair. Inside the face B's own detail and, away from the edge, B's own tone remain.

Multi-band blending spreads a difference of tone over the face's edge; it does not remove it, and
B's skin under A's lighting is rarely A's colour. ``match_lighting`` removes it first: on the face's
outer ring (a fifth of its smaller side deep, ``LIGHT_BAND``) it compares B's render with A's frame
under it (A's skin, lit by A's scene), and fits to their ratio a per-channel gain that is a plane in
log colour (A's mean tone and A's gradient of light across the face), robustly, where the frame looks
like A's skin. B's face times that gain has A's colour and light, so little step is left to blend at
its edge; B's shading, detail and the differences of tone between B's regions remain.

Fitted on each frame alone, the gain jumps wherever hair, glasses or a turned head change what lies
under B's edge for a frame or two: the whole face brightens and darkens (on a driver with glasses
and head motion, the face's mean colour changed 1.8 grey levels from frame to frame, median, 7.9 at
the 95th percentile, against 1.1 and 3.5 in A's own frames there). A drive therefore fits each
frame's plane (``light_plane``), makes them steady in time (``steady_light``: a median over the
frames around, then a Gaussian), and applies those (``apply_light``).

A's hair that falls inside the top of B's face (a fringe) is left in front of it
(``hair_in_front``): B's face would otherwise cut a clean hairline through it. So is the background
beside A's cheek where A's head is turned or narrower than B's.

The render's ``rgb`` is the face's own colour across its soft edge (see
``persona.plugins.kinds.Rendered``); ``alone`` shows it over grey as ``puppet.mp4`` does.

The seam is measured on a ring along the mask's edge (``seam``): the colour step across it (the
mean colour a few pixels inside minus that a few pixels outside, against the same step in A's own
frame) and the gradient energy on it over that of A's frame there (1 = as smooth as the frame).
"""

from __future__ import annotations

import cv2
import numpy as np


def _bounds(selected: np.ndarray) -> tuple[int, int, int, int] | None:
    """(y0, y1, x0, x1): the bounding box of the True pixels of ``selected`` (h, w), None for none."""
    x, y, w, h = cv2.boundingRect(np.asarray(selected, np.uint8))
    return (y, y + h, x, x + w) if w else None


def mask_box(selected: np.ndarray, margin: int = 0) -> tuple[slice, slice] | None:
    """The bounding box of the True pixels of ``selected`` (h, w) widened by ``margin`` px and cut to
    the image, as slices; None for none. Work on a face's pixels need not touch the rest of an HD frame."""
    bounds = _bounds(selected)
    if bounds is None:
        return None
    (y0, y1, x0, x1), (h, w) = bounds, np.shape(selected)[:2]
    return slice(max(y0 - margin, 0), min(y1 + margin, h)), slice(max(x0 - margin, 0), min(x1 + margin, w))


def levels_for(mask: np.ndarray) -> int:
    """Pyramid levels for a face mask: until the coarsest level's pixel is about a quarter of the
    face's smaller side (at least 1)."""
    bounds = _bounds(mask > 0.5)
    if bounds is None:
        return 1
    y0, y1, x0, x1 = bounds
    return int(max(1, np.floor(np.log2(min(y1 - y0, x1 - x0) / 4))))


def _level_weights(alpha: np.ndarray, levels: int) -> list[np.ndarray]:
    """The blending weight of each pyramid level 0..levels: the mask eroded by half the level's
    pixel (2^k / 2 px), then reduced to the level's size. The coarse levels' transitions lie inside
    B's face, so B's tone does not spill as a halo into A's hair and background.

    From level 2 on, the erosion is done two levels above the level's own (the mask reduced k - 2
    times, eroded there by 2 px, then reduced twice more): at full size the coarse levels' discs
    (up to 129 px across on an HD face) cost most of the composite's time, and the weights differ
    by a few hundredths where the mask's edge is steep (the composite by at most 6 levels, 0.06 on
    average, on a 1600-px frame)."""
    reduced = [alpha]
    for _ in range(levels - 2):
        reduced.append(cv2.pyrDown(reduced[-1]))
    weights = []
    for k in range(levels + 1):
        above = max(k - 2, 0)
        r = 2 ** k // 2 // 2 ** above
        w = reduced[above]
        if r:
            w = cv2.erode(w, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
        for _ in range(k - above):
            w = cv2.pyrDown(w)
        weights.append(w)
    return weights


def multiband(face: np.ndarray, frame: np.ndarray, alpha: np.ndarray, levels: int | None = None) -> np.ndarray:
    """The composite (h, w, 3) uint8 of ``face`` over ``frame`` (both (h, w, 3) uint8) with the soft
    mask ``alpha`` (h, w) in [0, 1]. Outside the mask the face image is replaced by the frame (the
    render's background must not bleed into the low bands). ``levels``: by default
    :func:`levels_for`.

    Only a box about the face is blended: farther than ``4 · 2^levels`` px from the mask no band of
    the face reaches (the coarsest pixel and the pyramid's 5-tap kernels, twice over), and the
    frame is returned as it is there. On an HD frame with a face of a few hundred pixels this is
    most of the frame left alone."""
    alpha = np.clip(np.asarray(alpha, np.float32), 0, 1)
    if levels is None:
        levels = levels_for(alpha)
    bounds = _bounds(alpha > 0)
    out = np.array(frame, dtype=np.uint8, copy=True)
    if bounds is None:
        return out
    step, reach = 2 ** levels, 4 * 2 ** levels
    y0, y1, x0, x1 = bounds
    top, left = max(y0 - reach, 0), max(x0 - reach, 0)
    top, left = top - top % step, left - left % step  # on the coarsest level's grid, as the whole frame's pyramid
    box = np.s_[top:y1 + reach, left:x1 + reach]
    out[box] = _pyramid_blend(np.asarray(face)[box], out[box], alpha[box], levels)
    return out


def _pyramid_blend(face: np.ndarray, frame: np.ndarray, alpha: np.ndarray, levels: int) -> np.ndarray:
    """:func:`multiband` on the whole of the images given. Each band k of the blend is the face's
    (``alpha`` over the frame) weighted by the level's weight w_k plus the frame's by 1 - w_k, that is
    the frame's band plus w_k times the band of their difference (the pyramid is linear): so the
    result is the frame plus the difference's pyramid, weighted level by level and collapsed. One
    pyramid instead of two."""
    bottom = np.asarray(frame, np.float32)
    diff = (np.asarray(face, np.float32) - bottom) * alpha[..., None]
    bands = []
    for _ in range(levels):
        small = cv2.pyrDown(diff)
        bands.append(diff - cv2.pyrUp(small, dstsize=(diff.shape[1], diff.shape[0])))
        diff = small
    weights = _level_weights(alpha, levels)
    out = diff * weights[levels][..., None]
    for k in reversed(range(levels)):
        out = cv2.pyrUp(out, dstsize=(bands[k].shape[1], bands[k].shape[0])) + bands[k] * weights[k][..., None]
    return np.clip(bottom + out, 0, 255).round().astype(np.uint8)


#: the depth inside B's face, as a share of its smaller side, over which :func:`light_plane` compares B's render
#: with A's frame: a fifth, the face's outer ring, cheeks and forehead included. The plane's gradient is set by
#: that ring; on a ring of 6 % it was the light of the face's rim alone (the fringe woman's self-reenactment
#: then lit her face twice as steeply from one side as her real frames show, docs/composite.md)
LIGHT_BAND = 0.2


def _robust_plane(xy: np.ndarray, values: np.ndarray, weight: np.ndarray, *, delta: float = 0.1,
                  rounds: int = 4) -> np.ndarray:
    """Coefficients (3, c) of the plane ``[1, x, y] @ coef`` that fits ``values`` (m, c) at points
    ``xy`` (m, 2) with prior weights ``weight`` (m,), by iteratively reweighted least squares with
    Huber's weights (``delta`` in the values' units): a few outliers (hair, a collar) do not tilt it."""
    design = np.column_stack([np.ones(len(xy)), xy])
    robust = np.ones_like(values)
    for _ in range(rounds):
        weighted = (weight[:, None] * robust).T[:, None, :] * design.T[None]  # (c, 3, m): rows by weight
        lhs = weighted @ design + 1e-9 * np.eye(3)  # normal equations, all channels at once
        coef = np.linalg.solve(lhs, weighted @ values.T[:, :, None])[..., 0].T  # (3, c)
        residual = np.abs(values - design @ coef)
        robust = np.minimum(1.0, delta / np.maximum(residual, 1e-12))
    return coef


def _skin_likeness(logc: np.ndarray, skin: np.ndarray, tint: float, shade: float) -> np.ndarray:
    """How much each pixel of ``logc`` (..., 3), log colour, looks like ``skin`` (3,) or (..., 3), the log
    colour of a face's skin (there: :func:`skin_light`): a Gaussian in chromaticity (σ ``tint``) and in
    brightness (σ ``shade``) about the skin's."""
    brightness = logc.mean(axis=-1, keepdims=True)
    level = np.mean(skin, axis=-1, keepdims=True)
    off = (np.sum((logc - brightness - (skin - level)) ** 2, axis=-1) / tint ** 2
           + (brightness[..., 0] - level[..., 0]) ** 2 / shade ** 2)
    return np.exp(-off / 2)


#: about how many pixels of a face's middle :func:`skin_light` fits its plane to (a grid over the middle; at most
#: four times as many): plenty for three coefficients a channel, where the middle of a face at 720p has a hundred
#: thousand
SKIN_SAMPLES = 1000


def skin_light(image: np.ndarray, middle: np.ndarray, rows: np.ndarray, cols: np.ndarray, *, tint: float = 0.1,
               shade: float = 0.5) -> np.ndarray:
    """(m, 3): a face's skin in its own light at the pixels (``rows``, ``cols``), from ``image`` (h, w, 3) under the
    face's ``middle`` (h, w) bool: its log colour per channel as a plane over the image's pixels, fitted by
    :func:`_robust_plane` to a grid of the middle's pixels (:data:`SKIN_SAMPLES`), each weighted first by how
    like the middle's median colour it is (twice as loose in tint as the skin tests): the eyes, brows, nostrils
    and mouth count little.

    One colour for the whole face is the skin of an evenly lit face. Lit by a window on one side and by lamps
    on the other, the skin's tint changes by 0.1-0.2 across the face, and the skin tests (σ 0.1) took the lit
    side for hair: the phone man's forehead stayed in front of B's face (docs/composite.md)."""
    step = max(1, int(np.sqrt(np.count_nonzero(middle) / SKIN_SAMPLES)))
    ys, xs = (index * step for index in np.nonzero(middle[::step, ::step]))
    values = np.log1p(np.asarray(image)[ys, xs].astype(np.float64))
    prior = _skin_likeness(values, np.median(values, axis=0), 2 * tint, shade)
    coef = _robust_plane(np.column_stack([xs, ys]).astype(np.float64), values, prior)
    return np.column_stack([np.ones(len(rows)), cols, rows]) @ coef


def match_lighting(face: np.ndarray, frame: np.ndarray, alpha: np.ndarray, *, lighting: float = 1.0,
                   tone: float = 1.0, tone_reach: float = 0.5, band: float = LIGHT_BAND, max_gain: float = 2.0,
                   tint: float = 0.1, shade: float = 0.5) -> np.ndarray:
    """``face`` (h, w, 3) uint8 with its colour and light matched to ``frame`` at the edge of the mask
    ``alpha`` (h, w) in [0, 1] (see the module's docstring).

    The gain is a plane in log colour per channel (a mean and a gradient of light across the face),
    fitted robustly to the ratio of A's frame to B's render on a band inside the edge, so it
    varies slowly and leaves B's detail and shading alone. Only where A's frame under B's edge looks
    like A's skin there (the frame under B's middle, carried across the face in A's light: :func:`skin_light`),
    and B's render like B's, does the band count, so that A's hair, collar or background there cannot darken
    or tint B's edge: tint is the tolerance (σ) of its chromaticity
    (log colour minus its channels' mean), shade that of its brightness (the mean log colour), loose
    so that a shadowed cheek still counts.

    lighting: how much of the gain is applied (0: none); tone: how much of the difference of mean
    colour between A's skin and B's is taken (1: all, so no step is left at the edge; 0: B's mean
    skin tone kept and only A's gradient of light matched, the multi-band blend spreads the rest);
    band: width of the band, as a fraction of the face's smaller side (at least 2 px; ``LIGHT_BAND``);
    max_gain: the largest factor (and 1/factor the smallest) by which a channel may be scaled anywhere.
    Outside the mask the face is returned unchanged (the composite takes the frame there)."""
    if lighting <= 0:
        return face
    plane = light_plane(face, frame, alpha, band=band, tint=tint, shade=shade)
    return apply_light(face, alpha, plane, lighting=lighting, tone=tone, tone_reach=tone_reach, max_gain=max_gain)


def light_plane(face: np.ndarray, frame: np.ndarray, alpha: np.ndarray, *, band: float = LIGHT_BAND,
                tint: float = 0.1, shade: float = 0.5) -> np.ndarray:
    """(4, 3): :func:`match_lighting`'s gain in log colour, per channel (columns), as a plane over the
    bounding box of the mask: its value at the box's top left corner, its change across the box's width
    and down its height; and its mean along the band it was fitted on (rows). All NaN when there is
    nothing to match (no mask, no band, nothing like skin under B's edge)."""
    nothing = np.full((4, 3), np.nan)
    inside = (np.asarray(alpha) > 0.5).astype(np.uint8)
    bounds = _bounds(inside)
    if bounds is None:
        return nothing
    y0, y1, x0, x1 = bounds
    width = max(2.0, band * min(y1 - y0, x1 - x0))
    box = np.s_[y0:y1, x0:x1]
    # the fit needs no more than a few thousand samples: at a scale where a pixel is 3 % of the face's smaller side
    # (coarser, a pixel astride hair and skin is neither, passes for a darker skin and tilts the plane)
    q = max(1.0, 0.03 * min(y1 - y0, x1 - x0))
    small = (max(1, round((x1 - x0) / q)), max(1, round((y1 - y0) / q)))
    shrink = lambda img: cv2.resize(img, small, interpolation=cv2.INTER_AREA)  # noqa: E731
    depth = cv2.distanceTransform((shrink(inside[box].astype(np.float32)) > 0.5).astype(np.uint8), cv2.DIST_L2, 5)
    ring = (depth > 0.5) & (depth <= 0.5 + width / q)
    if not ring.any():
        return nothing
    frame_a, face_b = (shrink(np.asarray(image)[box].astype(np.float32)) for image in (frame, face))
    a, b = np.log1p(frame_a), np.log1p(face_b)
    middle = depth > 4  # A's and B's skin: the colours under B's middle, deeper than 12 % of the face's side
    centre = middle if middle.any() else ring
    rows, cols = np.nonzero(ring)
    weight = np.ones(len(rows))
    for image, logc in ((frame_a, a), (face_b, b)):  # A's frame like A's skin there, B's render like B's
        skin = skin_light(image, centre, rows, cols, tint=tint, shade=shade)
        weight *= _skin_likeness(logc[ring], skin, tint, shade)
    if weight.sum() < 1e-3:  # nothing like skin under B's edge: nothing to match
        return nothing
    across = q * np.array([small[0], small[1]], np.float64)  # the shrunk box's width and height, in px
    xy = np.column_stack([cols, rows]) * q / across  # the band's points, the box's width and height 1
    coef = _robust_plane(xy, (a - b)[ring], weight)
    edge = coef[0] + np.average(xy, axis=0, weights=weight) @ coef[1:]  # the mean gain along the edge
    coef[1:] *= np.array([x1 - x0, y1 - y0])[:, None] / across[:, None]  # per the box's own width, height
    return np.vstack([coef, edge])


def apply_light(face: np.ndarray, alpha: np.ndarray, plane: np.ndarray, *, lighting: float = 1.0,
                tone: float = 1.0, tone_reach: float = 0.5, max_gain: float = 2.0) -> np.ndarray:
    """``face`` times the gain exp(lighting · ``plane``) (:func:`light_plane`), less (1 - ``tone``)
    of its mean along the edge (B's own mean tone kept), each channel's factor within 1 / ``max_gain``
    .. ``max_gain``, where the mask ``alpha`` is; unchanged where the plane is NaN or there is no mask.

    ``tone_reach`` > 0: ``tone`` is what the face's middle takes; at the mask's edge the face takes all of
    A's tone (no step there), and the share falls from all to ``tone`` as a smoothstep of the depth inside
    the mask, reaching ``tone`` at ``tone_reach`` times the face's smaller side (0.5: the face's middle)."""
    bounds = _bounds(np.asarray(alpha) > 0.5)
    if lighting <= 0 or bounds is None or not np.all(np.isfinite(plane)):
        return face
    edge, plane = np.asarray(plane[3], np.float64), np.array(plane[:3], np.float64)
    y0, y1, x0, x1 = bounds
    box = np.s_[y0:y1, x0:x1]
    # exp(lighting · clip(plane)) = clip(exp(lighting · plane)), and the exponential of a plane is the
    # product of a column's and a row's: no exponential of the whole box
    gx = np.arange(x1 - x0, dtype=np.float64)[None, :, None] / (x1 - x0)
    gy = np.arange(y1 - y0, dtype=np.float64)[:, None, None] / (y1 - y0)
    bound = max_gain ** lighting
    gain = np.exp(lighting * (plane[0] + gy * plane[2])).astype(np.float32) * np.exp(lighting * gx * plane[1]).astype(np.float32)
    if tone < 1:  # B's own mean tone: that part of the gain along the edge left out, all over or inside
        kept = np.float32(1 - tone)
        if tone_reach > 0:
            depth = cv2.distanceTransform((np.asarray(alpha)[box] > 0.5).astype(np.uint8), cv2.DIST_L2, 5)
            t = np.clip(depth / (tone_reach * min(y1 - y0, x1 - x0)), 0, 1)
            kept = kept * (t * t * (3 - 2 * t))[..., None]
        gain = gain * np.exp(-lighting * kept * edge.astype(np.float32))
    gain = np.clip(gain, 1 / bound, bound)
    matched = np.clip((np.asarray(face)[box].astype(np.float32) + 1) * gain - 1, 0, 255).round().astype(np.uint8)
    out = np.array(face, copy=True)
    out[box] = np.where((np.asarray(alpha)[box] > 0)[..., None], matched, out[box])
    return out


def steady_light(planes: np.ndarray, sigma: float) -> np.ndarray:
    """The light planes (T, 4, 3) of consecutive frames (:func:`light_plane`; NaN where a frame has
    none) made steady in time: each the median of the frames within 2σ, then a Gaussian (σ frames)
    average of those, both over the frames that have a plane. A fit thrown by hair, glasses or a hand
    under B's edge for a frame or two is outvoted; A's light changing over a second is followed. A
    frame without a plane of its own takes its neighbours'. σ 0: the planes as they are."""
    planes = np.asarray(planes, np.float64)
    if sigma <= 0 or len(planes) == 0:
        return planes
    radius = int(np.ceil(2 * sigma))
    flat = planes.reshape(len(planes), -1)
    ok = np.all(np.isfinite(flat), axis=1)
    median = np.full_like(flat, np.nan)
    for t in range(len(flat)):
        near = ok[max(t - radius, 0):t + radius + 1]
        if near.any():
            median[t] = np.median(flat[max(t - radius, 0):t + radius + 1][near], axis=0)
    have = np.all(np.isfinite(median), axis=1)
    weights = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    out = np.full_like(flat, np.nan)
    for t in range(len(flat)):
        lo, hi = max(t - radius, 0), min(t + radius + 1, len(flat))
        w = weights[lo - t + radius:hi - t + radius] * have[lo:hi]
        if w.sum() > 0:
            out[t] = w @ np.nan_to_num(median[lo:hi]) / w.sum()
    return out.reshape(planes.shape)


#: A's eyes and brows by their iBUG landmarks, and how far each one's hull is grown (times its width sideways,
#: half that up and down): an eye by half its width, so that its corners, lids and lashes are in and the brow
#: above is not; a brow by a fifth, so that its hairs above and beyond its points are in
EYES = ((slice(36, 42), slice(42, 48)), 0.5)
BROWS = ((slice(17, 22), slice(22, 27)), 0.2)


def features_of(points: np.ndarray | None, shape: tuple[int, int], features=EYES) -> np.ndarray:
    """(h, w) bool of an image ``shape``: the face's eyes (:data:`EYES`) or brows (:data:`BROWS`) by its iBUG
    landmarks ``points`` (68, 2), each the hull of its points grown as ``features`` says; nothing for one
    with a missing point, or without points."""
    out = np.zeros(shape[:2], bool)
    if points is None:
        return out
    groups, grow = features
    for group in groups:
        p = np.asarray(points, np.float64)[group]
        if not np.all(np.isfinite(p)):
            continue
        rx = max(1, int(round(grow * np.ptp(p[:, 0]))))
        ry = max(1, int(round(grow * np.ptp(p[:, 0]) / 2)))
        p = np.round(p)
        # drawn and grown in a box about the feature, not over the whole frame (an HD composite's every frame)
        lo = np.maximum(p.min(axis=0).astype(int) - (rx, ry), 0)
        hi = np.minimum(p.max(axis=0).astype(int) + (rx, ry) + 1, (shape[1], shape[0]))
        if np.any(hi <= lo):
            continue
        one = np.zeros((hi[1] - lo[1], hi[0] - lo[0]), np.uint8)
        cv2.fillConvexPoly(one, cv2.convexHull((p - lo).astype(np.int32)), 1)
        grown = cv2.dilate(one, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rx + 1, 2 * ry + 1)))
        out[lo[1]:hi[1], lo[0]:hi[0]] |= grown.astype(bool)
    return out


def edge_not_skin(image: np.ndarray, alpha: np.ndarray, *, reach: float = 0.12, chin: float = 35.0,
                  tint: float = 0.1, shade: float = 0.5, spared: np.ndarray | None = None) -> np.ndarray:
    """(h, w) in [0, 1]: how far ``image`` (h, w, 3) is from the skin of the face it shows, near the edge of the
    face's mask ``alpha`` (h, w) in [0, 1], where what is not skin comes in from beyond that edge: hair, a
    fringe, the background beside a turned cheek.

    The skin is the face's middle in its own light (:func:`skin_light`; deeper than ``reach`` of the face's
    smaller side) and a pixel's likeness to it that of :func:`match_lighting` (under 0.1: all; over 0.5: none).
    It counts only
    - within ``reach`` (a fraction of the face's smaller side) of the mask's edge;
    - all round the face but the sector of the chin: the edge within ``chin`` degrees of straight down from
      the mask's centre (a jaw, a chin, a beard and the collar below), fading in over the next 20 degrees;
    - where what is not skin reaches in from beyond the edge (:func:`_reaching_in`): a mole, stubble or the
      shadow of a dimple in the band is the face's own;
    - never within ``spared`` ((h, w) bool)."""
    alpha = np.asarray(alpha, np.float32)
    inside = (alpha > 0.5).astype(np.uint8)
    out = np.zeros(alpha.shape, np.float32)
    bounds = _bounds(inside)
    if bounds is None:
        return out
    y0, y1, x0, x1 = bounds
    side = min(y1 - y0, x1 - x0)
    depth = cv2.distanceTransform(inside[y0:y1, x0:x1], cv2.DIST_L2, 5)
    centre = depth > reach * side
    if not centre.any():
        return out
    ys, xs = np.nonzero((alpha[y0:y1, x0:x1] > 0) & (depth <= reach * side))  # the edge band
    m = cv2.moments(inside[y0:y1, x0:x1], binaryImage=True)
    down = np.degrees(np.arctan2(np.abs(xs - m["m10"] / m["m00"]), ys - m["m01"] / m["m00"]))  # 0: straight down
    beside = np.clip((down - chin) / 20, 0, 1).astype(np.float32)  # 0 in the chin's sector
    a = np.asarray(image)[y0:y1, x0:x1]
    skin = skin_light(a, centre, ys, xs, tint=tint, shade=shade)
    not_skin = np.clip((0.5 - _skin_likeness(np.log1p(a[ys, xs].astype(np.float32)), skin, tint, shade)) / 0.4, 0, 1)
    seen = np.zeros(centre.shape, bool)  # what is not skin in the whole band, chin's sector too
    seen[ys, xs] = not_skin > 0
    reaching = _reaching_in(seen, inside[y0:y1, x0:x1] == 0)[ys, xs]
    keep = (beside > 0) & reaching
    out[y0 + ys[keep], x0 + xs[keep]] = not_skin[keep] * beside[keep]  # 0 off the band
    if spared is not None:
        out[spared] = 0
    return out


def hair_in_front(face: np.ndarray, frame: np.ndarray, alpha: np.ndarray, *, reach: float = 0.12,
                  chin: float = 35.0, tint: float = 0.1, shade: float = 0.5,
                  eyes: np.ndarray | None = None, brows: np.ndarray | None = None) -> np.ndarray:
    """How much of A's frame stays in front of B's face (h, w) in [0, 1]: what is not A's skin inside
    the edge of B's mask (:func:`edge_not_skin` of A's frame within B's ``alpha``): A's hair that falls over
    it (a fringe, strands at the temples) and, where A's head is turned or narrower than B's, the background
    beside A's cheek.

    It counts whatever B's render shows there: B's own hair, which B's texture keeps where B's photos all had
    it (a fringe, strands at the temples, a face from one video), lies behind A's hair as B's skin does.
    - All round the face but the chin's sector: B's cheek drawn over the wall beside a turned head showed as
      a soft band; A's collar or the shadow under A's chin is left to B's jaw and chin.
    - Never within A's ``eyes`` ((h, w) bool, :func:`features_of`): their lashes and corners are dark and not
      skin, but not in front of B's face either (they showed as a smudge beside B's eye where A's face is
      narrower than B's).
    - Within A's ``brows`` ((h, w) bool), only where B's render is B's skin (as :func:`match_lighting` judges
      it): B's own brow is drawn where A's is, and a brow's end that A's hair or glasses join to the edge cut
      B's brow short (dlib then took the composite for A more often).
    It is softened over a pixel."""
    out = edge_not_skin(frame, alpha, reach=reach, chin=chin, tint=tint, shade=shade, spared=eyes)
    bounds = _bounds(np.asarray(alpha) > 0.5)
    if bounds is None:
        return out
    y0, y1, x0, x1 = bounds
    box = np.s_[y0:y1, x0:x1]
    if brows is not None:
        kept = out[box]  # a view: what is kept within the box
        over = brows[box] & (kept > 0)
        if over.any():  # B's skin is looked for only where something is kept within A's brows
            depth = cv2.distanceTransform((np.asarray(alpha)[box] > 0.5).astype(np.uint8), cv2.DIST_L2, 5)
            b = np.asarray(face)[box]
            skin_b = skin_light(b, depth > reach * min(y1 - y0, x1 - x0), *np.nonzero(over), tint=tint, shade=shade)
            kept[over] *= _skin_likeness(np.log1p(b[over].astype(np.float32)), skin_b, tint, shade)
    near = np.s_[max(y0 - 4, 0):y1 + 4, max(x0 - 4, 0):x1 + 4]  # softened over a pixel: nothing further
    out[near] = cv2.GaussianBlur(out[near], (0, 0), 1.0)
    return out


def _reaching_in(kept: np.ndarray, outside: np.ndarray) -> np.ndarray:
    """(h, w) bool: the connected regions of ``kept`` (h, w) bool that touch ``outside`` (h, w) bool, the
    frame beyond B's mask (and all beyond the array), or lie next to it. Hair and background come into B's
    face from beyond its edge; a patch of A's frame in the band that is not skin but reaches nothing outside
    (a mole, stubble, the shadow of a dimple or a glasses' pad on A's cheek where A's face is wider than B's)
    is A's face, and kept in front it showed as a dark blot on B's cheek."""
    count, labels = cv2.connectedComponents(kept.astype(np.uint8), connectivity=8)
    if count <= 1:
        return kept
    beyond = np.pad(outside.astype(np.uint8), 1, constant_values=1)
    near = cv2.dilate(beyond, np.ones((3, 3), np.uint8))[1:-1, 1:-1] > 0
    touching = np.zeros(count, bool)
    touching[np.unique(labels[near & kept])] = True  # labels of kept pixels: never the background's 0
    return touching[labels]


def blend(face: np.ndarray, frame: np.ndarray, alpha: np.ndarray, *, lighting: float = 1.0,
          tone: float = 1.0, tone_reach: float = 0.5, hair: float = 1.0, plane: np.ndarray | None = None,
          own: np.ndarray | None = None, points: np.ndarray | None = None) -> np.ndarray:
    """The composite as ``composite.mp4`` shows it: B's face matched to A's light and tone at its edge
    (:func:`apply_light` of ``plane``, by ``lighting`` and ``tone`` in [0, 1]; by default the plane
    fitted on this frame, :func:`light_plane`; a drive gives its planes made steady in time,
    :func:`steady_light`), but for ``own`` (h, w) in [0, 1], the share of each pixel that is the
    driver's own already (its mouth interior drawn into B's gap, Rendered.own), which keeps its colour;
    then blended band by band (:func:`multiband`) through the mask less ``hair`` (in [0, 1]) times
    :func:`hair_in_front`, which finds A's eyes and brows by A's landmarks ``points`` (68, 2), when given."""
    light = {"lighting": lighting, "tone": tone, "tone_reach": tone_reach}
    matched = (match_lighting(face, frame, alpha, **light) if plane is None else apply_light(face, alpha, plane, **light))
    if own is not None and np.any(own > 0):
        kept = np.asarray(own, np.float32)[..., None]
        matched = np.round(face * kept + matched * (1 - kept)).astype(np.uint8)
    if hair > 0:
        eyes = brows = None
        if points is not None:
            eyes, brows = (features_of(points, np.shape(alpha), f) for f in (EYES, BROWS))
        alpha = np.asarray(alpha, np.float32) * (1 - hair * hair_in_front(face, frame, alpha, eyes=eyes, brows=brows))
    return multiband(matched, frame, alpha)


def seam(image: np.ndarray, frame: np.ndarray, alpha: np.ndarray, *, reach: int = 4) -> dict | None:
    """The seam of a composite ``image`` over ``frame`` along the edge of the mask ``alpha`` (all
    (h, w[, 3])): ``colour_step`` — |mean colour on a ring ``reach`` px inside the edge minus that
    ``reach`` px outside|, in grey levels (Euclidean over RGB), minus the same in ``frame``;
    ``gradient_ratio`` — the mean squared gradient on the edge's ring (±``reach`` px) in the image
    over the frame's there. None when the mask has no edge. Measured on the mask's box widened beyond
    the widest ring below: the same figures as on the whole frame."""
    face = (np.asarray(alpha) > 0.5).astype(np.uint8)
    box = mask_box(face, 2 * reach + 2)
    if box is None:
        return None
    face, image, frame = face[box], np.asarray(image)[box], np.asarray(frame)[box]
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1, 2 * reach + 1))
    grown, shrunk = cv2.dilate(face, kernel), cv2.erode(face, kernel)
    inner = (shrunk > 0) & (cv2.erode(face, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (4 * reach + 1,) * 2)) == 0)
    outer = (grown == 0) & (cv2.dilate(face, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (4 * reach + 1,) * 2)) > 0)
    ring = (grown > 0) & (shrunk == 0)
    if not (inner.any() and outer.any() and ring.any()):
        return None

    def step(img):
        img = np.asarray(img, np.float64)
        return float(np.linalg.norm(img[inner].mean(axis=0) - img[outer].mean(axis=0)))

    def energy(img):
        grey = cv2.cvtColor(np.asarray(img, np.uint8), cv2.COLOR_RGB2GRAY).astype(np.float64)
        gx, gy = cv2.Sobel(grey, cv2.CV_64F, 1, 0, ksize=3), cv2.Sobel(grey, cv2.CV_64F, 0, 1, ksize=3)
        return float(np.mean((gx ** 2 + gy ** 2)[ring]))

    return {"colour_step": step(image) - step(frame), "gradient_ratio": energy(image) / max(energy(frame), 1e-9)}


#: the grey around the puppet's face shown alone (``puppet.mp4``), and in a render outside its mask
GREY = 128


def alone(face: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """The rendered face shown alone, as ``puppet.mp4`` has it: its colour through its soft mask
    ``alpha`` (h, w) in [0, 1] over plain grey (a render's ``rgb`` is the face's own colour across
    the soft edge, not yet blended with anything: see ``persona.plugins.kinds.Rendered``)."""
    return paste(face, np.full_like(face, GREY), alpha)


def paste(face: np.ndarray, frame: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """The plain composite of uint8 images through the soft mask, ``face α + frame (1 - α)``, uint8 (for
    comparison): the frame itself outside the box of α > 0."""
    a = np.clip(np.asarray(alpha, np.float32), 0, 1)
    out = np.array(frame, np.uint8)
    box = mask_box(a > 0)
    if box is not None:
        a = a[box][..., None]
        out[box] = np.round(np.asarray(face)[box].astype(np.float32) * a + out[box].astype(np.float32) * (1 - a))
    return out


def seams(face: np.ndarray, frame: np.ndarray, alpha: np.ndarray, blended: np.ndarray) -> dict[str, dict | None]:
    """:func:`seam` of the composite as written (``blended``, :func:`blend`'s) and of the plain
    :func:`paste`, keyed "blend" and "paste"."""
    return {"blend": seam(blended, frame, alpha), "paste": seam(paste(face, frame, alpha), frame, alpha)}
