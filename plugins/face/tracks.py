"""Per-frame tracks: filling the frames of a video where no face was found, and steadying the
landmarks a detector finds frame by frame."""

from __future__ import annotations

import cv2
import numpy as np

#: forward-backward error (px) above which a point carried between two frames is not trusted
CARRY_ERROR = 0.25
#: scale (px) of the weight a carried point loses for landing away from the frame's own: exp(-d² / 2 s²)
AGREE = 1.0
_LK = dict(winSize=(15, 15), maxLevel=2, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))


def bridge(values: np.ndarray, found: np.ndarray) -> np.ndarray:
    """Fill frames without a face by linear interpolation in time between the nearest
    frames with one (held constant before the first and after the last).

    values : (n, ...) float — per-frame values (pose, fiducials), anything where not found; a NaN
        value (a fiducial not visible in that frame) is bridged from the frames that have it, and
        stays NaN only when no frame does
    found : (n,) bool
    """
    values = np.asarray(values, dtype=np.float64)
    if not found.any():
        raise ValueError("no frame has a face: nothing to bridge from")
    frames = np.arange(len(values))
    flat = values.reshape(len(values), -1)
    out = np.empty_like(flat)
    for j in range(flat.shape[1]):
        use = found & np.isfinite(flat[:, j])  # a point not visible in a frame is bridged too
        out[:, j] = np.interp(frames, frames[use], flat[use, j]) if use.any() else np.nan
    return out.reshape(values.shape)


def carried(image_from: np.ndarray, image_to: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (k, 2) of one grey image carried to another by pyramidal Lucas-Kanade, and whether each is
    trusted: found both ways, and carried back to within :data:`CARRY_ERROR` px of where it started."""
    p = np.asarray(points, np.float32).reshape(-1, 1, 2)
    q, found, _ = cv2.calcOpticalFlowPyrLK(image_from, image_to, p, None, **_LK)
    back, found_back, _ = cv2.calcOpticalFlowPyrLK(image_to, image_from, q, None, **_LK)
    ok = (found[:, 0] == 1) & (found_back[:, 0] == 1) & (np.linalg.norm((back - p)[:, 0], axis=1) < CARRY_ERROR)
    return q[:, 0].astype(np.float64), ok


def steadied(points: np.ndarray, frames, found: np.ndarray, radius: int) -> np.ndarray:
    """A detector's landmarks (n, k, 2) in consecutive frames (n, H, W, 3) uint8, each frame's points
    averaged with those of the ``radius`` frames on each side, carried into it (:func:`carried`). The
    detector's noise, different in each frame, averages down; the face's motion does not, as each
    neighbour's points are first moved to where its features are in this frame (not in the paper).

    A carried point weighs exp(-Δt² / 2σ²), σ = radius / 2, times exp(-d² / 2 :data:`AGREE`²), d its
    distance from the frame's own: where the flow cannot follow a feature (a lid that shuts, a lip
    corner sliding along the lip's line) the neighbours' points land away from the detector's and lend
    little. The frame's own weighs 1. Frames not ``found`` are left as they are and lend nothing."""
    points = np.asarray(points, np.float64)
    if radius <= 0:
        return points
    grey = {}  # the grey frames within ``radius`` of the one being steadied, each read once

    def image(t):
        if t not in grey:
            grey[t] = cv2.cvtColor(np.asarray(frames[t]), cv2.COLOR_RGB2GRAY)
        return grey[t]

    out = points.copy()
    sigma = radius / 2
    n = len(points)
    for t in np.flatnonzero(found):
        for old in [s for s in grey if s < t - radius]:
            del grey[old]
        total, weight = points[t].copy(), np.ones(len(points[t]))
        for s in range(max(0, t - radius), min(n, t + radius + 1)):
            if s == t or not found[s]:
                continue
            moved, ok = carried(image(s), image(t), points[s])
            d2 = np.sum((moved - points[t]) ** 2, axis=1)
            w = np.where(ok, np.exp(-(s - t) ** 2 / (2 * sigma ** 2) - d2 / (2 * AGREE ** 2)), 0.0)
            total += w[:, None] * np.where(ok[:, None], moved, 0.0)
            weight += w
        out[t] = total / weight[:, None]
    return out
