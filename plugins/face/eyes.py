"""Eyelids that close: B's eye drawn shut in a frame's texture when the target closes it.

Not in the paper. The drive's texture keeps B's neutral geometry (paper §6), with the detail of
the photos whose expression is the target's; a collection rarely has photos with the eyes shut,
so the texture's eyes stay open. The 3D mesh then brings B's lids together, but it squeezes the
open eye between them rather than covering it: a bright sliver of eye white and iris stays, and the
eye still reads as open (dlib, and a viewer, see it so). Here each eye's opening in the canonical
texture — the polygon of its six fiducials at B's neutral, grown by a pixel — is replaced by the
skin around it (inpainted from the lids) with the line of lashes where the lids meet (a soft dark
line, the colour of the eye's darkest tenth, from corner to corner through the middles of the
facing lid points), with a weight that grows as the target's lids come
together: 0 while that eye is open by at least ``start`` (65 %) of its neutral opening, 1 once it is
open by at most ``end`` (45 %), smooth in between. An open eye is left exactly as it was. The
thresholds are dlib's: on a shut eye its lid points stay 40-50 % of their open distance apart (the
lashes' line), as the drivers' blinks measured (docs/expression.md).
"""

from __future__ import annotations

import cv2
import numpy as np

from .template import IDX49
from .warp import FACING, gap

#: per eye (the face's right, then left): its six fiducials among the 49 (iBUG 36-41, 42-47) and
#: its facing lid pairs
EYES = ((tuple(IDX49.index(i) for i in range(36, 42)), FACING[0:2]),
        (tuple(IDX49.index(i) for i in range(42, 48)), FACING[2:4]))


def closure(target: np.ndarray, neutral: np.ndarray, *, start: float = 0.65, end: float = 0.45) -> np.ndarray:
    """(2,) how shut each eye of ``target`` (49, 2) is, in [0, 1], against ``neutral`` (49, 2): 0 while
    open by at least ``start`` of its neutral opening, 1 at most ``end``, smoothstep in between."""
    out = np.zeros(2)
    for k, (_, pairs) in enumerate(EYES):
        ratio = gap(target, pairs) / max(float(gap(neutral, pairs)), 1e-6)
        if np.isfinite(ratio):
            s = np.clip((start - ratio) / (start - end), 0.0, 1.0)
            out[k] = s * s * (3 - 2 * s)
    return out


def _lash_line(polygon: np.ndarray) -> np.ndarray:
    """(4, 2) where a shut eye's lids meet, from its six points (iBUG order: outer corner, two upper
    lid points, inner corner, two lower): the corners and the middles of the facing pairs."""
    return np.array([polygon[0], (polygon[1] + polygon[5]) / 2, (polygon[2] + polygon[4]) / 2, polygon[3]])


def close(texture: np.ndarray, neutral: np.ndarray, shut: np.ndarray, *, grow: int = 1,
          margin: int = 6) -> np.ndarray:
    """``texture`` (H, W, 3) at the geometry of the fiducials ``neutral`` (49, 2), each eye k blended
    towards the skin around it by ``shut[k]`` in [0, 1] (:func:`closure`)."""
    if not np.any(shut > 0):
        return texture
    out = np.asarray(texture, np.float32).copy()
    h, w = out.shape[:2]
    for (points, _), s in zip(EYES, shut):
        polygon = np.asarray(neutral, np.float64)[list(points)]
        if s <= 0 or not np.isfinite(polygon).all():
            continue
        x0, y0 = np.floor(polygon.min(axis=0)).astype(int) - margin
        x1, y1 = np.ceil(polygon.max(axis=0)).astype(int) + margin + 1
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
        if x1 - x0 < 3 or y1 - y0 < 3:
            continue
        hole = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.fillPoly(hole, [np.round(polygon - (x0, y0)).astype(np.int32)], 1)
        if grow:
            hole = cv2.dilate(hole, np.ones((2 * grow + 1, 2 * grow + 1), np.uint8))
        patch = np.clip(out[y0:y1, x0:x1], 0, 255).round().astype(np.uint8)
        skin = cv2.inpaint(patch, hole, 3, cv2.INPAINT_TELEA).astype(np.float32)
        inner = patch[hole > 0].astype(np.float32)
        lash = inner[np.argsort(inner.sum(axis=1))[: max(1, len(inner) // 10)]].mean(axis=0)
        line = np.zeros(hole.shape, np.float32)
        cv2.polylines(line, [np.round(_lash_line(polygon) - (x0, y0)).astype(np.int32)], False, 1.0, 1, cv2.LINE_AA)
        line = np.clip(cv2.GaussianBlur(line, (0, 0), 0.5) * 1.5, 0, 1)[..., None]
        skin = skin * (1 - line) + lash * line
        weight = s * cv2.GaussianBlur(hole.astype(np.float32), (0, 0), 0.8)[..., None]
        out[y0:y1, x0:x1] = out[y0:y1, x0:x1] * (1 - weight) + skin * weight
    return out
