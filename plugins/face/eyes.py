"""Eyelids that close: B's lids drawn together over the eye in a frame's texture as the target closes it.

Not in the paper. The drive's texture keeps B's neutral geometry (paper §6), with the detail of
the photos whose expression is the target's; a collection rarely has photos with the eyes shut,
so the texture's eyes stay open. The 3D mesh then brings B's lids together, but it squeezes the
open eye between them rather than covering it: a sliver of eye white and iris stays, and the eye
still reads as open (dlib, and a viewer, see it so).

A real eye closes by its lids coming together over it, the upper most of the way. dlib's lid points of a
shut eye stay ``end`` of their open distance apart (the lashes' line; the drivers' blinks measure 0.25-0.46
on HD clips and 0.39-0.49 on a 256² one), so an eye whose lid points are r of their neutral distance apart
shows φ(r) = start · (r - end) / (start - end) of its opening below ``start``, and all of it (φ = r) from
there up: the target's own ratio, what the driver's eye showed. The mesh already squeezes the texture's eye to r;
here the lids — the skin around the eye, inpainted from the lids, with a soft line of lashes the colour of
the eye's darkest tenth hanging from the upper one's edge — are drawn over 1 - φ(r) / r of the eye's opening
(the polygon of its six fiducials at B's neutral, grown by a pixel) in the canonical texture: the upper lid
``meet`` of it from the top, the lower lid the rest from the bottom, so that a shut eye is one line of lashes
where they meet. An eye open by ``start`` or more is left exactly as it was (docs/expression.md).
"""

from __future__ import annotations

import cv2
import numpy as np

from .template import IDX49
from .warp import FACING, gap

#: the lid and its lashes are drawn this many times finer and averaged down, so each texel gets the share
#: of it they cover: a lid that comes down a little further each frame moves smoothly, not in whole-texel
#: steps, and the lash line is a smooth curve, not a stair of single texels (OpenCV antialiases only
#: 8-bit lines, and its filled polygons keep whole-texel steps)
FINER = 8


def _drawn(shape: tuple[int, int], points: np.ndarray, *, line: float = 0) -> np.ndarray:
    """(H, W) float32 in [0, 1]: the share of each texel covered by the polygon ``points`` (x, y), or by
    a line ``line`` texels wide through them if that is not 0."""
    canvas = np.zeros((shape[0] * FINER, shape[1] * FINER), np.uint8)
    fine = [np.round((np.asarray(points, np.float64) + 0.5) * FINER - 0.5).astype(np.int32)]
    if line:
        cv2.polylines(canvas, fine, False, 255, max(1, round(line * FINER)))
    else:
        cv2.fillPoly(canvas, fine, 255)
    return cv2.resize(canvas, shape[::-1], interpolation=cv2.INTER_AREA).astype(np.float32) / 255


#: per eye (the face's right, then left): its six fiducials among the 49 (iBUG 36-41, 42-47) and
#: its facing lid pairs
EYES = ((tuple(IDX49.index(i) for i in range(36, 42)), FACING[0:2]),
        (tuple(IDX49.index(i) for i in range(42, 48)), FACING[2:4]))


def region(neutral: np.ndarray, shape: tuple[int, int], *, grow: int = 3, blur: float = 2.0) -> np.ndarray:
    """(H, W) float32 in [0, 1]: where a texture at the geometry of the fiducials ``neutral`` (49, 2) shows
    the eyes: their openings (the polygons of their six fiducials) grown by ``grow`` texels over the lids and
    feathered by a Gaussian of σ ``blur``, so a texture blended in there has no edge."""
    mask = np.zeros(shape, np.float32)
    for points, _ in EYES:
        polygon = np.asarray(neutral, np.float64)[list(points)]
        if np.isfinite(polygon).all():
            mask = np.maximum(mask, _drawn(shape, polygon))
    if grow:
        mask = cv2.dilate(mask, np.ones((2 * grow + 1, 2 * grow + 1), np.uint8))
    return cv2.GaussianBlur(mask, (0, 0), blur) if blur else mask


#: the distance of a target's lids over B's neutral one below which the eye starts to shut, and at which it is
#: shut: the texture's defaults (``shut_from``, ``shut_at``), which the transfer's brow hold follows too. dlib puts
#: the lids of a shut eye 0.25-0.5 of their open distance apart, the less the sharper the clip; at 0.3 an HD
#: driver's half-shut eye (0.6-0.7) is drawn half open, not as a slit of lashes (docs/expression.md)
SHUT_FROM, SHUT_AT = 0.9, 0.3

#: how far down the opening a shut eye's upper lid comes (its line of lashes there), the lower lid rising the rest:
#: the texture's default (``shut_meet``)
SHUT_MEET = 0.6

#: over how many texels of its travel a lid and its lashes fade in (the texture's default, ``shut_fade``): a lid
#: that has come down a fraction of a texel still lies on the texture's own lash line, and new lashes drawn at full
#: strength over those thickened them into a dark line of eyeliner across an eye barely narrower than B's neutral
SHUT_FADE = 0.5


def opened(target: np.ndarray, neutral: np.ndarray) -> np.ndarray:
    """(2,) how far apart each eye's lids are in the fiducials ``target`` (49, 2), over their distance in
    ``neutral``'s (NaN where either has a NaN)."""
    return np.array([gap(target, pairs) / max(float(gap(neutral, pairs)), 1e-6) for _, pairs in EYES])


def lowered(target: np.ndarray, neutral: np.ndarray, *, start: float = SHUT_FROM, end: float = SHUT_AT) -> np.ndarray:
    """(2,) the share of each eye's opening the upper lid leaves uncovered in the texture, in [0, 1]:
    φ(r) / r, r the distance of the eye's lids in the fiducials ``target`` (49, 2) over ``neutral``'s
    (:func:`opened`; the module's docstring); 1 from ``start`` up, 0 at ``end`` and below."""
    out = np.ones(2)
    for k, r in enumerate(opened(target, neutral)):
        if np.isfinite(r) and r < start:
            out[k] = np.clip(start * (r - end) / (start - end) / max(r, 1e-6), 0.0, 1.0)
    return out


def lower(texture: np.ndarray, neutral: np.ndarray, visible: np.ndarray, *, grow: int = 1,
          margin: int = 6, lashes: float = 2.0, meet: float = SHUT_MEET, fade: float = SHUT_FADE) -> np.ndarray:
    """``texture`` (H, W, 3) at the geometry of the fiducials ``neutral`` (49, 2), each eye k's upper
    lid drawn down so that the share ``visible[k]`` (:func:`lowered`) of its opening stays uncovered,
    its line of lashes ``lashes`` texels wide hanging from its edge. The upper lid comes down ``meet`` of the way
    to the lower lid as the eye shuts and the lower lid rises the rest, so that a shut eye is a line of lashes
    across skin where the lids meet, not the outline of an open eye (as at ``meet`` 1, its lashes on the lower lid's
    line). The lids and lashes fade in over the first ``fade`` texels their edges travel (0: at once), so the
    texture does not change at a step as an eye narrows past ``SHUT_FROM``."""
    if not np.any(visible < 1):
        return texture
    out = np.asarray(texture, np.float32).copy()
    h, w = out.shape[:2]
    for (points, _), v in zip(EYES, visible):
        polygon = np.asarray(neutral, np.float64)[list(points)]  # iBUG order: outer corner, upper lid
        if v >= 1 or not np.isfinite(polygon).all():             # (2), inner corner, lower lid (2)
            continue
        x0, y0 = np.floor(polygon.min(axis=0)).astype(int) - margin
        x1, y1 = np.ceil(polygon.max(axis=0)).astype(int) + margin + 1
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
        if x1 - x0 < 3 or y1 - y0 < 3:
            continue
        polygon = polygon - (x0, y0)
        opening = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.fillPoly(opening, [np.round(polygon).astype(np.int32)], 1)
        if grow:
            opening = cv2.dilate(opening, np.ones((2 * grow + 1, 2 * grow + 1), np.uint8))
        patch = np.clip(out[y0:y1, x0:x1], 0, 255).round().astype(np.uint8)
        skin = cv2.inpaint(patch, opening, 3, cv2.INPAINT_TELEA).astype(np.float32)
        inside = patch[opening > 0].astype(np.float32)
        lash = inside[np.argsort(inside.sum(axis=1))[: max(1, len(inside) // 10)]].mean(axis=0)
        upper, lower_lid = polygon[1:3], polygon[[5, 4]]
        # the lid: from the upper lid's points down to its new edge, (1 - v) · meet of the way to the lower lid;
        # the lower lid rises the rest of the way
        edge = np.vstack([polygon[0], upper + (1 - v) * meet * (lower_lid - upper), polygon[3]])
        lid = _drawn(opening.shape, np.vstack([polygon[:4], edge[::-1]]))
        if grow:  # up over the old lid line too, which is the lid's crease now, not its edge
            lid = cv2.dilate(lid, np.ones((2 * grow + 1, 1), np.uint8)) * opening
        if meet < 1:
            rim = np.vstack([polygon[0], lower_lid + (1 - v) * (1 - meet) * (upper - lower_lid), polygon[3]])
            lid = np.maximum(lid, _drawn(opening.shape, np.vstack([polygon[0], lower_lid, polygon[3], rim[::-1]])))
        hanging = edge + [[0, 0], [0, lashes / 2], [0, lashes / 2], [0, 0]]  # from the lid's edge down
        line = np.clip(cv2.GaussianBlur(_drawn(opening.shape, hanging, line=lashes), (0, 0), 0.5) * 1.5, 0, 1)
        travel = (1 - v) * max(meet, 1 - meet) * float(np.abs(lower_lid - upper)[:, 1].max())  # texels
        strength = min(travel / fade, 1.0) if fade > 0 else 1.0
        weight = strength * cv2.GaussianBlur(np.maximum(lid, line), (0, 0), 0.8)[..., None]  # the lashes too
        line = line[..., None]
        skin = skin * (1 - line) + lash * line
        out[y0:y1, x0:x1] = out[y0:y1, x0:x1] * (1 - weight) + skin * weight
    return out
